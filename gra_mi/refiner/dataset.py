"""The video refiner's dataset: sequences of (coarse render, ground truth, camera-space envmap) frames + a reference,
on disk and as the training loop and inference read them. One floor below the builders that write it
(:mod:`gra_mi.refiner.data` from a capture, :mod:`gra_mi.refiner.synthetic` for tests).

On disk (docs/data-format.md, ``gra-mi-refiner-data/1``): ``dataset.json`` and one ``sequences/NAME.safetensors``
per sequence with linear HDR float tensors ``coarse`` (N, H, W, 3), ``target`` (N, H, W, 3; optional for
inference), ``env`` (N, h, 2h, 3) camera-space envmaps, ``reference`` (H, W, 3) the subject under neutral light and
``reference_env`` (h, 2h, 3) its lighting. H and W are multiples of 16 (images are zero-padded at the bottom/right;
``crop`` gives the valid size). Training draws windows of the refiner's length from sequences of any length.

The models see tone-mapped values in [-1, 1]: images through sRGB after a dataset-wide exposure; envmaps through
a log curve (``ENV_STOPS`` stops above the dataset's mean envmap radiance), as HDR suns would clip otherwise.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from gra_mi.core.color import srgb_decode, srgb_encode
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path, atomic_write_text, json_field, read_json

DATA_FORMAT = "gra-mi-refiner-data/1"
SPLITS = ("train", "selection", "test")
"""Sequence splits: trained on; held out to choose the refiner's mix (:mod:`gra_mi.refiner.mix`);
held out for the evaluation."""
ENV_STOPS = 12.0

FIELDS = ("coarse", "target", "env", "reference", "reference_env")


def image_to_video(linear: torch.Tensor, exposure: float) -> torch.Tensor:
    return 2 * srgb_encode((linear * exposure).clamp(0, 1)) - 1


def video_to_image(video: torch.Tensor, exposure: float) -> torch.Tensor:
    """Inverse of :func:`image_to_video` (exact below the clipping point)."""
    return srgb_decode(((video + 1) / 2).clamp(0, 1)) / exposure


def env_to_video(env: torch.Tensor, env_exposure: float) -> torch.Tensor:
    return 2 * (torch.log2(1 + env.clamp(min=0) * env_exposure) / ENV_STOPS).clamp(0, 1) - 1


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
