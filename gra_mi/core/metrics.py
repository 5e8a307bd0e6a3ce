"""Image metrics, defined once for every report (fit, RelightNet validation, the refiner, the demo, the benchmark).

Conventions (docs/evaluation.md in spirit; the evaluation issue builds on these):

- Images are (H, W, C) NumPy arrays (C ≥ 3; only RGB is compared); ``mask`` (H, W) bool says which pixels count
  (the subject: one mask for every stage compared on a frame). Every masked pixel weighs the same, every channel too.
- **PSNR** = 10 log10(peak² / MSE) over the masked pixels and channels. ``peak``: 1 for display-referred images
  (tone-mapped into [0, 1]); for linear HDR radiance, :func:`linear_peak` — the reference's maximum over the mask.
  With a noisy reference that maximum is a firefly, which inflates PSNR: report :func:`brightness_error` beside it.
- **SSIM**: kornia's, 7×7 Gaussian window, on both images divided by ``peak`` and clamped to [0, 1], averaged over
  the channels and then over the masked pixels.
"""

from __future__ import annotations

import numpy as np


def _masked(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    rgb = np.asarray(image, np.float64)[..., :3]
    return rgb.reshape(-1, 3) if mask is None else rgb[np.asarray(mask, bool)]


def linear_peak(reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The PSNR peak of a linear HDR reference: its maximum over the mask (1 when the mask is empty)."""
    values = _masked(reference, mask)
    return float(values.max()) if values.size and values.max() > 0 else 1.0


def psnr(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, peak: float | None = None) -> float:
    """PSNR in dB over the masked pixels; ``peak`` None: :func:`linear_peak` of the reference. inf when equal."""
    peak = linear_peak(reference, mask) if peak is None else float(peak)
    a, b = _masked(image, mask), _masked(reference, mask)
    if a.size == 0:
        return float("inf")
    mse = float(np.mean(((a - b) / peak) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(1.0 / mse))


def ssim(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, peak: float | None = None) -> float:
    """SSIM averaged over the masked pixels (kornia, 7×7 window, images / ``peak`` clamped to [0, 1])."""
    import kornia
    import torch

    peak = linear_peak(reference, mask) if peak is None else float(peak)

    def tensor(x):
        return torch.from_numpy(np.ascontiguousarray(np.asarray(x, np.float32)[..., :3] / peak)).clamp(0, 1).permute(2, 0, 1)[None]

    per_pixel = kornia.metrics.ssim(tensor(image), tensor(reference), window_size=7).mean(dim=1)[0].numpy()
    weights = np.ones(per_pixel.shape, bool) if mask is None else np.asarray(mask, bool)
    return float(per_pixel[weights].mean()) if weights.any() else 1.0


def mean_l1(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean absolute difference over the masked pixels and channels (in the images' own units)."""
    return float(np.mean(np.abs(_masked(image, mask) - _masked(reference, mask))))


def relative_error(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, floor: float = 2e-2) -> float:
    """Mean |a − r| / max(r, floor) over the masked pixels (Mitsuba's test metric: dark pixels do not dominate)."""
    a, r = _masked(image, mask), _masked(reference, mask)
    return float(np.mean(np.abs(a - r) / np.maximum(r, floor)))


def relative_rmse(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """RMS difference over the masked pixels and channels, over the reference's mean there (a render's noise)."""
    a, r = _masked(image, mask), _masked(reference, mask)
    return float(np.sqrt(np.mean((a - r) ** 2)) / max(float(r.mean()), 1e-12))


def brightness_error(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Relative error of the total light over the mask: Σ image / Σ reference − 1 (−0.8: 80 % too dark)."""
    total = float(_masked(reference, mask).sum())
    return float(_masked(image, mask).sum()) / total - 1.0 if total > 0 else 0.0
