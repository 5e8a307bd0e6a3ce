"""The UV texture seen by a camera, with alpha = coverage: the image-space coarse render."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def rasterize_to_camera(ls, camera, texture: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Look the UV texture up through each pixel centre of ``camera``: (H, W, C + 1) with alpha = coverage.

    Bilinear in UV; texels outside ``mask`` do not bleed in (normalised by the mask's own interpolation). ``ls`` is the
    :class:`~gra_mi.stage.scene.LightstageScene` at the frame to show (it keeps each camera's rays on the device).
    """
    h, w = camera.height, camera.width
    si = ls.scene.ray_intersect(ls.camera_rays(camera), ray_flags=mi.RayFlags.UV, coherent=True)
    valid = si.is_valid()
    channels = texture.shape[2]
    weight = np.ones(texture.shape[:2] + (1,), np.float32) if mask is None else mask[..., None].astype(np.float32)
    tex = mi.Texture2f(
        mi.TensorXf(np.concatenate([texture * weight, weight], axis=2).astype(np.float32)), use_accel=False, wrap_mode=dr.WrapMode.Clamp
    )
    values = tex.eval(si.uv, valid)
    # Normalise by the interpolated mask and pack (H, W, C + 1) on the device: one transfer back.
    cov = values[channels]
    alpha = dr.select(valid, 1.0, 0.0)
    scale = dr.select(cov > 1e-6, alpha / dr.maximum(cov, 1e-6), 0.0)
    out = dr.zeros(mi.Float, h * w * (channels + 1))
    pixel = dr.arange(mi.UInt32, h * w) * (channels + 1)
    for c in range(channels):
        dr.scatter(out, values[c] * scale, pixel + c)
    dr.scatter(out, alpha, pixel + channels)
    return np.array(out, dtype=np.float32).reshape(h, w, channels + 1)
