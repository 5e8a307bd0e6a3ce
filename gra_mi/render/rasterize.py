"""The UV texture seen by a camera, with alpha = coverage: the image-space coarse render."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

RASTER_SAMPLES = 3
"""Sub-samples per pixel and axis (3: a 3×3 stratified grid). Edges and texture detail are box-filtered as the
path-traced capture's box reconstruction filter does; 1 is point sampling at the pixel centre (no anti-aliasing)."""


def rasterize_to_camera(ls, camera, texture: np.ndarray, mask: np.ndarray | None = None, samples: int = RASTER_SAMPLES) -> np.ndarray:
    """Look the UV texture up through ``samples``² stratified points of each pixel of ``camera``: (H, W, C + 1),
    premultiplied, with alpha = the fraction of the pixel's sub-samples that hit the subject (as Mitsuba's box filter).

    Bilinear in UV; texels outside ``mask`` do not bleed in (normalised by the mask's own interpolation). ``ls`` is the
    :class:`~gra_mi.stage.scene.LightstageScene` at the frame to show (it keeps each camera's rays on the device).
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    h, w = camera.height, camera.width
    channels = texture.shape[2]
    weight = np.ones(texture.shape[:2] + (1,), np.float32) if mask is None else mask[..., None].astype(np.float32)
    tex = mi.Texture2f(
        mi.TensorXf(np.concatenate([texture * weight, weight], axis=2).astype(np.float32)), use_accel=False, wrap_mode=dr.WrapMode.Clamp
    )
    accum = [dr.zeros(mi.Float, h * w) for _ in range(channels + 1)]
    strata = (np.arange(samples) + 0.5) / samples
    for oy in strata:
        for ox in strata:
            si = ls.subject_hits(ls.camera_rays(camera, (ox, oy)))
            valid = si.is_valid()
            values = tex.eval(si.uv, valid)
            # Normalise by the interpolated mask: chart borders keep their own colour.
            cov = values[channels]
            scale = dr.select(valid & (cov > 1e-6), 1.0 / dr.maximum(cov, 1e-6), 0.0)
            for c in range(channels):
                accum[c] += values[c] * scale
            accum[channels] += dr.select(valid, 1.0, 0.0)
            dr.eval(accum)
    # Pack (H, W, C + 1) on the device: one transfer back.
    out = dr.zeros(mi.Float, h * w * (channels + 1))
    pixel = dr.arange(mi.UInt32, h * w) * (channels + 1)
    inv = 1.0 / (samples * samples)
    for c in range(channels + 1):
        dr.scatter(out, accum[c] * inv, pixel + c)
    return np.array(out, dtype=np.float32).reshape(h, w, channels + 1)


def mesh_shape(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh", bsdf=None):
    """A Mitsuba mesh from arrays (no file): positions (V, 3) in metres, faces (F, 3)."""
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    mesh = mi.Mesh(name, len(vertices), len(faces), props=props)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(np.ascontiguousarray(vertices, np.float32).T))
    params["faces"] = dr.ravel(mi.Vector3u(np.ascontiguousarray(faces, np.uint32).T))
    params.update()
    return mesh


def silhouette(vertices: np.ndarray, faces: np.ndarray, camera) -> np.ndarray:
    """(H, W) bool: the pixels of ``camera`` whose centre ray hits the mesh (its reprojection, for a mask check)."""
    scene = mi.load_dict({"type": "scene", "mesh": mesh_shape(vertices, faces, "silhouette")})
    return np.array(scene.ray_test(camera.device_rays(), coherent=True)).reshape(camera.height, camera.width)
