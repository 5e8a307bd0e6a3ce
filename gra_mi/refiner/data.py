"""The video refiner's data: sequences of (coarse render, ground truth, camera-space envmap) frames + a reference.

On disk (docs/data-format.md, ``gra-mi-refiner-data/1``): ``dataset.json`` and one ``sequences/NAME.safetensors``
per sequence with linear HDR float tensors ``coarse`` (N, H, W, 3), ``target`` (N, H, W, 3; optional for
inference), ``env`` (N, h, 2h, 3) camera-space envmaps, ``reference`` (H, W, 3) the subject under neutral light and
``reference_env`` (h, 2h, 3) its lighting. H and W are multiples of 16 (images are zero-padded at the bottom/right;
``crop`` gives the valid size). Training draws windows of the refiner's length from sequences of any length.

Two builders: :func:`dataset_from_capture` (the pipeline: RelightNet or microfacet renders of a capture, the
captured images as targets) and :func:`synthetic_dataset` (a fast stand-in for tests: a textured ball moving under
a different light each frame, whose coarse render lacks the texture's fine detail and the highlight).

The models see tone-mapped values in [-1, 1]: images through sRGB after a dataset-wide exposure; envmaps through
a log curve (``ENV_STOPS`` stops above the dataset's mean envmap radiance), as HDR suns would clip otherwise.
"""

from __future__ import annotations

import json
import math
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from gra_mi.capture.dataset import load_observation
from gra_mi.core.color import srgb_decode, srgb_encode
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.io import atomic_path, atomic_write_text, json_field, read_json
from gra_mi.core.progress import progress
from gra_mi.core.provenance import claim_output
from gra_mi.core.runtime import torch_device
from gra_mi.core.shard import Shard
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.envmap import leds_to_envmap, pixel_directions, to_camera_space

DATA_FORMAT = "gra-mi-refiner-data/1"
SPLITS = ("train", "selection", "test")
"""Sequence splits: trained on; held out to choose the refiner's mix (:mod:`gra_mi.refiner.mix`);
held out for the evaluation."""
ENV_STOPS = 12.0


# --------------------------------------------------------------------------------------------------------------
# Tone mapping between linear radiance and the VAE's [-1, 1]
# --------------------------------------------------------------------------------------------------------------


def image_to_video(linear: torch.Tensor, exposure: float) -> torch.Tensor:
    return 2 * srgb_encode((linear * exposure).clamp(0, 1)) - 1


def video_to_image(video: torch.Tensor, exposure: float) -> torch.Tensor:
    """Inverse of :func:`image_to_video` (exact below the clipping point)."""
    return srgb_decode(((video + 1) / 2).clamp(0, 1)) / exposure


def env_to_video(env: torch.Tensor, env_exposure: float) -> torch.Tensor:
    return 2 * (torch.log2(1 + env.clamp(min=0) * env_exposure) / ENV_STOPS).clamp(0, 1) - 1


# --------------------------------------------------------------------------------------------------------------
# Dataset files
# --------------------------------------------------------------------------------------------------------------

FIELDS = ("coarse", "target", "env", "reference", "reference_env")


def write_sequence(folder: Path, name: str, tensors: dict[str, np.ndarray]) -> str:
    from safetensors.numpy import save_file

    rel = f"sequences/{name}.safetensors"
    with atomic_path(folder / rel) as tmp:
        save_file({k: np.ascontiguousarray(v, dtype=np.float32) for k, v in tensors.items()}, str(tmp))
    return rel


def write_dataset_json(
    folder: Path, sequences: list[dict], height: int, width: int, crop: tuple[int, int], exposure: float, env_exposure: float, **extra
) -> Path:
    data = {
        "format": DATA_FORMAT,
        "height": height,
        "width": width,
        "crop": list(crop),
        "exposure": exposure,
        "env_exposure": env_exposure,
        "sequences": sequences,
        **extra,
    }
    atomic_write_text(folder / "dataset.json", json.dumps(data, indent=1) + "\n")
    return folder / "dataset.json"


@dataclass
class SequenceInfo:
    name: str
    split: str
    frames: int
    subject: str
    file: Path
    has_target: bool
    box: tuple[int, int, int, int] | None = None
    """The subject crop in the delivered frames (y0, x0, y1, x1); None: the sequence holds whole frames."""


class RefinerDataset:
    """A folder written by one of the builders; windows come out as model-ready tensors in [-1, 1]."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        path = self.folder / "dataset.json"
        data = read_json(path, " (make one with `gra-mi refiner-data`)")
        if not isinstance(data, dict) or data.get("format") != DATA_FORMAT:
            got = data.get("format") if isinstance(data, dict) else data
            raise GraMiInputError(path, f"field 'format': expected '{DATA_FORMAT}', got {got!r}")
        self.height, self.width = (json_field(path, data, k, int, low=16) for k in ("height", "width"))
        if self.height % 16 or self.width % 16:
            raise GraMiInputError(path, f"fields 'height'/'width' must be multiples of 16, got {self.height}×{self.width}")
        self.crop = tuple(data.get("crop", [self.height, self.width]))
        self.exposure, self.env_exposure = (json_field(path, data, k, float, low=1e-12) for k in ("exposure", "env_exposure"))
        self.meta = data
        self.sequences: dict[str, SequenceInfo] = {}
        for i, s in enumerate(json_field(path, data, "sequences", list)):
            where = f"sequences[{i}]."
            for key, kind in (("name", str), ("split", str), ("file", str)):
                json_field(path, s, key, kind, where=where)
            json_field(path, s, "frames", int, low=1, where=where)
            if s["split"] not in SPLITS:
                raise GraMiInputError(path, f"expected one of {', '.join(SPLITS)}, got {s['split']!r}", field=where + "split")
            if s["name"] in self.sequences:
                raise GraMiInputError(path, f"sequence '{s['name']}' is listed twice", field=where + "name")
            file = self.folder / s["file"]
            if not file.is_file():
                raise GraMiInputError(file, f"sequence '{s['name']}' file not found")
            box = s.get("box")
            if box is not None and not (
                isinstance(box, list) and len(box) == 4 and all(isinstance(v, int) for v in box) and box[2] > box[0] and box[3] > box[1]
            ):
                raise GraMiInputError(
                    path, f"expected [y0, x0, y1, x1] integers with y1 > y0 and x1 > x0, got {box!r}", field=where + "box"
                )
            if box is not None and "frame" not in data:
                raise GraMiInputError(path, "sequences with a 'box' need the delivered frame size 'frame': [height, width]", field="frame")
            self.sequences[s["name"]] = SequenceInfo(
                s["name"],
                s["split"],
                int(s["frames"]),
                s.get("subject", ""),
                file,
                bool(s.get("has_target", True)),
                tuple(box) if box else None,
            )

    def check(self, names: list[str] | None = None) -> None:
        """Open each sequence's file (default: all) and check it holds what dataset.json says (its tensors, enough
        frames), so that a command stops before it writes anything rather than part-way through."""
        for name in self.sequences if names is None else names:
            info = self.sequences[name]
            with self._open(name) as f:
                need = {"coarse", "env", "reference", "reference_env"} | ({"target"} if info.has_target else set())
                if missing := sorted(need - set(f.keys())):
                    raise GraMiInputError(info.file, f"missing tensor(s) {', '.join(missing)} (expected {', '.join(sorted(need))})")
                for key in sorted(need - {"reference", "reference_env"}):
                    held = f.get_slice(key).get_shape()[0]
                    if held < info.frames:
                        raise GraMiInputError(
                            info.file, f"'{key}' holds {held} frames, but dataset.json says sequence '{name}' has {info.frames}"
                        )

    def names(self, split: str | None = None) -> list[str]:
        return [n for n, s in self.sequences.items() if split is None or s.split == split]

    def _open(self, name: str):
        from safetensors import safe_open

        if name not in self.sequences:
            raise GraMiInputError(self.folder / "dataset.json", f"no sequence '{name}' (have {sorted(self.sequences)})")
        try:
            return safe_open(str(self.sequences[name].file), framework="pt")
        except Exception as exc:  # SafetensorError: cut short, or not a safetensors file
            raise GraMiInputError(self.sequences[name].file, f"not a readable safetensors file ({str(exc)[:100]})") from None

    def window(self, name: str, start: int, length: int) -> dict[str, torch.Tensor]:
        """Frames [start, start + length) as (3, T, H, W) videos in [-1, 1]; frames past the end repeat the last one.

        Read lazily from the file (safetensors slices), so a long sequence is never held in memory whole.
        """
        info = self.sequences[name]
        with self._open(name) as f:
            idx = [min(start + t, info.frames - 1) for t in range(length)]
            lo, hi = idx[0], idx[-1] + 1

            def frames(key):
                block = f.get_slice(key)[lo:hi]
                return block[[i - lo for i in idx]]

            out = {
                "coarse": image_to_video(frames("coarse"), self.exposure).permute(3, 0, 1, 2),
                "env": env_to_video(frames("env"), self.env_exposure).permute(3, 0, 1, 2),
                "reference": image_to_video(f.get_tensor("reference"), self.exposure).permute(2, 0, 1),
                "reference_env": env_to_video(f.get_tensor("reference_env"), self.env_exposure).permute(2, 0, 1),
            }
            if info.has_target:
                out["target"] = image_to_video(frames("target"), self.exposure).permute(3, 0, 1, 2)
        return out

    def linear_frames(self, name: str, key: str, start: int, stop: int) -> torch.Tensor:
        with self._open(name) as f:
            return f.get_slice(key)[start:stop]

    def delivered(self, name: str, index: int, key: str, image: np.ndarray | None = None) -> np.ndarray:
        """Frame ``index`` of ``key`` (coarse or target) as delivered (the whole frame, linear), with the refiner's
        ``image`` of that frame in place of the stored one: for a subject crop, its change from the stored crop goes
        back into the stored whole frame; for whole frames, the padding is cut off.

        The change is taken from what the refiner was shown: the stored frame clipped at its video range's white
        (:func:`image_to_video`). Highlights above it, which the refiner cannot see or make, pass through from the
        stored frame, so a refiner that returns what it was shown delivers the stored frame exactly."""
        ch, cw = self.crop
        stored = self.linear_frames(name, key, index, index + 1)[0].numpy()
        box = self.sequences[name].box
        if image is not None:
            change = image - np.clip(stored, 0.0, 1.0 / self.exposure)
        if box is None:
            return (stored if image is None else stored + change)[:ch, :cw]
        frame = self.linear_frames(name, f"{key}_frame", index, index + 1)[0].numpy()
        return frame if image is None else paste_box(frame, change, box)


# --------------------------------------------------------------------------------------------------------------
# Synthetic sequences (tests, CI, benchmarks)
# --------------------------------------------------------------------------------------------------------------


def _latlong_dirs(h: int) -> np.ndarray:

    return pixel_directions(h, 2 * h)


def synthetic_sequence(frames: int, height: int, width: int, env_height: int, subject_seed: int, seed: int) -> dict[str, np.ndarray]:
    """A ball with a subject-specific fine texture moving and turning under a new light each frame.

    target = texture · (ambient + sun·cos) + a specular highlight; coarse = a blurred texture under the same diffuse
    light (no highlight) — the kind of gap the refiner closes. Envmaps: the ambient colour + a sun blob, camera space.
    """
    rng = np.random.default_rng(seed)
    srng = np.random.default_rng(10_000 + subject_seed)
    freq, colors = srng.uniform(6, 14, 2), srng.uniform(0.15, 0.9, (2, 3))
    y, x = np.meshgrid((np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width, indexing="ij")
    dirs = _latlong_dirs(env_height)
    phase0, speed = rng.uniform(0, 2 * math.pi), rng.uniform(0.15, 0.35)
    sun_az, sun_el = rng.uniform(0, 2 * math.pi), rng.uniform(-0.3, 1.0)
    out = {k: [] for k in ("coarse", "target", "env")}
    radius = 0.32 * min(height, width) / width  # in units of the image width

    def render(t: float, light_dir, sun, ambient, textured: bool):
        cx = 0.5 + 0.22 * math.sin(phase0 + speed * t)
        cy = 0.5 + 0.08 * math.cos(phase0 + 0.7 * speed * t)
        px, py = (x - cx) * width / height, (y - cy)
        r = radius * width / height
        d2 = (px**2 + py**2) / r**2
        inside = d2 < 1
        nz = np.sqrt(np.clip(1 - d2, 0, 1))
        n = np.stack([px / r, -py / r, nz], -1)
        u = np.arctan2(n[..., 0], n[..., 2]) + 0.4 * speed * t  # the ball turns: texture moves over it
        pattern = 0.5 + 0.5 * np.sin(freq[0] * u) * np.sin(freq[1] * n[..., 1] * 3)
        if not textured:
            pattern = np.full_like(pattern, 0.5)  # the coarse render's texture has lost the fine detail
        albedo = colors[0] * pattern[..., None] + colors[1] * (1 - pattern[..., None])
        cos = np.clip(n @ light_dir, 0, None)[..., None]
        image = albedo * (ambient + sun * cos)
        if textured:
            h = light_dir + np.array([0, 0, 1.0])
            h /= np.linalg.norm(h)
            image = image + 0.6 * sun * np.clip(n @ h, 0, None)[..., None] ** 40
        return (image * inside[..., None]).astype(np.float32)

    for t in range(frames):
        az = sun_az + 0.35 * t
        el = sun_el + 0.3 * math.sin(0.5 * t)
        light_dir = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        sun = rng.uniform(0.4, 1.2, 3) * np.array([1.0, 0.9, 0.8])
        ambient = rng.uniform(0.05, 0.25, 3)
        env = ambient + sun * 40 * np.exp((dirs @ light_dir - 1) / 0.01)[..., None]
        out["env"].append(env.astype(np.float32))
        out["target"].append(render(t, light_dir, sun, ambient, True))
        out["coarse"].append(render(t, light_dir, sun, ambient, False))
    neutral = np.array([0.0, 0.0, 1.0])
    reference = render(0, neutral, np.full(3, 0.3), np.full(3, 0.6), True)
    return {
        **{k: np.stack(v) for k, v in out.items()},
        "reference": reference,
        "reference_env": np.full((env_height, 2 * env_height, 3), 0.6, np.float32),
    }


def synthetic_dataset(
    folder: str | Path,
    subjects: dict[int, tuple[int, int]],
    frames: int = 17,
    height: int = 64,
    width: int = 64,
    env_height: int = 16,
    test_frames: int = 0,
    seed: int = 0,
    overwrite: bool = False,
) -> RefinerDataset:
    """subjects: subject seed → (number of training sequences, number of test sequences of ``test_frames``[, number
    of selection sequences of ``test_frames``])."""

    config = {"subjects": {str(k): list(v) for k, v in subjects.items()}, "frames": frames, "height": height, "width": width}
    config |= {"env_height": env_height, "test_frames": test_frames, "seed": seed}
    folder = claim_output(folder, "refiner-data --synthetic", {}, config, overwrite=overwrite)
    entries = []
    k = seed
    for subject, (n_train, n_test, *n_selection) in subjects.items():
        counts = (("train", n_train, frames), ("test", n_test, test_frames or frames))
        for split, count, length in counts + (("selection", sum(n_selection), test_frames or frames),):
            for i in range(count):
                name = f"s{subject}_{split}{i:02d}"
                k += 1
                rel = write_sequence(folder, name, synthetic_sequence(length, height, width, env_height, subject, k))
                entries.append({"name": name, "split": split, "frames": length, "subject": f"synthetic{subject}", "file": rel})
    write_dataset_json(folder, entries, height, width, (height, width), exposure=1.0, env_exposure=2.0, source="synthetic")
    return RefinerDataset(folder)


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


def crop_box(images: np.ndarray, box: tuple[int, int, int, int], scale: float, size: tuple[int, int]) -> np.ndarray:
    """Cut ``box`` (at the evaluation scale: capture pixels × ``scale``) out of full-resolution ``images`` (N, H, W, C)
    and resample it to ``size`` (h, w): bilinear, after an area pre-filter when the crop shrinks. Zeros past the frame."""
    t = torch.from_numpy(np.ascontiguousarray(images, dtype=np.float32)).permute(0, 3, 1, 2)
    y0, x0, y1, x1 = box
    shrink = int(min((y1 - y0) / scale / size[0], (x1 - x0) / scale / size[1]))
    if shrink >= 2:  # keep bilinear sampling from aliasing
        t = F.avg_pool2d(t, shrink, ceil_mode=True)
        scale *= shrink
    h, w = t.shape[-2:]
    # pixel centres of the output, in the source's normalised coordinates (align_corners=False)
    ys = (y0 + (torch.arange(size[0], dtype=torch.float64) + 0.5) * (y1 - y0) / size[0]) / scale / h * 2 - 1
    xs = (x0 + (torch.arange(size[1], dtype=torch.float64) + 0.5) * (x1 - x0) / size[1]) / scale / w * 2 - 1
    grid = torch.stack(torch.meshgrid(ys, xs, indexing="ij")[::-1], dim=-1)[None].expand(t.shape[0], -1, -1, -1)
    out = F.grid_sample(t, grid.float(), mode="bilinear", padding_mode="zeros", align_corners=False)
    return out.permute(0, 2, 3, 1).numpy()


def paste_box(frame: np.ndarray, change: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """``frame`` (fh, fw, C) at the evaluation scale plus ``change`` (h, w, C) on the crop, area-averaged into ``box``."""
    y0, x0, y1, x1 = box
    t = torch.from_numpy(np.ascontiguousarray(change, dtype=np.float32)).permute(2, 0, 1)[None]
    t = F.interpolate(t, size=(y1 - y0, x1 - x0), mode="area")[0].permute(1, 2, 0).numpy()
    out = np.array(frame, dtype=np.float32, copy=True)
    fh, fw = out.shape[:2]
    cy0, cx0, cy1, cx1 = max(y0, 0), max(x0, 0), min(y1, fh), min(x1, fw)
    out[cy0:cy1, cx0:cx1] += t[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0]
    return out


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
    claim_output(out, "refiner-data", inputs, config.record(), overwrite=overwrite, shard=shard)
    uniform, jobs = _sequence_jobs(capture, config)
    if shard.whole:
        raw = [_raw_sequence(capture, relighter, model, job, uniform, config) for job in progress(jobs, description="refiner sequences")]
    else:
        for job in progress(shard.take(jobs), description=f"refiner sequences (shard {shard})"):
            _save_part(out, job, _raw_sequence(capture, relighter, model, job, uniform, config))
        if not all(_part_path(out, job).is_file() for job in jobs):
            return None  # another shard's sequences are still being made: the last shard writes the dataset
        raw = [_load_part(out, job) for job in jobs]
    dataset = _write_dataset(out, raw, capture, config, relighter.ls.sequence.fps, "relightnet" if model is not None else "microfacet")
    shutil.rmtree(out / "parts", ignore_errors=True)
    return dataset


def _raw_sequence(capture, relighter, model, job, uniform, config: CaptureSequencesConfig) -> tuple:
    split, cam, entries, length = job
    return (split, cam, *_capture_sequence(capture, relighter, model, cam, entries, length, uniform, config))


def _write_dataset(out: Path, raw: list[tuple], capture, config: CaptureSequencesConfig, fps: float, coarse: str) -> RefinerDataset:
    """Every sequence (cut to its subject box with a zoom) and dataset.json, with the whole dataset's exposures."""
    crop = raw[0][3]
    boxes = _zoom_to_subject(raw, config) if config.zoom else {}
    entries = [_entry(split, cam, seq, frames, capture, out, boxes) for split, cam, seq, _, frames in raw]
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
    return capture, relighter, model


def _sequence_jobs(capture, config: CaptureSequencesConfig):
    """(the neutral reference frame, [(split, camera, capture frames, length)])."""
    uniform = next((f for f in capture.frames if f.split == "train" and f.kind == "uniform"), None)
    if uniform is None:
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
    return uniform, jobs


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
