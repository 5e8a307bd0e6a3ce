"""Training, validation and inference of RelightNet on a capture and its fitted maps (``gra-mi train-relightnet``).

Loss (paper Sec. 3.2): L1 between the predicted UV texture rasterised into each camera and the captured image, over
the subject's pixels, multi-view. Each sample is one (frame, training camera) of the capture's training frames.
Validation: held-out cameras on training frames (novel views) and all cameras on the test sequences (held-out
envmaps), with PSNR and SSIM (kornia) for the microfacet render alone and with RelightNet — the ablation.

Runs on CPU or GPU; several processes with ``torchrun`` (DDP: gloo on CPU, NCCL on GPU), each taking its share of
the samples; rank 0 writes checkpoints, logs and plots. Interrupting loses nothing: ``checkpoint.pt`` holds the
model, the optimiser and the step, and a rerun resumes.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from gra_mi.core.errors import GraMiInputError, require_positive
from gra_mi.core.io import atomic_write_text, write_png
from gra_mi.core.training import TrainingLoop, write_training_log
from gra_mi.relightnet.infer import view_inputs
from gra_mi.relightnet.model import RelightNet, RelightNetConfig
from gra_mi.render.bridge import camera_uv_grid, sample_texture, to_torch

logger = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    steps: int = 400
    """Optimisation steps (one sample per step and process)."""
    lr: float = 1e-3
    """Adam learning rate."""
    checkpoint_every: int = 50
    """Steps between checkpoints."""
    log_every: int = 10
    """Steps per row of the training log (the mean loss over them)."""
    seed: int = 0
    """Random seed (initial weights and sample order)."""
    base_channels: int = 16
    """UNet channels at full resolution (doubled per level, capped at 128)."""
    env_height: int = 16
    """Height of the camera-space envmap the network sees (width = 2x)."""
    max_train_views: int | None = None
    """Train on the first N training views only (an overfitting check, or a quick look); default: all."""

    def validate(self) -> None:
        positive = {"steps": self.steps, "checkpoint_every": self.checkpoint_every, "log_every": self.log_every}
        positive |= {"base_channels": self.base_channels, "env_height": self.env_height}
        if self.max_train_views is not None:
            positive["max_train_views"] = self.max_train_views
        require_positive(positive)
        require_positive({"lr": self.lr})


@dataclass
class Sample:
    name: str
    split: str  # "train", "novel view" or "novel lighting"
    features: torch.Tensor  # (1, 15, R, R)
    mask: torch.Tensor  # (1, 1, R, R)
    env: torch.Tensor  # (1, 3, h, 2h)
    grid: torch.Tensor  # (1, H, W, 2)
    pixels: torch.Tensor  # (1, 1, H, W) subject pixels in both the render and the capture
    target: torch.Tensor  # (1, 3, H, W)


def build_samples(
    capture, relighter, env_height: int, device: str = "cpu", splits=("train", "novel view", "novel lighting")
) -> list[Sample]:
    from gra_mi.capture.dataset import load_observation
    from gra_mi.core.progress import progress

    stage = relighter.ls.stage
    jobs = []
    for entry in capture.frames:
        if entry.split == "train":
            jobs += [(entry, c, "train") for c in capture.train_cameras] + [(entry, c, "novel view") for c in capture.eval_cameras]
        else:
            jobs += [(entry, c, "novel lighting") for c in capture.train_cameras[:1] + capture.eval_cameras]
    jobs = [j for j in jobs if j[2] in splits]
    samples = []
    for entry, cam, split in progress(jobs, description="RelightNet samples"):
        intensities = capture.lighting(stage, entry)
        features, mask, env, _ = view_inputs(relighter, entry.frame, cam, intensities, env_height, device)
        relighter.ls.set_frame(entry.frame)
        grid, hit = camera_uv_grid(relighter.ls, stage.camera(cam), device)
        image = load_observation(capture, cam, entry.frame)
        target = to_torch(image[..., :3], device).permute(2, 0, 1)[None].contiguous()
        pixels = hit * to_torch((image[..., 3] > 0.99).astype(np.float32), device)[None, None]
        samples.append(Sample(f"{cam}/frame_{entry.frame:04d}", split, features, mask, env, grid, pixels, target))
    return samples


def masked_l1(image: torch.Tensor, target: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    return (torch.abs(image - target) * pixels).sum() / (3 * pixels.sum()).clamp(min=1)


def image_metrics(image: torch.Tensor, target: torch.Tensor, pixels: torch.Tensor) -> tuple[float, float]:
    """PSNR and SSIM (:mod:`gra_mi.core.metrics`) over the subject's pixels of (1, 3, H, W) images; the pixels outside
    the subject are zeroed in both first, as the SSIM window reaches across the silhouette."""
    from gra_mi.core import metrics

    a, b = ((x * pixels)[0].permute(1, 2, 0).detach().cpu().numpy() for x in (image, target))
    mask = pixels[0, 0].detach().cpu().numpy() > 0.5
    return metrics.psnr(a, b, mask), metrics.ssim(a, b, mask)


# --------------------------------------------------------------------------------------------------------------


def train_relightnet(capture_dir: str | Path, fit_dir: str | Path, out: str | Path, config: TrainConfig) -> Path:
    from gra_mi.core.runtime import ensure_mitsuba, torch_device
    from gra_mi.render.relighter import fitted_relighter

    config.validate()
    loop = TrainingLoop(Path(out), config.steps, config.checkpoint_every, config.log_every, "train RelightNet")
    ensure_mitsuba()
    device = torch_device()
    torch.manual_seed(config.seed)
    out = Path(out)
    capture, relighter = fitted_relighter(capture_dir, fit_dir, out / "cache" if loop.rank == 0 else None)
    samples = build_samples(capture, relighter, config.env_height, device)
    train = [s for s in samples if s.split == "train"]
    if not train:
        raise GraMiInputError(capture.folder / "capture.json", "no training views")
    if config.max_train_views:
        train = train[: config.max_train_views]
    mine = train[loop.rank :: loop.world]  # each process its share

    net_config = RelightNetConfig(
        resolution=relighter.albedo_tex.shape[0], base_channels=config.base_channels, env_height=config.env_height
    )
    model = RelightNet(net_config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    state = loop.resume(device)
    if state is not None:
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
    ddp = loop.parallel(model)
    order = np.random.default_rng(config.seed + loop.rank).permutation(len(mine))

    def state_of() -> dict:
        return {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "config": asdict(config)}

    for step in loop.steps(state_of):
        s = mine[order[step % len(mine)]]
        optimizer.zero_grad(set_to_none=True)
        texture = ddp(s.features, s.env, s.mask)
        loss = masked_l1(sample_texture(texture, s.grid), s.target, s.pixels)
        loss.backward()
        optimizer.step()
        loop.add_loss(float(loss.detach()))  # the log keeps the mean since its last row: one view per step is noisy
    if not loop.finish():
        return out
    log_rows = loop.log_rows
    model.save(out)
    write_training_log(out, ["step", "l1", "seconds"], log_rows, "RelightNet training", "L1 (training view)")
    validate(model.eval(), samples, out)
    return out / "validation.md"


@torch.no_grad()
def validate(model: RelightNet, samples: list[Sample], out: Path) -> dict:
    """Ablation on every split: microfacet only vs + RelightNet (PSNR, SSIM), and an image grid."""
    results: dict[str, dict[str, list]] = {}
    grid_rows = []
    for s in samples:
        coarse = sample_texture(s.features[:, :3], s.grid)
        relit = sample_texture(model(s.features, s.env, s.mask), s.grid)
        entry = results.setdefault(s.split, {"microfacet": [], "relightnet": []})
        entry["microfacet"].append(image_metrics(coarse, s.target, s.pixels))
        entry["relightnet"].append(image_metrics(relit, s.target, s.pixels))
        if s.split != "train" and len(grid_rows) < 4:
            grid_rows.append(torch.cat([s.target * s.pixels, coarse * s.pixels, relit * s.pixels], dim=3)[0].permute(1, 2, 0).cpu().numpy())
    if grid_rows:
        write_png(out / "grid.png", np.concatenate(grid_rows, axis=0), exposure=None)
    summary = {
        split: {
            method: {"psnr": float(np.mean([m[0] for m in v])), "ssim": float(np.mean([m[1] for m in v])), "views": len(v)}
            for method, v in methods.items()
        }
        for split, methods in results.items()
    }
    atomic_write_text(out / "validation.json", json.dumps(summary, indent=1) + "\n")
    lines = [
        "# RelightNet — validation and ablation",
        "",
        "Like the paper's Table 2 rows 1-2: the coarse microfacet render alone, then with RelightNet. LPIPS needs its",
        "weights on disk and is not computed here.",
        "",
        "| split | views | microfacet PSNR | microfacet SSIM | + RelightNet PSNR | + RelightNet SSIM |",
        "|---|---|---|---|---|---|",
    ]
    for split, m in summary.items():
        a, b = m["microfacet"], m["relightnet"]
        lines.append(f"| {split} | {a['views']} | {a['psnr']:.2f} | {a['ssim']:.4f} | {b['psnr']:.2f} | {b['ssim']:.4f} |")
    lines += ["", "Grid (held-out views): ground truth | microfacet | RelightNet", "", "![grid](grid.png)", "", "![loss](loss.png)"]
    atomic_write_text(out / "validation.md", "\n".join(lines) + "\n")
    return summary
