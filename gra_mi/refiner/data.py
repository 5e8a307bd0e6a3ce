"""The video refiner's training data from the pipeline: a capture's sequences rendered by its fit (and RelightNet),
the captured images as targets, each sequence cut to a fixed box around its subject (:func:`dataset_from_capture`).
The dataset's format and reader are :mod:`gra_mi.refiner.dataset`; synthetic sequences for tests
:mod:`gra_mi.refiner.synthetic`."""

from __future__ import annotations

import logging
import math
import shutil
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from gra_mi.capture.dataset import load_observation
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.io import atomic_path
from gra_mi.core.limits import require_memory_for
from gra_mi.core.progress import progress
from gra_mi.core.provenance import claim_output
from gra_mi.core.runtime import torch_device
from gra_mi.core.shard import Shard
from gra_mi.refiner.dataset import RefinerDataset, crop_box, write_dataset_json, write_sequence
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.envmap import leds_to_envmap, to_camera_space

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------------------------
# From the pipeline: a capture, its fit and RelightNet
# --------------------------------------------------------------------------------------------------------------


# The subject crop. At the evaluation scale the subject spans only some 50 × 55 pixels of a demo frame, which a
# VAE that shrinks images 4× or 8× keeps as a few latent cells. The refiner therefore works on a fixed box around
# the subject (one per sequence: no crop motion to flicker), cut from the full-resolution images and magnified
# ``zoom``× relative to the evaluation scale; its output goes back into the frame as a residual (what it changed,
# area-averaged back down), so a refiner that changes nothing returns its input exactly.


def _mask_extent(masks: np.ndarray) -> tuple[int, int, int, int]:
    ys, xs = np.nonzero(np.asarray(masks).any(axis=0))
    if len(ys) == 0:  # no subject in view: the whole frame
        return 0, 0, masks.shape[1], masks.shape[2]
    return int(ys.min()), int(xs.min()), int(ys.max()) + 1, int(xs.max()) + 1


def subject_boxes(masks: list[np.ndarray], zoom: float, margin: float = 0.08) -> tuple[tuple[int, int], list[tuple[int, int, int, int]]]:
    """One crop size for several sequences and each one's box: ``masks`` (N, fh, fw) per sequence at the evaluation
    scale → ((h, w) of the crops, multiples of 16; [(y0, x0, y1, x1)] at the evaluation scale, centred on the union of
    the sequence's masks, grown by ``margin`` of the tallest subject each side; a box may reach past the frame).

    With zoom 1, 2, 4, 8 or 16 the boxes are exactly crop size / zoom, so each crop pixel is a whole fraction of a frame
    pixel (the tiny VAE's 4 × 4 blocks then sit inside frame pixels at zoom 4)."""
    extents = [_mask_extent(m) for m in masks]
    tallest = max(max(y1 - y0, x1 - x0) for y0, x0, y1, x1 in extents)
    need = (
        max(y1 - y0 for y0, _, y1, _ in extents) + 2 * margin * tallest,
        max(x1 - x0 for _, x0, _, x1 in extents) + 2 * margin * tallest,
    )
    if zoom == int(zoom) and 16 % int(zoom) == 0:
        step = 16 // int(zoom)
        box = tuple(int(math.ceil(n / step) * step) for n in need)
        size = (box[0] * int(zoom), box[1] * int(zoom))
    else:
        size = tuple(int(math.ceil(n * zoom / 16) * 16) for n in need)
        box = tuple(int(math.ceil(n / zoom)) for n in size)
    boxes = []
    for y0, x0, y1, x1 in extents:
        top, left = int(round((y0 + y1 - box[0]) / 2)), int(round((x0 + x1 - box[1]) / 2))
        boxes.append((top, left, top + box[0], left + box[1]))
    return size, boxes


def _resize_pad(image: np.ndarray, scale: float) -> tuple[np.ndarray, tuple[int, int]]:
    from gra_mi.refiner.conditioning import pad_to_multiple

    t = torch.from_numpy(np.ascontiguousarray(image[..., :3])).permute(2, 0, 1)[None]
    if scale != 1.0:
        t = F.interpolate(t, scale_factor=scale, mode="area")
    h, w = t.shape[-2:]
    ph, pw = pad_to_multiple(h, w)
    t = F.pad(t, (0, pw - w, 0, ph - h))
    return t[0].permute(1, 2, 0).numpy(), (h, w)


@dataclass(kw_only=True)
class CaptureSequencesConfig:
    """How a capture becomes the refiner's sequences (:func:`dataset_from_capture`)."""

    scale: float = 0.5
    """Capture images → the delivered (and evaluated) frames."""
    zoom: float = 4.0
    """The refiner works on a fixed box around the subject per sequence, magnified this many times over --scale (cut
    from the full-resolution images); its change goes back into the delivered frames. 0: whole frames, padded to
    multiples of 16."""
    env_height: int = 16
    """Camera-space envmap height (width = 2x)."""
    train_length: int = 24
    """Frames per training sequence (looping clips repeat)."""
    test_length: int = 41
    """Frames per test sequence (41 = three 17-frame windows)."""
    train_cameras: int | None = None
    """Training sequences from this many of the capture's training cameras (evenly spaced); default: all."""

    def validate(self) -> None:
        require_positive({"scale": self.scale, "train_length": self.train_length, "test_length": self.test_length})
        if self.train_cameras is not None:
            require_positive({"train_cameras": self.train_cameras})
        if self.env_height < 4:
            raise GraMiParameterError("env_height", f"must be >= 4 (lat-long rows), got {self.env_height}")
        if self.zoom != 0 and not self.zoom >= 1:
            raise GraMiParameterError("zoom", f"must be >= 1 (or 0: whole frames), got {self.zoom}")

    def record(self) -> dict:
        """The run's identity in provenance.json (zoom 0 is recorded as None, whole frames)."""
        return (
            {"scale": self.scale, "env_height": self.env_height, "train_length": self.train_length}
            | {
                "test_length": self.test_length,
                "zoom": self.zoom or None,
            }
            | ({"train_cameras": self.train_cameras} if self.train_cameras else {})
        )  # older records: all cameras


def dataset_from_capture(
    capture_dir: str | Path,
    fit_dir: str | Path,
    out: str | Path,
    *,
    relightnet_dir: str | Path | None = None,
    config: CaptureSequencesConfig | None = None,
    cache_dir: str | Path | None = None,
    overwrite: bool = False,
    shard: Shard | None = None,
) -> RefinerDataset | None:
    """Sequences per camera: training cameras over the training frames, held-out cameras over the test frames.

    Coarse frames are RelightNet renders (``relightnet_dir``) or the microfacet render; targets are the captured images.
    The capture's clips loop, so a sequence shorter than its length is played again from its start. With a zoom, the
    sequences also hold the whole frames (``coarse_frame``/``target_frame``) and dataset.json each sequence's ``box``.
    ``shard``: make only this shard's sequences (each camera's is one job), kept in ``parts/``; the shard that finds
    every part there writes the dataset (one process's files) and returns it, the others return None.
    """

    config = config or CaptureSequencesConfig()
    config.validate()
    ensure_mitsuba()
    out, shard = Path(out), shard or Shard()
    capture, relighter, model = _coarse_stages(capture_dir, fit_dir, relightnet_dir, cache_dir or out / "cache")
    inputs = {"capture": capture_dir, "fit": fit_dir, "relightnet": relightnet_dir}
    jobs = _sequence_jobs(capture, config)
    _check_memory(capture, relighter.ls.stage, jobs, config)
    claim_output(out, "refiner-data", inputs, config.record(), overwrite=overwrite, shard=shard)
    if shard.whole:
        raw = [_raw_sequence(capture, relighter, model, job, config) for job in progress(jobs, description="refiner sequences")]
    else:
        for job in progress(shard.take(jobs), description=f"refiner sequences (shard {shard})"):
            _save_part(out, job, _raw_sequence(capture, relighter, model, job, config))
        if not all(_part_path(out, job).is_file() for job in jobs):
            return None  # another shard's sequences are still being made: the last shard writes the dataset
        raw = [_load_part(out, job) for job in jobs]
    left_out = {f"{job[0]}_{job[1]}": job[5] for job in jobs if job[5]}
    dataset = _write_dataset(
        out, raw, capture, config, relighter.ls.sequence.fps, "relightnet" if model is not None else "microfacet", left_out
    )
    shutil.rmtree(out / "parts", ignore_errors=True)
    return dataset


SEQUENCE_BYTES_PER_PIXEL = 32  # a delivered frame's coarse and target images (RGBA float32), its box's the same


def _check_memory(capture, stage, jobs: list[tuple], config: CaptureSequencesConfig) -> None:
    """The dataset is held whole before it is written: its frames (a box up to the frame's size × zoom²) and their
    envmaps, against the machine's memory, before anything is rendered."""
    total = 0.0
    for _, cam, _, length, _, _ in jobs:
        camera = stage.camera(cam)
        pixels = camera.width * camera.height * config.scale**2
        total += length * (pixels * SEQUENCE_BYTES_PER_PIXEL * (1 + config.zoom**2) + 2 * config.env_height**2 * 12)
    frames = sum(job[3] for job in jobs)
    what = f"{len(jobs)} sequences of {frames:,} frames in all (with these --scale, --zoom, --env-height and lengths)"
    require_memory_for(capture.folder, "", total, what)


def _raw_sequence(capture, relighter, model, job, config: CaptureSequencesConfig) -> tuple:
    split, cam, entries, length, reference, _ = job
    return (split, cam, *_capture_sequence(capture, relighter, model, cam, entries, length, reference, config))


def _write_dataset(
    out: Path, raw: list[tuple], capture, config: CaptureSequencesConfig, fps: float, coarse: str, left_out: dict[str, list[int]]
) -> RefinerDataset:
    """Every sequence (cut to its subject box with a zoom) and dataset.json, with the whole dataset's exposures;
    ``left_out``: sequence name → the capture frames it left out for want of an image."""
    crop = raw[0][3]
    boxes = _zoom_to_subject(raw, config) if config.zoom else {}
    entries = [_entry(split, cam, seq, frames, capture, out, boxes) for split, cam, seq, _, frames in raw]
    for entry in entries:
        if entry["name"] in left_out:
            entry["left_out_frames"] = left_out[entry["name"]]
    h, w = raw[0][2]["coarse"].shape[1:3]
    exposure, env_exposure = _exposures([seq for _, _, seq, _, _ in raw])
    write_dataset_json(
        out, entries, h, w, (h, w) if boxes else crop, exposure, env_exposure, source=str(capture.folder), coarse=coarse,
        scale=config.scale, fps=fps, **({"zoom": config.zoom, "frame": list(crop)} if boxes else {}),
    )  # fmt: skip
    return RefinerDataset(out)


def _part_path(out: Path, job) -> Path:
    return out / "parts" / f"{job[0]}_{job[1]}.npz"


def _save_part(out: Path, job, raw: tuple) -> None:
    """A shard's sequence before the dataset-wide steps (zoom boxes, exposures), for the shard that writes them."""
    _, _, seq, crop, frames = raw
    arrays = {k: v for k, v in seq.items() if k != "full"}
    for key, value in seq.get("full", {}).items():
        arrays[f"full.{key}"] = np.stack(value) if isinstance(value, list) else value
    with atomic_path(_part_path(out, job)) as tmp, open(tmp, "wb") as fh:
        np.savez(fh, **arrays, crop=np.array(crop), frames=np.array(frames))


def _load_part(out: Path, job) -> tuple:
    with np.load(_part_path(out, job), allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    crop, frames = tuple(int(x) for x in arrays.pop("crop")), [int(f) for f in arrays.pop("frames")]
    full = {k.split(".", 1)[1]: arrays.pop(k) for k in [k for k in arrays if k.startswith("full.")]}
    if full:
        arrays["full"] = {k: list(v) if k in ("coarse", "target") else v for k, v in full.items()}
    return (job[0], job[1], arrays, crop, frames)


def _coarse_stages(capture_dir, fit_dir, relightnet_dir, cache_dir):
    """(capture, its fitted relighter, RelightNet or None), loaded and checked before the output folder is claimed."""
    from gra_mi.fit.fitted import fitted_relighter

    capture, relighter = fitted_relighter(capture_dir, fit_dir, cache_dir)
    if relightnet_dir is None:
        return capture, relighter, None
    from gra_mi.relightnet.model import RelightNet

    model = RelightNet.load(relightnet_dir, torch_device())
    if model.config.resolution != relighter.albedo_tex.shape[0]:
        raise GraMiInputError(
            Path(relightnet_dir) / "relightnet.json",
            f"RelightNet runs at {model.config.resolution}², the fit in {fit_dir} at {relighter.albedo_tex.shape[0]}²: "
            "train RelightNet on this fit",
            field="resolution",
        )
    # RelightNet is fed the coarse renders it was trained on (their bounces of light are in its config).
    relighter.transport = replace(relighter.transport, bounces=model.config.input_bounces)
    return capture, relighter, model


def _sequence_jobs(capture, config: CaptureSequencesConfig) -> list[tuple]:
    """[(split, camera, capture frames, length, the neutral reference frame, the frames left out for want of an
    image)]."""
    uniforms = [f for f in capture.frames if f.split == "train" and f.kind == "uniform"]
    if not uniforms:
        raise GraMiInputError(capture.folder / "capture.json", "no uniformly lit training frame to serve as the neutral reference")
    # Training sequences hold the relit frames only: the refiner never refines a uniformly lit tracking frame, and
    # with them in, every other training frame is a flash that the 4-frame latents must mix with the relit ones.
    relit = [f for f in capture.frames if f.split == "train" and f.kind != "uniform"]
    if not relit:
        raise GraMiInputError(capture.folder / "capture.json", "no relit (envmap or pattern) training frame to train the refiner on")
    held_out = [f for f in capture.frames if f.split == "test"]
    cameras = capture.train_cameras
    if config.train_cameras:
        if config.train_cameras > len(cameras):
            raise GraMiParameterError("train_cameras", f"the capture has {len(cameras)} training cameras, asked for {config.train_cameras}")
        cameras = [cameras[k] for k in np.unique(np.linspace(0, len(cameras) - 1, config.train_cameras).round().astype(int))]
    jobs = [("train", cam, relit, config.train_length) for cam in cameras]
    # The held-out lighting on the first training camera (RelightNet's "novel lighting" view): a continuous video
    # that training never sees and the evaluation never scores, on which training chooses the refiner's mix.
    jobs += [("selection", cam, held_out, config.test_length) for cam in capture.train_cameras[:1] if held_out]
    jobs += [("test", cam, held_out, config.test_length) for cam in capture.eval_cameras]
    return [_with_images(capture, *job, uniforms) for job in jobs]


def _with_images(capture, split: str, cam: str, entries: list, length: int, uniforms: list) -> tuple:
    """A sequence job on the frames ``cam`` has an image of (a real capture's gaps). A training sequence drops the
    frames it lacks (its relit frames are not consecutive in the capture anyway); a held-out video keeps its longest
    unbroken run, so that no frame of it follows a gap. The reference: the camera's first uniformly lit frame."""
    reference = next((u for u in uniforms if capture.has_image(cam, u)), None)
    where = capture.folder / "capture.json"
    if reference is None:
        raise GraMiInputError(
            where, f"camera {cam} has no image of a uniformly lit training frame, the refiner's neutral reference", field="frames"
        )
    present, _, breaks = capture.frames_with_images(cam, [e.frame for e in entries])
    if not present:
        raise GraMiInputError(
            where, f"camera {cam} has no image of any frame of its {split} sequence: hold it out of the capture", field="frames"
        )
    if split != "train" and breaks:
        runs = np.split(np.array(present), breaks)
        present = [int(f) for f in max(runs, key=len)]  # the first of the longest
    by_frame = {e.frame: e for e in entries}
    kept = set(present)
    left_out = [e.frame for e in entries if e.frame not in kept]
    if left_out:
        logger.warning("%s_%s: %d of its %d frames left out (no image, or past a gap)", split, cam, len(left_out), len(entries))
    return split, cam, [by_frame[f] for f in present], length, reference, left_out


def _capture_sequence(capture, relighter, model, cam: str, entries, length: int, uniform, config: CaptureSequencesConfig):
    """(the sequence's arrays at the delivered scale, the frame's size before padding, the capture frame of each
    sequence frame); with a zoom, also the full-resolution frames and subject masks the boxes are cut from."""
    from gra_mi.relightnet.infer import render_view

    stage, scale = relighter.ls.stage, config.scale

    def camera_env(entry):
        lighting = leds_to_envmap(stage, capture.lighting(stage, entry), config.env_height)
        return to_camera_space(lighting, stage.camera(cam), supersample=1)

    full = {  # capture resolution: the source of the crops
        "coarse": [render_view(relighter, model, e.mesh_frame, cam, capture.lighting(stage, e)).image[..., :3] for e in entries],
        "target": [load_observation(capture, cam, e.frame) for e in entries],
        "reference": load_observation(capture, cam, uniform.frame),
    }
    unique = {k: [_resize_pad(v, scale)[0] for v in full[k]] for k in ("coarse", "target")}
    unique["env"] = [camera_env(e) for e in entries]
    order = [i % len(entries) for i in range(max(length, len(entries)))]
    seq = {k: np.stack([v[i] for i in order]) for k, v in unique.items()}
    seq["reference"], crop = _resize_pad(full["reference"], scale)
    seq["reference_env"] = camera_env(uniform)
    if config.zoom:
        alpha = np.stack([_resize_pad(t[..., 3:].repeat(3, -1), scale)[0][: crop[0], : crop[1], 0] for t in full["target"]])
        seq["full"] = full | {"masks": (alpha > 0.5) | (seq["coarse"][: len(entries), : crop[0], : crop[1]].max(-1) > 0)}
    return seq, crop, [entries[i].frame for i in order]


def _zoom_to_subject(raw, config: CaptureSequencesConfig) -> dict[str, tuple[int, int, int, int]]:
    """Cut every sequence to its box around the subject, one crop size for the whole dataset; the whole frames stay
    as ``coarse_frame``/``target_frame``. Returns each sequence's box."""
    scale, crop = config.scale, raw[0][3]
    size, found = subject_boxes([seq["full"]["masks"] for _, _, seq, _, _ in raw], config.zoom)
    boxes = {}
    for (split, cam, seq, _, _), box in zip(raw, found, strict=True):
        full = seq.pop("full")
        boxes[f"{split}_{cam}"] = box
        n = len(full["coarse"])
        order = [i % n for i in range(len(seq["coarse"]))]
        seq["coarse_frame"] = seq["coarse"][:, : crop[0], : crop[1]]
        seq["target_frame"] = seq["target"][:, : crop[0], : crop[1]]
        seq["coarse"] = crop_box(np.stack(full["coarse"]), box, scale, size)[order]
        seq["target"] = crop_box(np.stack([t[..., :3] for t in full["target"]]), box, scale, size)[order]
        seq["reference"] = crop_box(full["reference"][None, ..., :3], box, scale, size)[0]
    return boxes


def _exposures(sequences: list[dict]) -> tuple[float, float]:
    """(image exposure, envmap exposure) of the whole dataset. The subject's median radiance goes to 0.25 (≈ mid-grey
    after sRGB), unless that clips more than 1 % of it: the refiner sees nothing above white (its highlights pass
    through from the input). Percentiles of the subject, not its maximum: robust to the path tracer's fireflies."""
    targets = np.concatenate([s["target"].reshape(-1, 3) for s in sequences])
    subject = targets[targets.max(axis=1) > 0]  # not the background
    median, peak = float(np.median(subject.mean(axis=1))), float(np.quantile(subject.max(axis=1), 0.99))
    envs = np.concatenate([s["env"].reshape(-1, 3) for s in sequences])
    return min(0.25 / max(median, 1e-6), 1.0 / max(peak, 1e-6)), 1.0 / max(float(envs.mean()), 1e-6)


def _entry(split: str, cam: str, seq: dict, capture_frames: list[int], capture, out: Path, boxes: dict) -> dict:
    """Write one sequence; its dataset.json entry."""
    name = f"{split}_{cam}"
    return {
        "name": name,
        "split": split,
        "frames": len(seq["coarse"]),
        "subject": f"capture:{capture.preset}",
        "file": write_sequence(out, name, seq),
        "camera": cam,
        "capture_frames": capture_frames,  # the capture frame shown in each sequence frame (clips loop)
        **({"box": list(boxes[name])} if boxes else {}),
    }
