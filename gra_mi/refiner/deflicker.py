"""Flicker correction (paper, supplementary "Flicker Correction"): pull a refined frame's low-frequency illumination
towards a temporally stable render while keeping its fine detail.

With the refined frame ``x`` as the guide of both (He et al.'s guided filter, kornia's ``guided_blur``):

    low_x = guided(x → x)        the refined frame's own illumination, aligned to its edges
    low_c = guided(x → coarse)   the stable render's illumination (RelightNet's), aligned to the same edges
    out   = x + (low_c − low_x)

Both are filtered in display values (sRGB at one exposure, as the refiner sees them), where the filter's ``eps``
(squared display units) has a meaning; the result goes back to linear radiance.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gra_mi.core.color import display_exposure, srgb_decode, to_display
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.io import Mp4Stream, read_exr, write_exr, write_png
from gra_mi.core.progress import progress


@dataclass
class DeflickerConfig:
    filter_radius: int = 4
    """Guided filter radius in pixels (window 2r + 1): how low the corrected frequencies reach."""
    filter_eps: float = 0.05
    """Guided filter regularisation, in squared display units: structure with a local standard deviation well above
    √eps (≈ 0.22: the silhouette) is kept in the illumination maps, finer detail (wrinkles) is not, so it stays the
    refined frame's own. Measured on a synthetic flicker (tests/test_eval.py): 1e-3 keeps the detail in the maps and
    swaps it for the coarse render's blur; 0.05 takes 62 % of the flicker out and raises PSNR."""
    strength: float = 1.0
    """Fraction of the illumination residual added back (0: off, 1: the paper's correction)."""

    def validate(self) -> None:
        if not isinstance(self.filter_radius, int) or self.filter_radius < 1:
            raise GraMiParameterError("filter_radius", f"must be an integer >= 1, got {self.filter_radius}")
        require_positive({"filter_eps": self.filter_eps})
        if not 0.0 <= self.strength <= 1.0:
            raise GraMiParameterError("strength", f"must be in [0, 1], got {self.strength}")


def _encode(linear: np.ndarray, exposure: float) -> torch.Tensor:

    return torch.from_numpy(to_display(linear, exposure)).float().permute(2, 0, 1)[None]


def _decode(display: torch.Tensor, exposure: float) -> np.ndarray:

    return (srgb_decode(display[0].permute(1, 2, 0).double().numpy()) / exposure).astype(np.float32)


def deflicker_frame(frame: np.ndarray, stable: np.ndarray, exposure: float, config: DeflickerConfig | None = None) -> np.ndarray:
    """One corrected frame (H, W, 3 linear) from a refined ``frame`` and the temporally ``stable`` render of the same
    view (both linear, same size), filtered at display ``exposure``. Alpha, if any, is passed through."""
    from kornia.filters import guided_blur

    config = config or DeflickerConfig()
    if frame.shape[:2] != stable.shape[:2]:
        raise GraMiParameterError(
            "stable", f"frame is {frame.shape[1]}×{frame.shape[0]}, its stable render {stable.shape[1]}×{stable.shape[0]}"
        )
    k = filter_window(config, frame.shape)
    x, c = _encode(frame, exposure), _encode(stable, exposure)
    low_x = guided_blur(x, x, k, config.filter_eps, border_type="reflect")
    low_c = guided_blur(x, c, k, config.filter_eps, border_type="reflect")
    # the correction as a change, so what lies above the display's white (clipped in x) passes through
    out = frame[..., :3] + (_decode(x + config.strength * (low_c - low_x), exposure) - _decode(x, exposure))
    if frame.shape[-1] > 3:
        out = np.concatenate([out, frame[..., 3:]], axis=-1)
    return out


def filter_window(config: DeflickerConfig, shape: tuple[int, ...]) -> int:
    """The guided filter's window (2r + 1 pixels), its radius refused where not less than the frame's side: a reflected
    border needs it inside, and its k × k kernel costs k² floats (a radius of 100,000 asked for 160 GB)."""
    k, (h, w) = 2 * config.filter_radius + 1, shape[:2]
    if config.filter_radius >= min(h, w):
        raise GraMiParameterError(
            "filter_radius", f"{config.filter_radius}: the window reaches past the {w}×{h} frame's borders; at most {min(h, w) - 1}"
        )
    return k


def _frame_files(folder: Path, what: str) -> list[Path]:
    if not folder.is_dir():
        raise GraMiInputError(folder, f"{what}: folder not found")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".exr", ".png") and not p.name.startswith("."))
    exr = [p for p in files if p.suffix.lower() == ".exr"]
    files = exr or files  # frames written as EXR + PNG previews: the EXRs are the data
    if not files:
        raise GraMiInputError(folder, f"{what}: no .exr or .png frames")
    return files


def read_frame(path: Path) -> np.ndarray:
    """A frame as linear RGB(A): EXR as stored, PNG decoded from sRGB."""

    if path.suffix.lower() == ".exr":
        return read_exr(path)
    import imageio.v3 as iio

    try:
        pixels = iio.imread(path).astype(np.float64) / 255.0
    except Exception as exc:
        raise GraMiInputError(path, f"not a readable PNG ({exc})") from None
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=-1)

    rgb = srgb_decode(pixels[..., :3])
    return np.concatenate([rgb, pixels[..., 3:]], axis=-1).astype(np.float32)


def deflicker_folder(
    frames_dir: str | Path, stable_dir: str | Path, out: str | Path, config: DeflickerConfig | None = None, exposure: float | None = None
) -> list[Path]:
    """``gra-mi deflicker``: correct every frame in ``frames_dir`` with the frame of the same position (sorted names)
    in ``stable_dir``; writes ``out/NAME.exr`` + ``.png`` and ``deflickered.mp4``. ``exposure`` None: the one that
    shows the first stable frame's 99th percentile at 0.8 (:func:`gra_mi.core.color.display_exposure`)."""

    config = config or DeflickerConfig()
    config.validate()
    frames, stable = _frame_files(Path(frames_dir), "frames"), _frame_files(Path(stable_dir), "--stable")
    if len(frames) != len(stable):
        raise GraMiInputError(
            stable_dir, f"--stable: {len(stable)} frames, but {frames_dir} has {len(frames)}; one stable frame per frame expected"
        )
    out = Path(out)
    for name, given in (("frames", frames_dir), ("--stable", stable_dir)):
        if out.resolve() == Path(given).resolve():
            raise GraMiInputError(out, f"is the {name} folder: the corrected frames would overwrite their input; choose another --out")
    pairs = list(zip(frames, stable, strict=True))
    for path, guide_path in progress(pairs, description="deflicker: checking frames"):  # nothing written before all pass
        frame = read_frame(path)
        _check_pair(path, frame, guide_path, read_frame(guide_path))
        filter_window(config, frame.shape)
    written = []
    with Mp4Stream(out / "deflickered.mp4", 24.0) as mp4:
        for path, guide_path in progress(pairs, description="deflicker"):
            frame, guide = read_frame(path), read_frame(guide_path)
            if exposure is None:
                exposure = display_exposure(guide, guide[..., :3].max(axis=-1) > 0)
            corrected = deflicker_frame(frame, guide, exposure, config)
            write_exr(out / f"{path.stem}.exr", corrected)
            write_png(out / f"{path.stem}.png", corrected, exposure=exposure)
            mp4.append(corrected, exposure)
            written.append(out / f"{path.stem}.exr")
    return written


def _check_pair(path: Path, frame: np.ndarray, guide_path: Path, guide: np.ndarray) -> None:
    """A frame and its stable render: the same size, and finite (a NaN would pass through the guided filter)."""
    if frame.shape[:2] != guide.shape[:2]:
        raise GraMiInputError(guide_path, f"{guide.shape[1]}×{guide.shape[0]} pixels, but {path.name} is {frame.shape[1]}×{frame.shape[0]}")
    for source, image in ((path, frame), (guide_path, guide)):
        bad = int((~np.isfinite(image[..., :3])).sum())
        if bad:
            raise GraMiInputError(source, f"{bad} non-finite (NaN/Inf) pixel values")
