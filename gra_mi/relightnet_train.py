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
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from gra_mi.bridge import NUM_NORMAL_FRAMES, camera_uv_grid, sample_texture, to_torch, uv_features
from gra_mi.errors import GraMiInputError
from gra_mi.imageio import atomic_path, atomic_write_text, write_png
from gra_mi.relightnet import RelightNet, RelightNetConfig
from gra_mi.training import init_distributed, write_training_log

logger = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    steps: int = 400
    """Optimisation steps (one sample per step and process)."""
    lr: float = 1e-3
    checkpoint_every: int = 50
    log_every: int = 10
    seed: int = 0
    base_channels: int = 16
    env_height: int = 16
    max_train_views: int | None = None
    """Use only the first N training views (an overfitting check, or a quick look)."""


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


def view_inputs(relighter, frame: int, camera: str, intensities: np.ndarray, env_height: int, device: str = "cpu", point_light=None):
    """RelightNet's inputs for one view: (features, mask, camera-space env, shading)."""
    from gra_mi.envmap import leds_to_envmap, to_camera_space
    from gra_mi.point_light import conditioning_pattern
    from gra_mi.uvspace import TexelGeometry

    stage = relighter.ls.stage
    shading, geom = relighter.shade(frame, camera, intensities, point_light)
    seq = relighter.ls.sequence
    normals = [np.array(geom.normal).T]  # frame t: already interpolated for the shading
    normals += [
        np.array(TexelGeometry.from_frame(relighter.atlas, seq.vertices[max(frame - k, 0)], seq.normals[max(frame - k, 0)]).normal).T
        for k in range(1, NUM_NORMAL_FRAMES)
    ]
    features, mask = uv_features(relighter.atlas, shading.radiance, normals, shading.view_dir, device)
    lights = intensities
    if point_light is not None:  # the paper's conditioning stands for the point light in the envmap
        lights = intensities + conditioning_pattern(stage, relighter.ls.scene, point_light) * stage.led_distances()[:, None] ** 2
    env = to_camera_space(leds_to_envmap(stage, lights, env_height), stage.camera(camera), supersample=1)
    return features, mask, to_torch(env, device).permute(2, 0, 1)[None].contiguous(), shading


def build_samples(
    capture, relighter, env_height: int, device: str = "cpu", splits=("train", "novel view", "novel lighting")
) -> list[Sample]:
    from gra_mi.capture import load_observation
    from gra_mi.progress import progress

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
        if relighter.ls.frame != entry.frame:
            relighter.ls.set_frame(entry.frame)
        grid, hit = camera_uv_grid(relighter.ls.scene, stage.camera(cam), device)
        image = load_observation(capture, cam, entry.frame)
        target = to_torch(image[..., :3], device).permute(2, 0, 1)[None].contiguous()
        pixels = hit * to_torch((image[..., 3] > 0.99).astype(np.float32), device)[None, None]
        samples.append(Sample(f"{cam}/frame_{entry.frame:04d}", split, features, mask, env, grid, pixels, target))
    return samples


def masked_l1(image: torch.Tensor, target: torch.Tensor, pixels: torch.Tensor) -> torch.Tensor:
    return (torch.abs(image - target) * pixels).sum() / (3 * pixels.sum()).clamp(min=1)


def image_metrics(image: torch.Tensor, target: torch.Tensor, pixels: torch.Tensor) -> tuple[float, float]:
    """PSNR (peak = the target's maximum over the subject) and SSIM over the subject's pixels."""
    import kornia

    peak = float((target * pixels).max().clamp(min=1e-6))
    a, b = (image * pixels) / peak, (target * pixels) / peak
    mse = float(((a - b) ** 2).sum() / (3 * pixels.sum()).clamp(min=1))
    psnr = float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)
    ssim_map = kornia.metrics.ssim(a.clamp(0, 1), b.clamp(0, 1), window_size=7).mean(dim=1, keepdim=True)
    ssim = float((ssim_map * pixels).sum() / pixels.sum().clamp(min=1))
    return psnr, ssim


# --------------------------------------------------------------------------------------------------------------


def train_relightnet(
    capture_dir: str | Path, fit_dir: str | Path, out: str | Path, config: TrainConfig, variant: str | None = None
) -> Path:
    from gra_mi.plugins import register_plugins
    from gra_mi.relight import fitted_relighter
    from gra_mi.variant import choose_variant, torch_device

    rank, world = init_distributed()
    choose_variant(variant)
    register_plugins()
    device = torch_device()
    torch.manual_seed(config.seed)
    out = Path(out)
    capture, relighter = fitted_relighter(capture_dir, fit_dir, out / "cache" if rank == 0 else None)
    samples = build_samples(capture, relighter, config.env_height, device)
    train = [s for s in samples if s.split == "train"]
    if not train:
        raise GraMiInputError(capture.folder / "capture.json", "no training views")
    if config.max_train_views:
        train = train[: config.max_train_views]
    mine = train[rank::world]  # each process its share

    net_config = RelightNetConfig(
        resolution=relighter.albedo_tex.shape[0], base_channels=config.base_channels, env_height=config.env_height
    )
    model = RelightNet(net_config).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    start_step, log_rows = 0, []
    checkpoint = out / "checkpoint.pt"
    if checkpoint.is_file():
        state = torch.load(checkpoint, map_location=device, weights_only=False)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start_step, log_rows = state["step"], state["log"]
        logger.info("resuming from step %d", start_step)
    ddp = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    rng = np.random.default_rng(config.seed + rank)
    order = rng.permutation(len(mine))
    t0 = time.perf_counter()
    window: list[float] = []  # losses since the last log row: the log keeps their mean (one view per step is noisy)

    def save_checkpoint(step: int) -> None:
        if rank != 0:
            return
        with atomic_path(checkpoint) as tmp:
            torch.save(
                {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step, "log": log_rows, "config": asdict(config)},
                tmp,
            )

    from gra_mi.progress import progress

    for step in progress(range(start_step, config.steps), description="train RelightNet") if rank == 0 else range(start_step, config.steps):
        s = mine[order[step % len(mine)]]
        optimizer.zero_grad(set_to_none=True)
        texture = ddp(s.features, s.env, s.mask)
        loss = masked_l1(sample_texture(texture, s.grid), s.target, s.pixels)
        loss.backward()
        optimizer.step()
        window.append(float(loss.detach()))
        if (step + 1) % config.log_every == 0 or step + 1 == config.steps:
            log_rows.append((step + 1, float(np.mean(window)), time.perf_counter() - t0))
            window = []
        if (step + 1) % config.checkpoint_every == 0:
            save_checkpoint(step + 1)
    save_checkpoint(config.steps)
    if world > 1:
        torch.distributed.barrier()
    if rank != 0:
        return out
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


def relightnet_texture(model: RelightNet, relighter, frame: int, camera: str, intensities: np.ndarray, point_light=None):
    """Inference: RelightNet's UV texture (R, R, 3) for one view, and the one-bounce shading it started from."""
    device = next(model.parameters()).device
    features, mask, env, shading = view_inputs(relighter, frame, camera, intensities, model.config.env_height, str(device), point_light)
    with torch.no_grad():
        texture = model(features, env, mask)
    return texture[0].permute(1, 2, 0).cpu().numpy(), shading
