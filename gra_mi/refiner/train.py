"""Training the video refiner (``gra-mi train-refiner``; paper Sec. 3.3 and Supp. "WAN2.1-VACE Finetuning").

One step: draw a window of ``window`` frames (17) from a training sequence; augment as the paper does (10 %: one
frame repeated — a static clip — then simulated pan/zoom with p = 0.9; dynamic clips get pan/zoom with p = 0.05;
bicubic, the same on input and ground truth); with p = 0.4 the first ``handoff`` (5) coarse frames are replaced by
ground-truth frames and marked inactive (mask 0) — the seed frames that teach continuation; encode the target
video (with the neutral-light reference as an extra leading frame that has its own flow target), the VACE control
and the envmap tokens; then latent flow matching (paper Eq. 11, in Wan's convention) with **error recycling**
(paper Eq. 13-15, Stable Video Infinity): residuals of the model's own predictions are kept in a bounded error bank
indexed by noise level and re-injected into the noise (p = 0.01), the clean latent (p = 0.9) and the inactive
conditioning latents (p = 0.9).

Checkpoints (``checkpoint.pt``: trainable weights, optimiser, step, log, error bank) make a rerun resume. Several
processes with ``torchrun`` (DDP; each rank keeps its own error bank). Few-shot identity adaptation is training
from a trained refiner (``init``) on a few clips of another subject.
"""

from __future__ import annotations

import json
import logging
import math
from collections import OrderedDict
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from gra_mi.core.errors import GraMiInputError, require_positive, require_seed
from gra_mi.core.io import atomic_write_text
from gra_mi.core.runtime import torch_device
from gra_mi.core.training import TrainingLoop, write_training_log
from gra_mi.refiner.conditioning import latent_frames, seed_mask
from gra_mi.refiner.config import RefinerConfig
from gra_mi.refiner.dataset import RefinerDataset
from gra_mi.refiner.flow import noisy_latent, recycling_residuals, sampling_sigmas, shift_sigma, velocity_target
from gra_mi.refiner.mix import PSNR_BUDGET, choose_mix, mix_scores, write_mix_report
from gra_mi.refiner.model import VideoRefiner, parameter_counts

logger = logging.getLogger(__name__)


@dataclass
class RefinerTrainConfig:
    steps: int = 200
    """Optimisation steps."""
    lr: float = 1e-3
    """AdamW learning rate."""
    grad_accumulation: int = 1
    """Windows per optimisation step."""
    seed: int = 0
    """Random seed."""
    seed_frames_prob: float = 0.4
    static_clip_prob: float = 0.1
    static_motion_prob: float = 0.9
    dynamic_motion_prob: float = 0.05
    noise_error_prob: float = 0.01
    latent_error_prob: float = 0.9
    inactive_error_prob: float = 0.9
    train_base: bool = False
    """Train every DiT weight too (pretraining a prior: pipelines/pretrain_tiny_refiner.py), not only LoRA, VACE and
    the envmap layers (the paper's fine-tuning)."""
    error_recycling: bool = True
    """Error recycling (paper Eq. 13-15); off: plain flow matching (an ablation)."""
    bank_grid: int = 50
    """Noise levels the error bank is indexed by (nearest of this many shifted sampling steps)."""
    bank_per_level: int = 32
    """Residuals kept per noise level and bank (random replacement once full): memory is bounded."""
    train_shift: float = 1.0
    """σ = shift(u), u ~ U[0, 1]; 1 = the paper's uniform s."""
    sample_shift: float = 3.0
    checkpoint_every: int = 50
    """Steps between checkpoints."""
    log_every: int = 10
    """Steps per row of the training log."""
    latent_cache: int = 256
    """Encoded windows kept in memory (only un-augmented ones repeat)."""
    choose_mix: bool = True
    """After training, choose on the data's selection sequences how much of the refiner's change to deliver (table:
    OUT/mix.md); off, or without selection sequences: all of it (mix 1)."""
    selection_steps: int = 20
    """Euler steps of the selection rollouts (use what `gra-mi refine --steps` will)."""

    def validate(self) -> None:
        require_positive({"steps": self.steps, "lr": self.lr, "grad_accumulation": self.grad_accumulation})
        require_positive({"bank_grid": self.bank_grid, "bank_per_level": self.bank_per_level})
        require_positive({"checkpoint_every": self.checkpoint_every, "log_every": self.log_every})
        require_positive({"train_shift": self.train_shift, "sample_shift": self.sample_shift, "selection_steps": self.selection_steps})
        require_seed(self.seed)


# --------------------------------------------------------------------------------------------------------------
# Error bank
# --------------------------------------------------------------------------------------------------------------


class ErrorBank:
    """Residuals by noise-level index; at most ``per_level`` per index, stored in float16 on the CPU."""

    def __init__(self, levels: int, per_level: int, dtype: torch.dtype = torch.float16):
        self.levels, self.per_level, self.dtype = levels, per_level, dtype
        self.entries: dict[int, list[torch.Tensor]] = {}

    def add(self, level: int, residual: torch.Tensor, rng: np.random.Generator) -> None:
        items = self.entries.setdefault(int(level), [])
        residual = residual.detach().to("cpu", self.dtype).clone()
        if len(items) < self.per_level:
            items.append(residual)
        else:
            items[int(rng.integers(len(items)))] = residual

    def sample(self, level: int, shape: torch.Size, rng: np.random.Generator) -> torch.Tensor | None:
        """A residual from the nearest filled level with the right shape, or None."""
        filled = sorted((abs(k - level), k) for k, v in self.entries.items() if v and v[0].shape == shape)
        if not filled:
            return None
        items = self.entries[filled[0][1]]
        return items[int(rng.integers(len(items)))].float()

    def __len__(self) -> int:
        return sum(len(v) for v in self.entries.values())

    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for v in self.entries.values() for t in v)

    def max_nbytes(self, shape: torch.Size) -> int:
        return self.levels * self.per_level * math.prod(shape) * torch.finfo(self.dtype).bits // 8

    def state(self) -> dict:
        return {"levels": self.levels, "per_level": self.per_level, "entries": self.entries}

    @classmethod
    def from_state(cls, state: dict) -> ErrorBank:
        bank = cls(state["levels"], state["per_level"])
        bank.entries = state["entries"]
        return bank


# --------------------------------------------------------------------------------------------------------------
# Windows, augmentation, conditioning
# --------------------------------------------------------------------------------------------------------------


def pan_zoom(video: torch.Tensor, zoom: float, shift: tuple[float, float]) -> torch.Tensor:
    """(3, T, H, W) in [-1, 1]: a camera move growing linearly over the clip (bicubic; black enters at the edges)."""
    c, t, h, w = video.shape
    a = torch.linspace(0, 1, t)
    scale = 1 / (1 + (zoom - 1) * a)
    theta = torch.zeros(t, 2, 3)
    theta[:, 0, 0], theta[:, 1, 1] = scale, scale
    theta[:, 0, 2], theta[:, 1, 2] = shift[0] * a, shift[1] * a
    grid = F.affine_grid(theta, (t, c, h, w), align_corners=False)
    moved = F.grid_sample(video.permute(1, 0, 2, 3) + 1, grid, mode="bicubic", padding_mode="zeros", align_corners=False) - 1
    return moved.clamp(-1, 1).permute(1, 0, 2, 3)


def augment(window: dict[str, torch.Tensor], config: RefinerTrainConfig, rng: np.random.Generator) -> tuple[dict, str]:
    """The paper's augmentations; returns the window and what was done ('' = nothing)."""
    out, what = dict(window), []
    t = window["coarse"].shape[1]
    motion_prob = config.dynamic_motion_prob
    if rng.random() < config.static_clip_prob:
        k = int(rng.integers(t))
        for key in ("coarse", "target", "env"):
            out[key] = out[key][:, k : k + 1].expand(-1, t, -1, -1).contiguous()
        motion_prob = config.static_motion_prob
        what.append("static")
    if rng.random() < motion_prob:
        zoom = float(rng.uniform(0.85, 1.2))
        shift = (float(rng.uniform(-0.15, 0.15)), float(rng.uniform(-0.1, 0.1)))
        for key in ("coarse", "target"):
            out[key] = pan_zoom(out[key], zoom, shift)
        what.append("pan/zoom")
    return out, "+".join(what)


@dataclass
class Encoded:
    clean: torch.Tensor  # (1, 16, 1 + F', h, w): reference latent + target latents
    control: torch.Tensor  # (1, 96, 1 + F', h, w)
    env_latents: torch.Tensor  # (1, 16, 1 + F', h_e, w_e)
    given: int  # leading latent frames that are given: the reference, and the seed frames' latents


def encode_window(model: VideoRefiner, window: dict, seeded: int) -> Encoded:
    coarse = window["coarse"]
    if seeded:
        coarse = torch.cat([window["target"][:, :seeded], coarse[:, seeded:]], dim=1)
    _, t, h, w = coarse.shape
    control, env_latents = model.conditioning(
        coarse, seed_mask(t, h, w, seeded), window["reference"], window["env"], window["reference_env"]
    )
    clean = torch.cat([model.encode(window["reference"][None, :, None]), model.encode(window["target"][None])], dim=2)
    return Encoded(clean, control, env_latents, 1 + latent_frames(seeded))


# --------------------------------------------------------------------------------------------------------------
# One flow-matching step with error recycling
# --------------------------------------------------------------------------------------------------------------


@dataclass
class StepResult:
    loss: torch.Tensor
    level: int
    injected: str


def flow_matching_loss(
    model,
    enc: Encoded,
    config: RefinerTrainConfig,
    rng: np.random.Generator,
    generator: torch.Generator,
    banks: tuple[ErrorBank, ErrorBank] | None,
    sigma: float | None = None,
    noise: torch.Tensor | None = None,
) -> StepResult:
    """Paper Eq. 15 (Eq. 11 without recycling) in Wan's convention; updates the error banks with the residuals."""
    core = model.module if hasattr(model, "module") else model
    grid = sampling_sigmas(config.bank_grid, config.sample_shift)[:-1]
    if sigma is None:
        sigma = float(shift_sigma(float(rng.random()), config.train_shift))
    level = int(torch.argmin((grid - sigma).abs()))
    control = enc.control
    clean = core.to_flow(enc.clean, control, enc.given)  # the latents, or the residual over the coarse input (tiny)
    if noise is None:
        noise = torch.randn(clean.shape, generator=generator)
    noise = noise.to(clean.device)
    injected = []
    if banks is not None:
        noise_bank, data_bank = banks
        if rng.random() < config.noise_error_prob and (e := noise_bank.sample(level, clean.shape, rng)) is not None:
            noise = noise + e.to(clean.device)
            injected.append("noise")
        e1 = data_bank.sample(level, clean.shape, rng)
        if e1 is not None:
            e1 = e1.to(clean.device)
            if rng.random() < config.latent_error_prob:
                clean_in = clean + e1
                injected.append("latent")
            else:
                clean_in = clean
            if rng.random() < config.inactive_error_prob:
                control = control.clone()
                # the inactive latents (not the reference frame); the bank holds flow-space residuals
                core.channels.inactive(control)[:, :, 1:] += e1[:, :, 1:] * (core.residual_scale or 1.0)
                injected.append("inactive")
        else:
            clean_in = clean
    else:
        clean_in = clean
    s = torch.tensor([sigma], dtype=torch.float32, device=clean.device)
    x = noisy_latent(clean_in, noise, s.view(1, 1, 1, 1, 1))
    target = velocity_target(clean, noise)  # the paper's v^rcy = z₁ − z̃₀: the *unperturbed* data, the perturbed noise
    env = core.env_tokens(enc.env_latents)
    predicted = model(x, s, control, env)
    loss = F.mse_loss(predicted, target)
    if banks is not None:
        e_noise, e_data = recycling_residuals(predicted.detach(), target, sigma)
        banks[0].add(level, e_noise, rng)
        banks[1].add(level, e_data, rng)
    return StepResult(loss, level, "+".join(injected))


# --------------------------------------------------------------------------------------------------------------
# Training loop
# --------------------------------------------------------------------------------------------------------------


def _windows(dataset: RefinerDataset, window: int, split: str) -> list[tuple[str, int]]:
    items = []
    for name in dataset.names(split):
        info = dataset.sequences[name]
        if not info.has_target:
            continue
        items += [(name, s) for s in range(max(info.frames - window + 1, 1))]
    return items


def train_refiner(
    dataset_dir: str | Path,
    out: str | Path,
    config: RefinerTrainConfig,
    model_config: RefinerConfig | None = None,
    init: str | Path | None = None,
    overwrite: bool = False,
) -> Path:
    """Train (or, with ``init``, adapt) a refiner; writes weights, logs, a loss plot and ``train.json``."""

    config.validate()
    model_config = model_config or RefinerConfig()
    model_config.validate()  # before the dataset is read
    loop = TrainingLoop(Path(out), config.steps, config.checkpoint_every, config.log_every, "train refiner")
    device = torch.device(torch_device())
    out = Path(out)
    dataset = RefinerDataset(dataset_dir)
    dataset.check()
    loop.claim("train-refiner", {"data": dataset_dir, "init": init}, {"train": asdict(config), "model": asdict(model_config)}, overwrite)
    model = VideoRefiner.load(init) if init is not None else VideoRefiner(model_config)
    if config.train_base:
        model.transformer.requires_grad_(True)
    model.to(device)
    windows = WindowSource(
        dataset, model, config, device, _training_windows(dataset, model.config.window, dataset_dir)[loop.rank :: loop.world]
    )
    optimizer = torch.optim.AdamW(model.trainable_parameters(), lr=config.lr, weight_decay=0.0)
    banks = (ErrorBank(config.bank_grid, config.bank_per_level), ErrorBank(config.bank_grid, config.bank_per_level))
    state = loop.resume(device)
    if state is not None:
        model.load_state_dict(state["trainable"], strict=False)
        optimizer.load_state_dict(state["optimizer"])
        if state.get("banks") is not None:
            banks = tuple(ErrorBank.from_state(b) for b in state["banks"])
    ddp = loop.parallel(model)

    def state_of() -> dict:
        return {
            "trainable": model.trainable_state(), "optimizer": optimizer.state_dict(), "config": asdict(config),
            "banks": [b.state() for b in banks] if config.error_recycling else None,
        }  # fmt: skip

    good = _finite_snapshot(model, loop.start)  # the weights a divergence falls back to
    for step in loop.steps(state_of, row_extra=lambda: (len(banks[1]),)):
        optimizer.zero_grad(set_to_none=True)
        losses = [_accumulate(ddp, windows, config, banks, loop.rank, step, micro) for micro in range(config.grad_accumulation)]
        norm = float(torch.nn.utils.clip_grad_norm_(model.trainable_parameters(), 1.0))
        if loop.diverged(step, max(losses) + norm, "the flow-matching loss or its gradient"):
            break
        if step % config.checkpoint_every == 0:
            good = _finite_snapshot(model, step) or good  # these weights gave a finite loss and gradient
        for value in losses:
            loop.add_loss(value)
        optimizer.step()
    if loop.divergence is None and not all(bool(torch.isfinite(p).all()) for p in model.trainable_parameters()):
        loop.mark_diverged(config.steps, "the weights after the last step")
    if loop.divergence is not None:
        model.load_state_dict(good[1], strict=False)  # never keep non-finite weights (the checkpoint holds these too)
        loop.divergence["kept_step"] = good[0]
    if not loop.finish():
        return out
    return _write_outputs(out, model, dataset, config, loop, banks, {"dataset": str(dataset_dir), "init": str(init) if init else None})


def _training_windows(dataset: RefinerDataset, window: int, dataset_dir) -> list[tuple[str, int]]:
    items = _windows(dataset, window, "train")
    if not items:
        raise GraMiInputError(Path(dataset_dir) / "dataset.json", "no training sequence with targets")
    short = [n for n in dataset.names("train") if dataset.sequences[n].frames < window]
    if short:
        logger.warning("sequences shorter than the %d-frame window repeat their last frame: %s", window, short)
    return items


class WindowSource:
    """This process's training windows, drawn, augmented and encoded; un-augmented encodings are kept (up to
    ``config.latent_cache``), since only those repeat."""

    def __init__(self, dataset: RefinerDataset, model: VideoRefiner, config: RefinerTrainConfig, device, items: list[tuple[str, int]]):
        self.dataset, self.model, self.config, self.device, self.items = dataset, model, config, device, items
        self.cache: OrderedDict = OrderedDict()

    def draw(self, rng: np.random.Generator) -> Encoded:
        name, begin = self.items[int(rng.integers(len(self.items)))]
        raw = self.dataset.window(name, begin, self.model.config.window)
        win, augmented = augment(raw, self.config, rng)
        seeded = self.model.config.handoff if rng.random() < self.config.seed_frames_prob else 0
        key = (name, begin, seeded)
        if not augmented and key in self.cache:
            self.cache.move_to_end(key)
            return self.cache[key]
        enc = encode_window(self.model, {k: v.to(self.device) for k, v in win.items()}, seeded)
        if not augmented:
            self.cache[key] = enc
            while len(self.cache) > self.config.latent_cache:
                self.cache.popitem(last=False)
        return enc


def _accumulate(ddp, windows: WindowSource, config: RefinerTrainConfig, banks, rank: int, step: int, micro: int) -> float:
    """One window's flow-matching loss, its gradient accumulated; the draw depends on the step only (resumable)."""
    rng = np.random.default_rng([config.seed, rank, step, micro])
    generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
    enc = windows.draw(rng)
    result = flow_matching_loss(ddp, enc, config, rng, generator, banks if config.error_recycling else None)
    (result.loss / config.grad_accumulation).backward()
    return float(result.loss.detach())


def _write_outputs(out: Path, model: VideoRefiner, dataset: RefinerDataset, config: RefinerTrainConfig, loop, banks, inputs: dict) -> Path:
    """The mix chosen on the selection sequences, the weights, the training log and ``train.json``."""
    log_rows = loop.log_rows
    mix = _choose_mix(model, dataset, config, out)
    model.save(out)
    write_training_log(
        out, ["step", "flow_matching_loss", "seconds", "error_bank_residuals"], log_rows, "Video refiner training",
        "flow-matching loss (MSE, latent)",
    )  # fmt: skip
    summary = {
        "steps": config.steps, **inputs, "parameters": parameter_counts(model),
        "final_loss": log_rows[-1][1] if log_rows else None, "first_loss": log_rows[0][1] if log_rows else None,
        "error_bank": {"residuals": len(banks[1]), "bytes": banks[0].nbytes() + banks[1].nbytes()},
        "mix": mix, "diverged": loop.divergence, "config": asdict(config),
    }  # fmt: skip
    atomic_write_text(out / "train.json", json.dumps(summary, indent=1) + "\n")
    return out


def _finite_snapshot(model: VideoRefiner, step: int) -> tuple[int, dict] | None:
    """(step, a copy of the trainable weights) if they are all finite, else None."""
    state = {k: v.clone() for k, v in model.trainable_state().items()}
    return (step, state) if all(bool(torch.isfinite(v).all()) for v in state.values()) else None


def _choose_mix(model: VideoRefiner, dataset: RefinerDataset, config: RefinerTrainConfig, out: Path) -> dict:
    """Set ``model.config.mix`` from the selection sequences (:mod:`gra_mi.refiner.mix`); what train.json records."""

    sequences = [n for n in dataset.names("selection") if dataset.sequences[n].has_target]
    if not (config.choose_mix and sequences):
        model.config.mix = 1.0
        why = "switched off" if not config.choose_mix else "the data has no selection sequence"
        logger.info("refiner mix 1 (%s): the refiner's output is delivered as it is", why)
        return {"chosen": 1.0, "why": why}
    model.eval()
    scores = mix_scores(model, dataset, sequences, config.selection_steps, config.sample_shift, config.seed)
    chosen = choose_mix(scores, PSNR_BUDGET)
    model.config.mix = chosen.mix
    logger.info("refiner mix %g, chosen on %s (mix.md)", chosen.mix, ", ".join(sequences))
    return write_mix_report(out, scores, chosen, sequences, PSNR_BUDGET)


@torch.no_grad()
def validation_loss(
    model: VideoRefiner, dataset: RefinerDataset, split: str = "train", sigmas=(0.2, 0.5, 0.8), max_windows: int = 8, seed: int = 0
) -> float:
    """Mean flow-matching loss over fixed windows, noise levels and noise (no recycling): comparable across models."""
    config = RefinerTrainConfig()
    items = _windows(dataset, model.config.window, split)
    items = items[:: max(1, len(items) // max_windows)][:max_windows]
    if not items:
        raise GraMiInputError(dataset.folder / "dataset.json", f"no '{split}' sequence with targets")
    losses = []
    for i, (name, begin) in enumerate(items):
        win = {k: v.to(model.device) for k, v in dataset.window(name, begin, model.config.window).items()}
        enc = encode_window(model, win, 0)
        for sigma in sigmas:
            g = torch.Generator().manual_seed(seed + 1000 * i + int(sigma * 100))
            noise = torch.randn(enc.clean.shape, generator=g)
            result = flow_matching_loss(model, enc, config, np.random.default_rng(0), g, None, sigma=sigma, noise=noise)
            losses.append(float(result.loss))
    return float(np.mean(losses))


@torch.no_grad()
def mean_estimate_error(model: VideoRefiner, dataset: RefinerDataset, split: str = "test", max_windows: int = 8, seed: int = 0) -> dict:
    """How much the refiner knows about its target beyond its input, in latent space over fixed windows.

    ``estimate``: the mean squared error of its clean-latent estimate from pure noise (σ = 1, where the flow's
    estimate is the target's conditional mean) against the target's latents; ``input``: the same for the input's own
    latents (a refiner that changes nothing); ``ratio`` = estimate / input. Below 1 the refiner predicts part of what
    the input misses; at or above 1 it predicts nothing that carries over, and its samples, whose error is the mean's
    plus their spread, cost PSNR. The reference frame is left out (it is given)."""
    items = _windows(dataset, model.config.window, split)
    items = items[:: max(1, len(items) // max_windows)][:max_windows]
    if not items:
        raise GraMiInputError(dataset.folder / "dataset.json", f"no '{split}' sequence with targets")
    estimate, unchanged = [], []
    for i, (name, begin) in enumerate(items):
        win = {k: v.to(model.device) for k, v in dataset.window(name, begin, model.config.window).items()}
        enc = encode_window(model, win, 0)
        noise = torch.randn(enc.clean.shape, generator=torch.Generator().manual_seed(seed + i)).to(model.device)
        one = torch.ones(1, device=model.device)
        flow = noise - model(noise, one, enc.control, model.env_tokens(enc.env_latents))
        estimate.append(float(((model.from_flow(flow, enc.control, enc.given) - enc.clean)[:, :, 1:] ** 2).mean()))
        unchanged.append(float(((model.base_latents(enc.control, enc.given) - enc.clean)[:, :, 1:] ** 2).mean()))
    e, u = float(np.mean(estimate)), float(np.mean(unchanged))
    return {"estimate": e, "input": u, "ratio": e / u, "windows": len(items)}
