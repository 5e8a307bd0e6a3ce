"""Editing the fitted albedo: paint an image over it, or tint a UV mask with a colour, then re-render.

Edits happen in linear Rec.709 like everything else; sRGB PNG inputs are decoded first. The result stays in
[0, 1] (an albedo).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.core.color import srgb_decode
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import read_exr, write_exr, write_png


def read_edit_image(path: str | Path) -> np.ndarray:
    """An edit layer as linear float (H, W, C): EXR as is, PNG/JPEG decoded from sRGB (alpha kept linear)."""
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "file not found")
    if path.suffix.lower() == ".exr":
        return read_exr(path)
    try:
        image = iio.imread(path).astype(np.float32) / 255.0
    except Exception as exc:  # imageio raises many types for unreadable files
        raise GraMiInputError(path, f"not a readable image ({exc})") from None
    if image.ndim == 2:
        image = image[..., None]
    channels = image.shape[2]
    if channels >= 3:
        image[..., :3] = srgb_decode(image[..., :3])
    return image


def _fit_resolution(layer: np.ndarray, resolution: int, source: str) -> np.ndarray:
    if layer.shape[0] != layer.shape[1]:
        raise GraMiInputError(source, f"an edit layer must be square like the UV texture, got {layer.shape[1]}x{layer.shape[0]}")
    if layer.shape[0] == resolution:
        return layer
    idx = np.minimum((np.arange(resolution) * layer.shape[0]) // resolution, layer.shape[0] - 1)
    return layer[idx][:, idx]  # nearest: edits are painted masks, not photographs


def edit_albedo(
    albedo: np.ndarray,
    image: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    color: tuple[float, float, float] | None = None,
    opacity: float = 1.0,
    source: str = "edit",
) -> np.ndarray:
    """Blend an edit over the albedo (R, R, 3).

    - ``image``: RGB or RGBA layer; its alpha (1 if absent) times ``opacity`` says where it replaces the albedo.
    - ``mask`` + ``color``: where the mask (single channel in [0, 1]) is set, the albedo becomes ``color``.
    """
    if not 0.0 <= opacity <= 1.0:
        raise GraMiParameterError("opacity", f"must lie in [0, 1], got {opacity}")
    r = albedo.shape[0]
    if image is not None:
        layer = _fit_resolution(image, r, source)
        if layer.shape[2] not in (3, 4):
            raise GraMiInputError(source, f"expected an RGB or RGBA image, got {layer.shape[2]} channels")
        weight = (layer[..., 3:4] if layer.shape[2] == 4 else np.ones((r, r, 1))) * opacity
        paint = layer[..., :3]
        bad = int((~np.isfinite(paint)).sum())
        if bad:  # np.clip would keep a NaN: it would reach the albedo and every render of it
            raise GraMiInputError(source, f"{bad} non-finite (NaN/Inf) colour values in the edit layer")
    elif mask is not None and color is not None:
        weight = _fit_resolution(mask, r, source)[..., :1] * opacity
        paint = np.broadcast_to(np.asarray(color, np.float32), (r, r, 3))
        if np.any(np.asarray(color) < 0) or np.any(np.asarray(color) > 1):
            raise GraMiParameterError("color", f"an albedo colour lies in [0, 1], got {color}")
    else:
        raise GraMiInputError(source, "give an image, or a mask and a colour")
    if not np.isfinite(weight).all() or weight.min() < 0 or weight.max() > 1:
        raise GraMiInputError(source, "mask / alpha values must lie in [0, 1]")
    return np.clip(albedo * (1 - weight) + paint * weight, 0.0, 1.0).astype(np.float32)


def parse_color(text: str) -> tuple[float, float, float]:
    """'r,g,b' → a linear RGB albedo colour (finite, in [0, 1])."""
    try:
        color = tuple(float(c) for c in text.split(","))
    except ValueError:
        color = ()
    if len(color) != 3 or not all(np.isfinite(color)):
        raise GraMiParameterError("color", f"expected r,g,b (three finite numbers), got '{text}'")
    return color  # type: ignore[return-value]


def edit_albedo_file(
    albedo_path: str | Path,
    out: str | Path,
    image_path: str | Path | None = None,
    mask_path: str | Path | None = None,
    color: tuple[float, float, float] | None = None,
    opacity: float = 1.0,
) -> Path:
    """:func:`edit_albedo` from files to files: the edited albedo EXR at ``out`` and a PNG preview beside it."""
    from gra_mi.render.relighter import load_texture

    albedo = load_texture(albedo_path, 3, "albedo")
    image = read_edit_image(image_path) if image_path else None
    mask = read_edit_image(mask_path) if mask_path else None
    edited = edit_albedo(albedo, image, mask, color, opacity, source=str(image_path or mask_path))
    out = Path(out)
    write_exr(out, edited)
    write_png(out.with_suffix(".png"), edited)
    return out
