"""Refining a sequence of any length (``gra-mi refine``; paper Sec. 3.3 "Error Recycling" and the 509-frame rollouts).

Each window of ``window`` (17) frames is sampled from noise with an Euler ODE solver (``steps`` steps, Wan's time
shift ``shift``) and a new seed per window. The first window refines all its frames; every later window starts
``window − handoff`` frames further on, and its first ``handoff`` (5) frames are the previous window's decoded
output, re-encoded as inactive (mask 0) VACE frames — the seed frames the refiner was trained to continue. Two
things make the joins continuous (``Joins``; measured in refine.json and in docs/results/refiner.md): the given latents (the
reference and the seed frames) are pinned to their exact flow path while sampling, the input the refiner saw for
them in training, so what it generates continues them; and the handed-off frames are shown as a cross-fade from
the previous window's version to their re-generation, which hides the VAE round trip of the hand-off. Only one
window is in memory at a time (input frames are read lazily, output frames are written as they come), so memory
stays flat with length.
"""

from __future__ import annotations

import contextlib
import json
import logging
import resource
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from gra_mi.capture.dataset import Capture
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive, require_seed
from gra_mi.core.io import Mp4Stream, atomic_write_text, write_exr, write_png
from gra_mi.core.metrics import display_psnr
from gra_mi.core.progress import progress
from gra_mi.core.provenance import claim_output
from gra_mi.core.runtime import torch_device
from gra_mi.refiner.conditioning import latent_frames, seed_mask
from gra_mi.refiner.dataset import RefinerDataset, video_to_image
from gra_mi.refiner.deflicker import DeflickerConfig, deflicker_frame, filter_window
from gra_mi.refiner.flow import euler_sample
from gra_mi.refiner.model import VideoRefiner
from gra_mi.render.composite import PlatformCompositor, PlatformConfig
from gra_mi.stage.envmap import envmap_to_leds, load_envmap

logger = logging.getLogger(__name__)


def window_starts(frames: int, window: int, handoff: int) -> list[int]:
    """Start frame of each window: 0, then every ``window − handoff`` frames until the sequence is covered."""
    stride = window - handoff
    starts = [0]
    while starts[-1] + window < frames:
        starts.append(starts[-1] + stride)
    return starts


@dataclass
class RefinedFrame:
    index: int
    video: torch.Tensor  # (3, H, W) in [-1, 1]
    window: int


@dataclass(frozen=True)
class Joins:
    """How windows join; every switch off is an ablation (``gra-mi refine --no-…``), all on is the default."""

    handoff: bool = True
    """The next window's first frames are this window's output, as inactive VACE frames (the paper); off: independent windows."""
    pin: bool = True
    """The given latents (reference, handed-off frames) follow their exact flow path while sampling; off: the sampler moves them."""
    crossfade: bool = True
    """The handed-off frames are shown as a cross-fade from this window's version to the next's; off: cut to the new window."""


@dataclass
class RefineConfig:
    steps: int = 20
    """Euler steps per window."""
    shift: float = 3.0
    """Wan time shift of the sampling schedule (1 = none)."""
    denoise: float = 1.0
    """How much of the sampling schedule runs. 1: all of it, from noise (the paper). Below 1: the last part only,
    from the coarse input's latents noised to that point (SDEdit): the refiner keeps the input's layout."""
    mix: float | None = None
    """The fraction of the refiner's change delivered, input + mix·(refined − input), in [0, 1]; default: the
    model's own, chosen when it was trained (refiner.json). 0 delivers the input and samples nothing."""
    seed: int = 0
    """Seed of the first window (each window uses seed + its index)."""
    frames: int | None = None
    """Refine only the first N frames; default: all."""
    joins: Joins = field(default_factory=Joins)
    fuse_lora: bool = True
    """Fold the LoRA into the DiT's weights (about 13 % faster per step for real sizes; measured no less accurate,
    benchmarks/refiner.py); off: keep the adapter apart."""

    def validate(self) -> None:
        require_positive({"steps": self.steps, "shift": self.shift})
        if not 0 < self.denoise <= 1:
            raise GraMiParameterError("denoise", f"must be in (0, 1], got {self.denoise}")
        if self.mix is not None and not 0 <= self.mix <= 1:
            raise GraMiParameterError("mix", f"must be in [0, 1], got {self.mix}")
        require_seed(self.seed)
        if self.frames is not None:
            require_positive({"frames": self.frames})

    def mix_for(self, model: VideoRefiner) -> float:
        """The mix delivered: this config's, or else the model's own (chosen in training)."""
        return model.config.mix if self.mix is None else self.mix


@torch.no_grad()
def rollout(
    model: VideoRefiner,
    dataset: RefinerDataset,
    sequence: str,
    config: RefineConfig | None = None,
    **options,
) -> Iterator[RefinedFrame]:
    """Yield the refined frames of ``sequence`` in order, window by window (``options`` override ``config``'s fields)."""
    config = replace(config or RefineConfig(), **options)
    config.validate()
    steps, shift, seed, frames, joins = config.steps, config.shift, config.seed, config.frames, config.joins
    info = dataset.sequences[sequence]
    total = info.frames if frames is None else frames
    if not 0 < total <= info.frames:
        raise GraMiParameterError("frames", f"sequence '{sequence}' has {info.frames} frames, asked for {total}")
    window, carry = model.config.window, model.config.handoff
    mix = config.mix_for(model)
    if mix == 0:  # the input, delivered as it is: nothing to sample
        for k, start in enumerate(range(0, total, window)):
            coarse = dataset.window(sequence, start, window)["coarse"]
            for i in range(min(window, total - start)):
                yield RefinedFrame(start + i, coarse[:, i].clone(), k)
        return
    carried: torch.Tensor | None = None  # (3, handoff, H, W): the previous window's last frames
    starts = window_starts(total, window, carry)
    for k, start in enumerate(starts):
        win = {key: v.to(model.device) for key, v in dataset.window(sequence, start, window).items()}
        coarse = win["coarse"]
        seeded = 0
        if carried is not None and joins.handoff:
            coarse = torch.cat([carried, coarse[:, carry:]], dim=1)
            seeded = carry
        _, t, h, w = coarse.shape
        control, env_latents = model.conditioning(
            coarse, seed_mask(t, h, w, seeded).to(model.device), win["reference"], win["env"], win["reference_env"]
        )
        env = model.env_tokens(env_latents)
        # The inactive latents of the seed frames are their encoding alone (the VAE is causal in time).
        given = 1 + latent_frames(seeded)  # the reference and the seed frames
        known = model.to_flow(model.channels.inactive(control), control, given)[:, :, :given] if joins.pin else None
        generator = torch.Generator().manual_seed(seed + k)  # a new seed per window
        from_input = model.to_flow(model.base_latents(control, given), control, given)  # the given, then the input's latents
        x = euler_sample(model, (1, 16, *control.shape[2:]), control, env, steps, shift, generator, known, from_input, config.denoise)
        video = model.decode_output(model.from_flow(x, control, given), control, coarse, given)
        if mix < 1:  # the handed-off frames are what was delivered, so the next window continues them
            video = coarse + mix * (video - coarse)
        if k > 0 and joins.crossfade:  # the previous window held its last frames back
            for i in range(min(carry, total - start)):
                alpha = (i + 1) / (carry + 1)
                yield RefinedFrame(start + i, ((1 - alpha) * carried[:, i] + alpha * video[:, i]).cpu(), k)
        first = 0 if k == 0 else carry
        last = t - carry if joins.crossfade and k + 1 < len(starts) else t
        for i in range(first, min(last, total - start)):
            yield RefinedFrame(start + i, video[:, i].cpu(), k)
        carried = video[:, t - carry :]


@torch.no_grad()
def vae_round_trip(model: VideoRefiner, dataset: RefinerDataset, sequence: str, total: int) -> Iterator[tuple[int, torch.Tensor]]:
    """(frame, decode(encode(ground truth))) in windows: what the VAE alone loses, apart from any refiner."""
    window = model.config.window
    for start in range(0, total, window):
        video = model.decode(model.encode(dataset.window(sequence, start, window)["target"][None].to(model.device)))[0]
        for i in range(min(window, total - start)):
            yield start + i, video[:, i].cpu()


def _peak_rss_mib() -> float:
    """This process's peak resident memory: VmHWM (reset by exec, unlike ru_maxrss, which a child inherits)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _subject(coarse: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Where the subject is: pixels lit in the coarse input or the ground truth. One mask for every comparison of a
    frame, so a refined frame is also charged for light it spreads over the background."""
    return (coarse.max(axis=-1) > 0) | (target.max(axis=-1) > 0)


def _capture_compositor(dataset: RefinerDataset, sequence: str, platform: PlatformConfig):
    """(sequence frame, linear image) → the image over its environment on a platform: for data made from a capture,
    whose dataset.json names the capture, the camera and the capture frame of each sequence frame."""

    entry = next(s for s in dataset.meta["sequences"] if s["name"] == sequence)
    path = dataset.folder / "dataset.json"
    for key in ("camera", "capture_frames"):
        if key not in entry:
            raise GraMiInputError(
                path,
                f"--composite: sequence '{sequence}' has no '{key}' (composites need data made from a capture by `gra-mi refiner-data`)",
            )
    capture = Capture.load(dataset.meta.get("source", ""))
    ls = capture.load_scene()
    scale = float(dataset.meta.get("scale", dataset.crop[1] / ls.stage.camera(entry["camera"]).width))
    camera = ls.stage.camera(entry["camera"]).resized(scale)
    entries = {f.frame: f for f in capture.frames}
    compositor = PlatformCompositor(ls.sequence, platform)
    envmaps: dict[str, tuple[np.ndarray, float]] = {}

    def compose(index: int, image: np.ndarray) -> np.ndarray:
        lighting = entries[entry["capture_frames"][index]]
        if lighting.envmap is None:
            raise GraMiInputError(path, f"--composite: capture frame {lighting.frame} is lit by an LED pattern, not an environment")
        if lighting.envmap not in envmaps:
            env = load_envmap(capture.folder / lighting.envmap)
            envmaps[lighting.envmap] = (env, envmap_to_leds(env, ls.stage).scale)
        env, env_scale = envmaps[lighting.envmap]
        return compositor(image, lighting.mesh_frame, camera, env, env_scale, lighting.envmap)

    return compose


def refine_to_folder(
    model_dir: str | Path,
    dataset_dir: str | Path,
    sequence: str,
    out: str | Path,
    config: RefineConfig | None = None,
    write_exr_frames: bool = True,
    vae_round_trip_psnr: bool = True,
    deflicker: DeflickerConfig | None = None,
    composite: PlatformConfig | None = None,
    overwrite: bool = False,
    **options,
) -> dict:
    """Refine one sequence into ``out``: frames (EXR linear + PNG), refined.mp4, comparison.mp4, refine.json; with
    ``deflicker``, also each frame flicker-corrected against its coarse input (:mod:`gra_mi.refiner.deflicker`) in
    ``out/deflickered/`` (EXR + PNG, deflickered.mp4); with ``composite``, ``composite.mp4``: the refined (and
    flicker-corrected) frames over the environment on a platform with the subject's shadow (:mod:`gra_mi.render.composite`;
    data made from a capture only).

    With a ground truth, refine.json has PSNRs of the coarse input, the refined frames and (``vae_round_trip_psnr``) the
    ground truth's own VAE round trip: what the VAE alone loses (with the tiny VAE, most of the gap to the input).
    ``options`` override ``config``'s fields (``steps=6``).
    """

    config = replace(config or RefineConfig(), **options)
    config.validate()
    out = Path(out)
    dataset = RefinerDataset(dataset_dir)
    if sequence not in dataset.sequences:
        raise GraMiParameterError("sequence", f"no sequence '{sequence}' in {dataset.folder} (have {sorted(dataset.sequences)})")
    dataset.check([sequence])
    if deflicker is not None:  # before the folder is claimed and the refiner runs
        filter_window(deflicker, dataset.delivered(sequence, 0, "coarse").shape)
    said = {"sequence": sequence, "refine": asdict(config), "deflicker": asdict(deflicker) if deflicker else None}
    said["composite"] = asdict(composite) if composite else None
    claim_output(out, "refine", {"model": model_dir, "data": dataset_dir}, said, overwrite=overwrite, restart=True)
    compose = _capture_compositor(dataset, sequence, composite) if composite is not None else None
    model = VideoRefiner.load(model_dir).to(torch.device(torch_device())).prepare_for_inference(config.fuse_lora)
    total = dataset.sequences[sequence].frames if config.frames is None else config.frames
    rows, changes, windows_seen, rss, previous = [], [], [], [], None
    t0 = time.perf_counter()
    with _RefineWriter(out, dataset, sequence, deflicker, compose, write_exr_frames) as writer:
        for frame in progress(rollout(model, dataset, sequence, config, frames=total), description=f"refine {sequence}", total=total):
            rows.append(writer.write(frame))
            ch, cw = dataset.crop
            shown = ((frame.video.permute(1, 2, 0).numpy()[:ch, :cw] + 1) / 2).clip(0, 1)
            if previous is not None:
                changes.append(float(np.abs(shown - previous).mean()))
            previous = shown
            windows_seen.append(frame.window)
            rss.append(_peak_rss_mib())
    seconds = time.perf_counter() - t0
    summary = {
        "sequence": sequence,
        "frames": len(rows),
        "windows": len(set(windows_seen)),
        "steps": config.steps,
        "shift": config.shift,
        "seed": config.seed,
        "mix": config.mix_for(model),
        "seconds": seconds,
        "frames_per_second": len(rows) / seconds,
        "joins": asdict(config.joins),
        "fuse_lora": config.fuse_lora,
        "deflicker": None if deflicker is None else asdict(deflicker),
        **_seams(windows_seen, changes, model.config.handoff),
        "peak_rss_mib": rss[-1] if rss else None,
        "rss_mib_after_first_window": next((r for r, w in zip(rss, windows_seen, strict=True) if w > 0), None),
    }
    if dataset.sequences[sequence].has_target:
        for key in ("psnr_coarse", "psnr_refined") + (("psnr_deflickered",) if deflicker is not None else ()):
            summary[key] = float(np.mean([r[key] for r in rows]))
        if vae_round_trip_psnr:
            summary["psnr_vae_round_trip"] = _vae_round_trip_psnr(model, dataset, sequence, total)
    summary["per_frame"] = rows
    atomic_write_text(out / "refine.json", json.dumps(summary, indent=1) + "\n")
    return summary


class _RefineWriter:
    """The refined frames (EXR + PNG), their flicker correction, and the videos (refined, comparison: coarse | refined
    | truth, deflickered, composite), written as the frames come; each frame's PSNRs where there is a truth."""

    def __init__(self, out: Path, dataset: RefinerDataset, sequence: str, deflicker, compose, write_exr_frames: bool):
        self.out, self.dataset, self.sequence, self.deflicker, self.compose = out, dataset, sequence, deflicker, compose
        self.write_exr_frames, self.exposure = write_exr_frames, dataset.exposure
        self.streams = contextlib.ExitStack()

    def __enter__(self):

        fps, out = float(self.dataset.meta.get("fps", 12)), self.out
        self.refined = self.streams.enter_context(Mp4Stream(out / "refined.mp4", fps))
        self.comparison = self.streams.enter_context(Mp4Stream(out / "comparison.mp4", fps))
        deflickered = Mp4Stream(out / "deflickered" / "deflickered.mp4", fps) if self.deflicker is not None else None
        self.deflickered = self.streams.enter_context(deflickered) if deflickered is not None else None
        self.composite = self.streams.enter_context(Mp4Stream(out / "composite.mp4", fps)) if self.compose is not None else None
        return self

    def __exit__(self, *exc):
        return self.streams.__exit__(*exc)

    def _image(self, folder: str, index: int, image: np.ndarray) -> None:

        if self.write_exr_frames or folder == "deflickered":
            write_exr(self.out / folder / f"frame_{index:04d}.exr", image)
            write_png(self.out / folder / f"frame_{index:04d}.png", image, exposure=self.exposure)

    def write(self, frame: RefinedFrame) -> dict:
        dataset, sequence, exposure = self.dataset, self.sequence, self.exposure
        # the whole frame, with the refined subject crop (if the data has one) put back
        image = dataset.delivered(sequence, frame.index, "coarse", video_to_image(frame.video, exposure).permute(1, 2, 0).numpy())
        coarse = dataset.delivered(sequence, frame.index, "coarse")
        self._image("frames", frame.index, image)
        self.refined.append(image, exposure)
        panels, row, delivered = [coarse, image], {"frame": frame.index, "window": frame.window}, image
        if self.deflicker is not None:  # the refiner's own display space: the dataset's exposure
            delivered = deflicker_frame(image, coarse, exposure, self.deflicker)
            self._image("deflickered", frame.index, delivered)
            self.deflickered.append(delivered, exposure)
        if dataset.sequences[sequence].has_target:
            target = dataset.delivered(sequence, frame.index, "target")
            panels.append(target)
            subject = _subject(coarse, target)
            row["psnr_coarse"] = display_psnr(coarse, target, subject)
            row["psnr_refined"] = display_psnr(image, target, subject)
            if self.deflicker is not None:
                row["psnr_deflickered"] = display_psnr(delivered, target, subject)
        self.comparison.append(np.concatenate(panels, axis=1), exposure)
        if self.compose is not None:
            self.composite.append(self.compose(frame.index, delivered), exposure)
        return row


def _seams(windows_seen: list[int], changes: list[float], handoff: int) -> dict:
    """The change into the first frame of a new window, and over its join (into each handed-off frame and the first
    one after them), against the change between the other consecutive frames."""
    firsts = [i for i in range(1, len(windows_seen)) if windows_seen[i] != windows_seen[i - 1]]
    in_join = {i + j for i in firsts for j in range(handoff + 1)}
    seam = [changes[i - 1] for i in firsts]
    join = [changes[i - 1] for i in sorted(in_join) if i < len(windows_seen)]
    inner = [changes[i - 1] for i in range(1, len(windows_seen)) if i not in in_join]
    return {
        "seam_jump": float(np.mean(seam)) if seam else None,
        "join_frame_change": float(np.mean(join)) if join else None,
        "inner_frame_change": float(np.mean(inner)) if inner else None,
    }


def _vae_round_trip_psnr(model: VideoRefiner, dataset: RefinerDataset, sequence: str, total: int) -> float:
    """The ground truth's own VAE round trip against the truth: what the VAE alone loses."""
    psnr = []
    for index, video in vae_round_trip(model, dataset, sequence, total):
        image = dataset.delivered(sequence, index, "target", video_to_image(video, dataset.exposure).permute(1, 2, 0).numpy())
        target = dataset.delivered(sequence, index, "target")
        coarse = dataset.delivered(sequence, index, "coarse")
        psnr.append(display_psnr(image, target, _subject(coarse, target)))
    return float(np.mean(psnr))
