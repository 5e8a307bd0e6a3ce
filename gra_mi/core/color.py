"""Colour: the sRGB transfer function (IEC 61966-2-1) for NumPy arrays and torch tensors, and the one exposure rule
that shows a linear HDR image on a display.

Every preview (PNG, MP4), display metric (PSNR, SSIM, ꟻLIP, LPIPS), edit layer and the video refiner's tone mapping
goes through these, so they agree. Values outside [0, 1] are clipped before encoding or decoding, and non-finite ones
show as the nearest end of the range: NaN and −Inf black, +Inf white.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

ENCODE_KNEE = 0.0031308
"""Linear values at or below this are encoded linearly (× 12.92); above, by the 1/2.4 power law."""
DECODE_KNEE = 0.04045
"""The same knee on the encoded side (12.92 × ENCODE_KNEE, rounded as the standard gives it)."""
DISPLAY_PERCENTILE = 99.0
DISPLAY_LEVEL = 0.8
"""The display exposure shows the image's 99th-percentile luminance at 0.8 of white: highlights keep some headroom."""


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")


def _unit(x):
    """Clipped to [0, 1] with NaN and −Inf → 0, +Inf → 1 (float64 for NumPy; a tensor keeps its dtype)."""
    if _is_torch(x):
        return x.nan_to_num(nan=0.0, posinf=1.0, neginf=0.0).clamp(0.0, 1.0)
    return np.clip(np.nan_to_num(np.asarray(x, np.float64), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)


def srgb_encode(linear):
    """Linear [0, 1] → sRGB-encoded [0, 1] (NumPy array or torch tensor)."""
    x = _unit(linear)
    if _is_torch(x):
        import torch

        return torch.where(x <= ENCODE_KNEE, 12.92 * x, 1.055 * x.clamp(min=ENCODE_KNEE) ** (1 / 2.4) - 0.055)
    return np.where(x <= ENCODE_KNEE, 12.92 * x, 1.055 * np.power(np.maximum(x, ENCODE_KNEE), 1 / 2.4) - 0.055)


def srgb_decode(encoded):
    """sRGB-encoded [0, 1] → linear [0, 1] (NumPy array or torch tensor): 8-bit images, PNG previews, edit layers."""
    y = _unit(encoded)
    if _is_torch(y):
        import torch

        return torch.where(y <= DECODE_KNEE, y / 12.92, ((y.clamp(min=DECODE_KNEE) + 0.055) / 1.055) ** 2.4)
    return np.where(y <= DECODE_KNEE, y / 12.92, np.power((np.maximum(y, DECODE_KNEE) + 0.055) / 1.055, 2.4))


def srgb_decode_levels(levels: np.ndarray) -> np.ndarray:
    """8- or 16-bit sRGB levels → linear float32 through a table of every level: :func:`srgb_decode` of ``level /
    top`` (the same values, bit for bit) at the cost of one look-up per pixel (an import decodes thousands of images)."""
    if levels.dtype.kind != "u" or levels.dtype.itemsize > 2:
        raise ValueError(f"expected 8- or 16-bit levels, got {levels.dtype}")
    return np.take(_decode_table(levels.dtype.itemsize), levels)


@lru_cache(maxsize=2)
def _decode_table(itemsize: int) -> np.ndarray:
    top = 2 ** (8 * itemsize) - 1
    return srgb_decode(np.arange(top + 1, dtype=np.float32) / top).astype(np.float32)


def display_exposure(image: np.ndarray, mask: np.ndarray | None = None, level: float = DISPLAY_LEVEL) -> float:
    """The exposure that shows ``image``'s 99th-percentile luminance (mean RGB of its finite, positive pixels, over
    ``mask`` if given) at ``level``; 1 for an image with no light."""
    rgb = np.asarray(image, np.float64)[..., :3]
    lum = (rgb.reshape(-1, 3) if mask is None else rgb[np.asarray(mask, bool)]).mean(axis=1)
    lum = lum[np.isfinite(lum) & (lum > 0)]
    top = float(np.percentile(lum, DISPLAY_PERCENTILE)) if lum.size else 0.0
    return level / top if top > 0 else 1.0


def to_display(image: np.ndarray, exposure: float) -> np.ndarray:
    """Linear RGB → what a screen shows: × exposure, clipped, sRGB-encoded; (H, W, 3) float64 in [0, 1]."""
    return srgb_encode(np.asarray(image, np.float64)[..., :3] * exposure)
