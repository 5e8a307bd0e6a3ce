"""Training, validation and inference of RelightNet on a capture and its fitted maps (``gra-mi train-relightnet``).

Loss (paper Sec. 3.2): L1 between the predicted UV texture rasterised into each camera and the captured image, over
the subject's pixels, multi-view, compared through a display's tone curve (:func:`normalised_l1`). Each sample is one (frame, training camera) of the capture's training frames.
Validation: held-out cameras on training frames (novel views) and all cameras on the test sequences (held-out
envmaps), with PSNR and SSIM (kornia) for the microfacet render alone and with RelightNet — the ablation.

Runs on CPU or GPU; several processes with ``torchrun`` (DDP: gloo on CPU, NCCL on GPU), each taking its share of
the samples; rank 0 writes checkpoints, logs and plots. Interrupting loses nothing: ``checkpoint.pt`` holds the
model, the optimiser and the step, and a rerun resumes.
"""

from __future__ import annotations

import json
import logging
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from gra_mi.capture.dataset import load_observation
from gra_mi.capture.reflectance import static_pose
from gra_mi.core import metrics
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive, require_seed
from gra_mi.core.io import atomic_path, atomic_write_text, pyplot, save_figure, write_png
from gra_mi.core.limits import DRIVE_BYTES, require_memory
from gra_mi.core.progress import progress
from gra_mi.core.runtime import torch_device
from gra_mi.core.training import TrainingLoop, write_training_log
from gra_mi.relightnet.data import HELD_OUT, TEST_LIGHTING, Sample, stack
from gra_mi.relightnet.infer import view_inputs
from gra_mi.relightnet.lightings import TrainingViews, synthesized_views
from gra_mi.relightnet.model import RelightNet, RelightNetConfig, exposure
from gra_mi.render.bridge import camera_uv_grid, sample_texture, to_torch
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.transport import LightTransport

logger = logging.getLogger(__name__)

ENV_BYTES_PER_PIXEL = 512  # an envmap of the encoder: baked from the LEDs, its tokens, their positions and Adam's state


@dataclass
class TrainConfig:
    steps: int = 1500
    """Optimisation steps (one batch per step and process)."""
    lr: float = 2e-3
    """Peak AdamW learning rate (linear warm-up over the first 5 % of the steps, then cosine decay to 1/20)."""
    weight_decay: float = 1e-4
    """AdamW weight decay."""
    batch_size: int = 2
    """Training views per step and process."""
    env_dropout: float = 0.1
    """Probability that a training view sees a black envmap, so the gain cannot rest on recognising the few training
    lightings alone."""
    validate_every: int = 100
    """Steps between validations on the fixed selection views; the weights that validate best are the ones saved."""
    selection_views: int = 8
    """Held-out views per held-out split used to select the weights (reported apart from the rest)."""
    checkpoint_every: int = 100
    """Steps between checkpoints."""
    log_every: int = 10
    """Steps per row of the training log (the mean loss over them)."""
    seed: int = 0
    """Random seed (initial weights and sample order)."""
    base_channels: int = 16
    """UNet channels at its top level (doubled per level, capped at 128)."""
    patch: int | None = None
    """Space-to-depth factor: the UNet's top level runs at the UV resolution / patch (1, 2 or 4); default: the factor
    that puts it at 128²."""
    env_height: int = 16
    """Height of the camera-space envmap the network sees (width = 2x)."""
    max_train_views: int | None = None
    """Train on the first N training views only (an overfitting check, or a quick look); default: all."""
    training_lightings: int | None = None
    """Train on the lit frames of this many of the capture's training lightings only (envmaps or patterns, evenly
    spaced; every uniformly lit frame is kept): how the gain grows with the lightings seen; default: all."""
    held_out_views: int = 64
    """Held-out views per held-out split (evenly spaced) that validation and the report score."""
    synthesized_lightings: int = 0
    """On a static capture with OLATs: also train on this many procedural envmaps (skies, rooms) mapped onto the
    LEDs, each target the sum of the capture's training OLATs (docs/evaluation.md); 0: the capture's own only."""
    synthesized_validation: int = 16
    """With --synthesized-lightings: held-out procedural envmaps (another seed range), truth from the OLATs."""
    transport: LightTransport = field(default_factory=LightTransport)
    loss: str = "display"
    """How the L1 compares images (also the score that selects the weights): "display" through a display's tone curve,
    as the metrics see them (an error in a shadow weighs what it looks like); "linear": radiance itself."""

    def validate(self) -> None:
        self.transport.validate(fixed=True)
        positive = {"steps": self.steps, "checkpoint_every": self.checkpoint_every, "log_every": self.log_every}
        positive |= {"base_channels": self.base_channels, "env_height": self.env_height, "batch_size": self.batch_size}
        positive |= {"validate_every": self.validate_every, "selection_views": self.selection_views}
        positive |= {"held_out_views": self.held_out_views, "synthesized_validation": self.synthesized_validation}
        if self.synthesized_lightings < 0:
            raise GraMiParameterError("synthesized_lightings", f"must be >= 0, got {self.synthesized_lightings}")
        require_memory(
            "synthesized_lightings", self.synthesized_lightings * DRIVE_BYTES, f"{self.synthesized_lightings:,} lightings' LED drives"
        )
        for name in ("max_train_views", "training_lightings"):
            if getattr(self, name) is not None:
                positive[name] = getattr(self, name)
        require_positive(positive)
        require_positive({"lr": self.lr})
        require_seed(self.seed)
        for name, value in (("weight_decay", self.weight_decay), ("env_dropout", self.env_dropout)):
            if not (0 <= value < 1):
                raise GraMiParameterError(name, f"must be in [0, 1), got {value}")
        if self.loss not in LOSS_ENCODINGS:
            raise GraMiParameterError("loss", f"must be one of {', '.join(LOSS_ENCODINGS)}, got {self.loss!r}")
        if self.patch not in (None, 1, 2, 4):
            raise GraMiParameterError("patch", f"must be 1, 2 or 4, got {self.patch}")
        if self.env_height % 4:
            raise GraMiParameterError("env_height", f"must be a multiple of 4, got {self.env_height}")
        require_memory(
            "env_height", ENV_BYTES_PER_PIXEL * 2 * self.env_height**2, f"a {2 * self.env_height}x{self.env_height} envmap's encoder"
        )
        widest = RelightNetConfig.max_channels
        if self.base_channels > widest:  # channels double per level up to the widest: more at the top is never used
            raise GraMiParameterError("base_channels", f"must be at most {widest} (the UNet's widest level), got {self.base_channels}")

    def learning_rate(self, step: int) -> float:
        warmup = max(1, self.steps // 20)
        if step < warmup:
            return self.lr * (step + 1) / warmup
        t = (step - warmup) / max(1, self.steps - warmup)
        return self.lr * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * min(t, 1.0))))


def held_training_bytes() -> int:
    """Training views are held in memory up to a quarter of the machine's memory (at least 2 GiB); above it they are
    made when drawn (a UV render each time)."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX
        total = 0
    return max(2 << 30, total // 4)


def view_jobs(capture, splits=("train", *HELD_OUT)) -> list[tuple]:
    """(frame entry, camera, split) of every view of the capture in ``splits``: training frames from the training
    cameras (and from the held-out ones: novel views), test frames from one training and every held-out camera."""
    jobs = []
    for entry in capture.frames:
        if entry.split == "train":
            jobs += [(entry, c, "train") for c in capture.train_cameras] + [(entry, c, "novel view") for c in capture.eval_cameras]
        else:
            split = "novel lighting (OLAT)" if entry.kind == "pattern" else "novel lighting (envmap)"
            jobs += [(entry, c, split) for c in capture.train_cameras[:1] + capture.eval_cameras]
    return [j for j in jobs if j[2] in splits and capture.has_image(j[1], j[0])]


@dataclass
class CapturedView:
    """Makes the :class:`Sample` of one captured view; each (pose, camera)'s UV grid is traced once."""

    capture: object
    relighter: object
    env_height: int
    device: str = "cpu"
    grids: dict = field(default_factory=dict)

    def __call__(self, job: tuple) -> Sample:
        entry, cam, split = job
        stage = self.relighter.ls.stage
        intensities = self.capture.lighting(stage, entry)
        features, mask, env, _ = view_inputs(self.relighter, entry.mesh_frame, cam, intensities, self.env_height, self.device)
        if (entry.mesh_frame, cam) not in self.grids:
            self.relighter.ls.set_frame(entry.mesh_frame)
            self.grids[entry.mesh_frame, cam] = camera_uv_grid(self.relighter.ls, stage.camera(cam), self.device)
        grid, hit = self.grids[entry.mesh_frame, cam]
        image = load_observation(self.capture, cam, entry.frame)
        target = to_torch(image[..., :3], self.device).permute(2, 0, 1)[None].contiguous()
        pixels = hit * to_torch((image[..., 3] > 0.99).astype(np.float32), self.device)[None, None]
        return Sample(f"{cam}/frame_{entry.frame:04d}", split, features, mask, env, grid, pixels, target)


def build_samples(capture, relighter, env_height: int, device: str = "cpu", splits=("train", *HELD_OUT)) -> list[Sample]:
    make = CapturedView(capture, relighter, env_height, device)
    return [make(job) for job in progress(view_jobs(capture, splits), description="RelightNet samples")]


def mark_selection(samples: list[Sample], per_split: int, scored_cameras: tuple[str, ...] = ()) -> None:
    """Mark up to ``per_split`` evenly spaced views of each held-out split, and at most half of them, as the
    selection views: the other half at least stays unseen by every choice training makes. Under the test lighting
    they come from the training cameras only: the held-out cameras' test frames (``scored_cameras``) are what
    `gra-mi eval` scores, and no choice may be made on them."""
    for split in HELD_OUT:
        views = [s for s in samples if s.split == split and not (split in TEST_LIGHTING and s.camera in scored_cameras)]
        count = min(per_split, max(1, len(views) // 2))
        for k in np.unique(np.linspace(0, len(views) - 1, count).round().astype(int)) if views else []:
            views[k].selection = True


LOSS_ENCODINGS = ("display", "linear")
DISPLAY_GAMMA = 1 / 2.2
DISPLAY_FLOOR = 1e-3  # keeps the tone curve's slope finite at black (in units of the exposure)


def normalised_l1(
    image: torch.Tensor, target: torch.Tensor, pixels: torch.Tensor, scale: torch.Tensor, encoding: str = "display"
) -> torch.Tensor:
    """L1 over the subject's pixels in units of each view's exposure (:func:`exposure`: every view weighs the same,
    whether lit by a dim OLAT or a bright sky), compared as ``encoding``: "display" through a display's tone curve
    (x^(1/2.2), unclipped), as the metrics see the images (PSNR, SSIM and ꟻLIP compare sRGB display values), so an error
    in a shadow weighs what it looks like; "linear": radiance itself."""
    a, b = image / scale, target / scale
    if encoding == "display":
        a, b = ((x.clamp(min=0) + DISPLAY_FLOOR) ** DISPLAY_GAMMA for x in (a, b))
    return (torch.abs(a - b) * pixels).sum() / (3 * pixels.sum()).clamp(min=1)


def image_metrics(image: torch.Tensor, target: torch.Tensor, pixels: torch.Tensor) -> tuple[float, float, float]:
    """Display PSNR, SSIM and brightness error (:func:`gra_mi.core.metrics.compare`) over the subject's pixels of
    (1, 3, H, W) images."""

    a, b = ((x * pixels)[0].permute(1, 2, 0).detach().cpu().numpy() for x in (image, target))
    scores = metrics.compare(a, b, pixels[0, 0].detach().cpu().numpy() > 0.5)
    return scores["psnr"], scores["ssim"], scores["brightness"]


# --------------------------------------------------------------------------------------------------------------


def train_relightnet(capture_dir: str | Path, fit_dir: str | Path, out: str | Path, config: TrainConfig, overwrite: bool = False) -> Path:
    """Train RelightNet into ``out``; a rerun with the same inputs and config resumes (``steps`` may grow), a folder
    made by another run is refused (``overwrite``: start over)."""
    from gra_mi.fit.fitted import fitted_relighter

    config.validate()
    loop = TrainingLoop(Path(out), config.steps, config.checkpoint_every, config.log_every, "train RelightNet")
    ensure_mitsuba()
    device = torch_device()
    torch.manual_seed(config.seed)
    out = Path(out)
    capture, relighter = fitted_relighter(capture_dir, fit_dir, out / "cache" if loop.rank == 0 else None, config.transport)
    train_jobs = of_lightings(view_jobs(capture, ("train",)), config.training_lightings)  # refused before any output
    if config.synthesized_lightings:
        static_pose(capture)  # a moving capture has no reflectance field: refused before the folder is claimed
    loop.claim("train-relightnet", {"capture": capture_dir, "fit": fit_dir}, config, overwrite)
    train, held_out = _views(capture, relighter, train_jobs, config, device, out / "cache" if loop.rank == 0 else None)
    train_views = train.spread(config.held_out_views)  # made once: the output gain and the report's training row
    samples = lit(train_views) + held_out  # what the report scores
    mine = train.share(loop.rank, loop.world)  # each process its share
    net_config = RelightNetConfig(
        resolution=relighter.albedo_tex.shape[0],
        base_channels=config.base_channels,
        env_height=config.env_height,
        patch=config.patch,
        input_bounces=config.transport.bounces,
    )
    model = RelightNet(net_config).to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    selector = Selector(model, [s for s in samples if s.selection], loop, config.loss)
    _resume(loop, model, optimizer, selector, config, device)
    if selector.best is None and loop.rank == 0:
        selector(0)  # the untrained network is the microfacet render: the baseline every later step must beat
        if selector.best is None:
            raise GraMiInputError(Path(fit_dir), "the microfacet render of the selection views is not finite (non-finite maps or images?)")
    ddp = loop.parallel(model)

    def state_of() -> dict:
        return {
            "model": model.state_dict(), "optimizer": optimizer.state_dict(), "config": asdict(config),
            "best": selector.best, "validation": selector.rows,
        }  # fmt: skip

    for step in loop.steps(state_of):
        if not _train_step(step, config, loop, ddp, optimizer, mine, device):
            break  # diverged: the weights that validated best (step 0 at worst: the microfacet render) are kept
        if loop.rank == 0 and ((step + 1) % config.validate_every == 0 or step + 1 == config.steps):
            model.eval()
            selector(step + 1)
            model.train()
    if loop.divergence is not None:
        model.load_state_dict(selector.best["model"])  # what the last checkpoint keeps, too: no non-finite weights
    if not loop.finish():
        return out
    return _write_outputs(out, model, selector, train_views, samples, loop)


def _views(
    capture, relighter, train_jobs: list, config: TrainConfig, device: str, cache: Path | None
) -> tuple[TrainingViews, list[Sample]]:
    """The training views (held, or made when drawn when they would not fit :func:`held_training_bytes` or lightings are
    synthesized) and the held-out views (at most ``held_out_views`` per split, the selection views marked)."""
    make = CapturedView(capture, relighter, config.env_height, device)
    jobs = view_jobs(capture, HELD_OUT)
    jobs = [j for split in HELD_OUT for j in _evenly([j for j in jobs if j[2] == split], config.held_out_views)]
    held_out = [make(j) for j in progress(jobs, description="RelightNet held-out views")]
    held_out = lit(held_out)
    train_jobs = train_jobs[: config.max_train_views or None]
    if not train_jobs:
        raise GraMiInputError(capture.folder / "capture.json", "no training views")
    synth = None
    if config.synthesized_lightings:
        synth, validation = synthesized_views(capture, relighter, config, device, cache)
        held_out += validation
    mark_selection(held_out, config.selection_views, tuple(capture.eval_cameras))
    r = relighter.albedo_tex.shape[0]
    if synth is None and len(train_jobs) * 4 * 20 * r * r <= held_training_bytes():
        return TrainingViews([make(j) for j in progress(train_jobs, description="RelightNet samples")], make), held_out
    return TrainingViews(train_jobs, make, synth), held_out


def lighting_of(entry) -> tuple | None:
    """What lit a frame: (kind, file), None for a uniformly lit one."""
    return None if entry.kind == "uniform" else (entry.kind, entry.envmap or entry.pattern)


def of_lightings(jobs: list[tuple], count: int | None) -> list[tuple]:
    """The jobs of uniformly lit frames and of ``count`` of the other lightings (evenly spaced in capture order; all
    jobs when ``count`` is None). Refused when the capture has fewer lightings than asked for."""
    if not count:
        return jobs
    lightings = [k for k in dict.fromkeys(lighting_of(entry) for entry, _, _ in jobs) if k is not None]
    if len(lightings) < count:
        raise GraMiParameterError("training_lightings", f"the capture has {len(lightings)} training lightings, asked for {count}")
    kept = set(_evenly(lightings, count))
    return [job for job in jobs if lighting_of(job[0]) in kept | {None}]


def lit(samples: list[Sample]) -> list[Sample]:
    """The views whose truth has light on the subject: an OLAT behind the subject leaves a camera nothing to score
    (black against black, an infinite PSNR)."""
    dark = [s for s in samples if not float((s.target * s.pixels).sum()) > 0]
    if dark:
        logger.info("%d views show no light on the subject and are not scored (%s, ...)", len(dark), dark[0].name)
    return [s for s in samples if float((s.target * s.pixels).sum()) > 0]


def _evenly(items: list, count: int) -> list:
    if len(items) <= count:
        return items
    return [items[k] for k in np.unique(np.linspace(0, len(items) - 1, count).round().astype(int))]


@dataclass
class Selector:
    """Validation on the selection views, and the weights that scored best so far (step 0, the microfacet render,
    included): a step whose score or weights are not finite marks the run diverged and is never kept."""

    model: RelightNet
    views: list[Sample]
    loop: TrainingLoop
    encoding: str = "display"  # the training loss's
    best: dict | None = None
    rows: list[dict] = field(default_factory=list)

    def __call__(self, step: int) -> None:
        row = selection_scores(self.model, self.views, step, self.encoding)
        # A capture without held-out views has nothing to select on: the latest weights are kept.
        score = row["score"] if self.views else -float(step)
        if not (np.isfinite(score) and all_finite(self.model)):
            self.loop.mark_diverged(step, "the weights" if np.isfinite(score) else "the validation score")
            return  # never kept, nor logged (validation.json's "diverged" says where)
        self.rows.append(row)
        if self.best is None or score < self.best["score"]:
            self.best = {"step": step, "score": score, "model": {k: v.detach().clone() for k, v in self.model.state_dict().items()}}


def _resume(loop: TrainingLoop, model, optimizer, selector: Selector, config: TrainConfig, device) -> None:
    """Carry on from ``checkpoint.pt`` if there is one: the same options (more steps extend a run) or a named refusal."""
    state = loop.resume(device)
    if state is None:
        return
    before = {k: v for k, v in state.get("config", {}).items() if k != "steps"}
    now = {k: v for k, v in asdict(config).items() if k != "steps"}
    if before != now:
        changed = sorted(k for k in now.keys() | before.keys() if before.get(k) != now.get(k))
        raise GraMiInputError(
            loop.checkpoint, f"was written with other training options ({', '.join(changed)}); use another --out, or delete it"
        )
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    selector.best, selector.rows = state["best"], state["validation"]


def _train_step(step: int, config: TrainConfig, loop: TrainingLoop, ddp, optimizer, mine: list[Sample], device) -> bool:
    """One optimisation step on this process's views; False (and no update) when the loss is not finite anywhere.
    The schedule and sample order are functions of the step: a resumed run sees what an uninterrupted one does."""
    for group in optimizer.param_groups:
        group["lr"] = config.learning_rate(step)
    order = np.random.default_rng([config.seed, loop.rank, step]).choice(len(mine), min(config.batch_size, len(mine)), replace=False)
    batch = stack([mine[k] for k in order])
    seed = (config.seed * 1_000_003 + step) * 64 + loop.rank
    drop = torch.rand(len(order), generator=torch.Generator().manual_seed(seed)) < config.env_dropout
    optimizer.zero_grad(set_to_none=True)
    texture = ddp(batch.features, batch.env, batch.mask, drop.to(device))
    scale = exposure(batch.features[:, :3], batch.mask).detach()
    loss = normalised_l1(sample_texture(texture, batch.grid, batch.mask), batch.target, batch.pixels, scale, config.loss)
    loss.backward()
    if loop.diverged(step, float(loss.detach())):
        return False
    optimizer.step()
    loop.add_loss(float(loss.detach()))  # the log keeps the mean since its last row: one batch per step is noisy
    return True


def _write_outputs(out: Path, model: RelightNet, selector: Selector, train: list[Sample], samples: list[Sample], loop) -> Path:
    """The kept weights with their output gain, the logs, the validation curve and the ablation report."""
    best = selector.best
    model.load_state_dict(best["model"])
    # Step 0 is the microfacet render itself, shipped as is (its brightness is the fit's calibration).
    model.config.output_gain = calibrate_output_gain(model.eval(), train) if best["step"] > 0 else 1.0
    logger.info("RelightNet output gain (the training views' total light): %.4f", model.config.output_gain)
    model.save(out)
    write_training_log(out, ["step", "l1", "seconds"], loop.log_rows, "RelightNet training", "L1 / exposure (training views)")
    write_validation_curve(out, selector.rows, best["step"])
    validate(model.eval(), samples, out, best["step"], selector.rows, loop.divergence)
    return out / "validation.md"


def all_finite(model: torch.nn.Module) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


@torch.no_grad()
def calibrate_output_gain(model: RelightNet, views: list[Sample]) -> float:
    """The gain that gives the network's renders of ``views`` their true total light (each view in units of its own
    exposure, so every view weighs the same): L1 fits medians, and the light the coarse render misses is one-sided."""
    model.config.output_gain = 1.0
    rendered = truth = 0.0
    for s in views:
        scale = float(exposure(s.features[:, :3], s.mask))
        image = sample_texture(model(s.features, s.env, s.mask), s.grid, s.mask)
        rendered += float((image * s.pixels).sum()) / scale
        truth += float((s.target * s.pixels).sum()) / scale
    return float(np.clip(truth / rendered, 0.5, 2.0)) if rendered > 0 else 1.0


@torch.no_grad()
def selection_scores(model: RelightNet, views: list[Sample], step: int, encoding: str = "display") -> dict:
    """The training loss on the selection views (:func:`normalised_l1`; their mean: the score that picks the weights,
    lower is better) and each held-out split's mean PSNR, for the validation curve."""
    per_split: dict[str, list] = {}
    l1s = []
    for s in views:
        image = sample_texture(model(s.features, s.env, s.mask), s.grid, s.mask)
        l1s.append(float(normalised_l1(image, s.target, s.pixels, exposure(s.features[:, :3], s.mask), encoding)))
        per_split.setdefault(s.split, []).append(image_metrics(image, s.target, s.pixels)[0])
    return {
        "step": step,
        "score": float(np.mean(l1s)) if l1s else float("nan"),
        "psnr": {k: float(np.mean(v)) for k, v in per_split.items()},
    }


def subject_crop(image: torch.Tensor, pixels: torch.Tensor, margin: int = 4) -> np.ndarray:
    """(1, 3, H, W) → (h, w, 3): the box around the subject's pixels (the grid shows the subject, not the stage)."""
    rows, cols = np.nonzero(pixels[0, 0].cpu().numpy() > 0.5)
    array = image[0].permute(1, 2, 0).cpu().numpy()
    if rows.size == 0:
        return array
    r0, c0 = max(rows.min() - margin, 0), max(cols.min() - margin, 0)
    return array[r0 : rows.max() + margin + 1, c0 : cols.max() + margin + 1]


def write_validation_curve(out: Path, rows: list[dict], best_step: int) -> None:
    """``validation_log.csv`` and ``validation.png``: each held-out split's PSNR on the selection views against the
    training step (step 0 is the microfacet render), the chosen step marked."""
    import csv

    splits = sorted({k for r in rows for k in r["psnr"]})
    with atomic_path(out / "validation_log.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["step", "selection_l1", *[f"psnr {k}" for k in splits]])
        writer.writerows([[r["step"], f"{r['score']:.6f}", *[f"{r['psnr'].get(k, float('nan')):.3f}" for k in splits]] for r in rows])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    steps = [r["step"] for r in rows]
    for k in splits:
        line = ax.plot(steps, [r["psnr"].get(k, np.nan) for r in rows], marker=".", label=k)[0]
        ax.axhline(rows[0]["psnr"].get(k, np.nan), color=line.get_color(), linestyle=":", linewidth=1)
    ax.axvline(best_step, color="k", linestyle="--", linewidth=1, label=f"kept: step {best_step}")
    ax.set_xlabel("training step (dotted: microfacet render, step 0)")
    ax.set_ylabel("PSNR on the selection views (dB)")
    ax.legend(fontsize=7)
    ax.set_title("RelightNet validation")
    fig.tight_layout()
    save_figure(fig, out / "validation.png")


@torch.no_grad()
def validate(
    model: RelightNet,
    samples: list[Sample],
    out: Path,
    best_step: int = 0,
    validation_rows: list | None = None,
    divergence: dict | None = None,
) -> dict:
    """Ablation on every split: microfacet only vs + RelightNet (PSNR, SSIM, brightness error), views that chose the
    weights reported apart from the rest, and an image grid."""
    results: dict[str, dict[str, list]] = {}
    grid_rows = []
    for s in samples:
        coarse = sample_texture(s.features[:, :3], s.grid, s.mask)
        relit = sample_texture(model(s.features, s.env, s.mask), s.grid, s.mask)
        split = f"{s.split} (selection)" if s.selection else s.split
        entry = results.setdefault(split, {"microfacet": [], "relightnet": []})
        entry["microfacet"].append(image_metrics(coarse, s.target, s.pixels))
        entry["relightnet"].append(image_metrics(relit, s.target, s.pixels))
        if s.split != "train" and not s.selection and len(grid_rows) < 4:
            grid_rows.append([subject_crop(x * s.pixels, s.pixels) for x in (s.target, coarse, relit)])
    if grid_rows:
        height = max(row[0].shape[0] for row in grid_rows)
        padded = [np.concatenate([np.pad(x, ((0, height - x.shape[0]), (0, 0), (0, 0))) for x in row], axis=1) for row in grid_rows]
        width = max(row.shape[1] for row in padded)
        write_png(out / "grid.png", np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in padded]), exposure=None)
    summary = {
        split: {
            method: {
                "psnr": float(np.mean([m[0] for m in v])),
                "ssim": float(np.mean([m[1] for m in v])),
                "brightness": float(np.mean([m[2] for m in v])),
                "views": len(v),
            }  # fmt: skip
            for method, v in methods.items()
        }
        for split, methods in sorted(results.items(), key=lambda kv: (kv[0] != "train", "selection" in kv[0], kv[0]))
    }
    report = {
        "splits": summary, "kept_step": best_step, "output_gain": model.config.output_gain,
        "validation": validation_rows or [], "diverged": divergence,
    }  # fmt: skip
    atomic_write_text(out / "validation.json", json.dumps(report, indent=1) + "\n")
    kept = "the untrained network, i.e. the microfacet render itself" if best_step == 0 else f"step {best_step}"
    lines = [
        "# RelightNet — validation and ablation",
        "",
        "Like the paper's Table 2 rows 1-2: the coarse microfacet render alone, then with RelightNet, on the subject's",
        "pixels (display PSNR, SSIM, and the brightness error Σ render / Σ truth − 1 beside them: docs/conventions.md).",
        "Held-out views that chose the weights (the selection views) are reported apart; the other held-out rows are",
        f"views training never looked at. Weights kept: {kept}, the best selection score (exposure-normalised L1) among",
        "every validation, step 0 included, so RelightNet never ships worse than its input on the selection views;",
        f"then one output gain, {model.config.output_gain:.4f}, gives the training views their total light (L1 learns medians).",
        "",
        "| split | views | microfacet PSNR | SSIM | brightness | + RelightNet PSNR | SSIM | brightness |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for split, m in summary.items():
        a, b = m["microfacet"], m["relightnet"]
        lines.append(
            f"| {split} | {a['views']} | {a['psnr']:.2f} | {a['ssim']:.4f} | {100 * a['brightness']:+.1f} % "
            f"| {b['psnr']:.2f} | {b['ssim']:.4f} | {100 * b['brightness']:+.1f} % |"
        )
    if divergence is not None:
        lines += [
            "",
            f"**Training diverged at step {divergence['step']}** ({divergence['what']} became non-finite) and stopped there;",
            f"the weights kept are those of step {best_step}, the best finite validation. Lower `--lr` and rerun with `--overwrite`.",
        ]
    lines += ["", "Validation during training:", "", "![validation](validation.png)", ""]
    lines += ["Grid (held-out views): ground truth | microfacet | RelightNet", "", "![grid](grid.png)", "", "![loss](loss.png)"]
    atomic_write_text(out / "validation.md", "\n".join(lines) + "\n")
    return summary
