"""Image metrics, defined once for every report (fit, RelightNet validation, the refiner, the demo, the benchmarks).

:func:`compare` is *the* comparison of a render with its truth, and the one every report prints:

- **Mask**: :func:`subject_mask` — the pixels the truth's subject covers (alpha ≥ 0.5); background is never scored.
- **Display PSNR**: both images are shown at one exposure, the truth's (:func:`display_exposure`: its 99th
  percentile of luminance over the mask at 0.8), sRGB-encoded and clipped to [0, 1] (:func:`to_display`), then
  PSNR with peak 1. A firefly in a noisy truth cannot move the peak, and what is compared is what a person sees.
- **SSIM** on the same display images (kornia, 7×7 Gaussian window), outside the mask zeroed in both.
- **Brightness error**: Σ render / Σ truth − 1 over the mask, in linear radiance (−0.8: 80 % too dark). PSNR and
  SSIM are blind to an exposure error of a few per cent; this is not, so it is reported beside them.

The lower-level functions take images as (H, W, C) NumPy arrays (C ≥ 3; only RGB is compared) and a ``mask``
(H, W) bool of the pixels that count; every masked pixel weighs the same, every channel too. :func:`psnr` with
``peak`` None uses :func:`linear_peak` (the reference's maximum), which suits only noise-free linear references.
"""

from __future__ import annotations

import numpy as np

from gra_mi.core.color import display_exposure, to_display


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


def subject_mask(reference: np.ndarray) -> np.ndarray:
    """The pixels the truth's subject covers: alpha ≥ 0.5 (RGBA), else any positive channel (RGB)."""
    reference = np.asarray(reference)
    if reference.shape[-1] >= 4:
        return reference[..., 3] >= 0.5
    return reference[..., :3].max(axis=-1) > 0


def display_psnr(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    """The PSNR of :func:`compare` alone (both images shown at the truth's exposure); NaN if ``image`` is not finite
    on the mask (a broken render scores as broken, not as the black its display shows)."""
    if not np.isfinite(_masked(image, mask)).all():
        return float("nan")
    exposure = display_exposure(reference, mask)
    return psnr(to_display(image, exposure), to_display(reference, exposure), mask, peak=1.0)


def compare(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """The comparison every report prints: display PSNR, display SSIM and brightness error of ``image`` against the
    truth ``reference`` over ``mask`` (None: :func:`subject_mask` of the reference). See the module doc. Every score
    is NaN when ``image`` is not finite on the mask."""
    mask = subject_mask(reference) if mask is None else np.asarray(mask, bool)
    if not np.isfinite(_masked(image, mask)).all():
        return {"psnr": float("nan"), "ssim": float("nan"), "brightness": float("nan")}
    exposure = display_exposure(reference, mask)
    shown, truth = to_display(image, exposure), to_display(reference, exposure)
    outside = ~mask[..., None]
    return {
        "psnr": psnr(shown, truth, mask, peak=1.0),  # display_psnr's value, from the images already shown
        "ssim": ssim(np.where(outside, 0.0, shown), np.where(outside, 0.0, truth), mask, peak=1.0),
        "brightness": brightness_error(image, reference, mask),
    }


FLIP_PPD = 67.0  # FLIP's default viewing condition: 0.7 m from a 0.7 m wide 3840-pixel monitor


def flip_map(image: np.ndarray, reference: np.ndarray, exposure: float) -> np.ndarray:
    """Per-pixel LDR-ꟻLIP (NVIDIA's ``flip-evaluator``) of ``image`` against ``reference`` as both are shown at
    ``exposure`` (:func:`to_display`): (H, W) in [0, 1], 0 where they look the same."""
    import flip_evaluator

    shown = to_display(image, exposure).astype(np.float32)
    truth = to_display(reference, exposure).astype(np.float32)
    error, _, _ = flip_evaluator.evaluate(
        truth, shown, "LDR", inputsRGB=True, applyMagma=False, computeMeanError=False, parameters={"ppd": FLIP_PPD}
    )
    return np.asarray(error, np.float64)[..., 0]


def flip(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean LDR-ꟻLIP over the mask (None: :func:`subject_mask`), both shown at the truth's exposure as in :func:`compare`."""
    mask = subject_mask(reference) if mask is None else np.asarray(mask, bool)
    error = flip_map(image, reference, display_exposure(reference, mask))
    return float(error[mask].mean()) if mask.any() else 0.0


def temporal_error(frames: list[np.ndarray], truths: list[np.ndarray], masks: list[np.ndarray], exposure: float, breaks=()) -> float:
    """Flicker: the mean absolute difference between a video's frame-to-frame change and the truth's, in display
    values (:func:`to_display` at one ``exposure`` for the whole video), over the pixels the subject covers in both
    frames of each pair. 0 when the video changes exactly as the truth does (a constant error, in colour or
    brightness, costs nothing); a frame alternating by ±a around the truth scores 2a. NaN for fewer than 2 frames.
    ``breaks``: frames that do not follow their predecessor (a gap in the capture lies between): no pair."""
    if len(frames) < 2:
        return float("nan")
    shown = [to_display(f, exposure) for f in frames]
    truth = [to_display(t, exposure) for t in truths]
    errors = []
    for t in (t for t in range(1, len(frames)) if t not in breaks):
        both = np.asarray(masks[t], bool) & np.asarray(masks[t - 1], bool)
        if both.any():
            errors.append(float(np.abs((shown[t] - shown[t - 1]) - (truth[t] - truth[t - 1]))[both].mean()))
    return float(np.mean(errors)) if errors else float("nan")
