"""Pixel footprints: which texels a training pixel averages, and with what weights (the Adam stage's data term).

A capture's pixel is the box-filtered average of the surface it sees. The fit predicts it the same way: ``samples``²
sub-pixel rays per pixel, each landing on the UV atlas between four texels (bilinear weights, renormalised over the
texels the atlas holds), the rays' weights summed per texel. One Dr.Jit kernel traces the rays and computes their
corners (rays, corners and the facing test never visit the host); NumPy then merges each pixel's duplicate texels
with one small sort per pixel row. On a GPU the kernel runs there and only the corners come back.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.capture.dataset import load_fit_observation

FOOTPRINT_SAMPLES = 4  # 4 × 4 sub-pixel rays per pixel: the capture's box pixel filter
COVERED = 0.999  # a pixel is fitted only where the capture's alpha says the subject covers all of it
CORNERS = ((0, 0), (1, 0), (0, 1), (1, 1))


def pixel_footprints(ls, camera, atlas, alpha: np.ndarray, samples: int = FOOTPRINT_SAMPLES, geometry=None, min_view_cos: float = 0.0):
    """For each pixel fully covered in the capture (alpha = 1) and by all of its ``samples``² sub-pixel rays: the
    texels its rays land on, with bilinear weights. With the frame's texel ``geometry``, pixels whose footprint holds
    a texel seen more obliquely than ``min_view_cos`` are left out too. Returns (pixel flat indices, entries (pixel
    row, texel, weight)), entries in pixel order, each pixel's texels ascending, each pixel's weights summing to 1."""
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    ys, xs = np.nonzero(alpha >= COVERED)
    texel, weight, usable = _sample_corners(ls, camera, atlas, xs, ys, samples, geometry, min_view_cos)
    keep = np.flatnonzero(usable.reshape(xs.size, samples * samples).all(axis=1))
    per_pixel = samples * samples * len(CORNERS)
    rows, tex, summed = _merge_corners(texel.reshape(-1, per_pixel)[keep], weight.reshape(-1, per_pixel)[keep])
    flat_pixels = (ys * alpha.shape[1] + xs)[keep]
    return flat_pixels, (rows, tex, summed)


def _merge_corners(texel: np.ndarray, weight: np.ndarray):
    """(pixels, corners) texels (-1: none) and weights → entries (pixel row, texel, summed weight), each pixel's
    texels once, ascending. Each corner is one int64, texel in the high word and the weight's bits in the low: a sort
    of each row groups a pixel's texels with their weights riding along (many small sorts: far faster than one sort
    of all the view's keys)."""
    key = texel.astype(np.int64) << 32
    key |= weight.view(np.uint32)
    key.sort(axis=1)
    tex = key >> 32
    first = tex >= 0  # texel -1 (weight 0) sorts first in its row
    first[:, 1:] &= tex[:, 1:] != tex[:, :-1]
    valid = np.flatnonzero(tex.ravel() >= 0)
    starts = np.flatnonzero(first.ravel()[valid])
    weights = key.ravel()[valid].astype(np.uint32).view(np.float32).astype(np.float64)
    heads = valid[starts]
    return heads // texel.shape[1], tex.ravel()[heads], np.add.reduceat(weights, starts) if starts.size else np.zeros(0)


def _sample_corners(ls, camera, atlas, xs, ys, samples: int, geometry, min_view_cos: float):
    """One kernel over every sub-pixel ray: its four corner texels (-1 where the weight is 0), their weights (the
    ray's share of its pixel: bilinear, renormalised over the atlas's texels, over samples²) and whether the ray can
    be predicted (it hits the subject inside the atlas and, with ``geometry``, sees no corner too obliquely)."""
    count = xs.size * samples * samples
    if count == 0:
        return np.zeros((0, len(CORNERS)), np.int32), np.zeros((0, len(CORNERS)), np.float32), np.zeros(0, bool)
    lane = dr.arange(mi.UInt32, count)
    pixel, sub = lane // (samples * samples), lane % (samples * samples)
    x = mi.Float(dr.gather(mi.UInt32, mi.UInt32(xs.astype(np.uint32)), pixel)) + (mi.Float(sub % samples) + 0.5) / samples
    y = mi.Float(dr.gather(mi.UInt32, mi.UInt32(ys.astype(np.uint32)), pixel)) + (mi.Float(sub // samples) + 0.5) / samples
    ray = camera.rays_through(x, y)
    si = ls.subject_hits(ray)
    r = atlas.resolution
    u, v = si.uv.x * r - 0.5, si.uv.y * r - 0.5
    u0, v0 = mi.Int32(dr.floor(u)), mi.Int32(dr.floor(v))
    du, dv = u - mi.Float(u0), v - mi.Float(v0)
    grid = atlas.texel_grid_on_device()
    texels, weights = [], []
    for cu, cv in CORNERS:
        cell = dr.clip(v0 + cv, 0, r - 1) * r + dr.clip(u0 + cu, 0, r - 1)
        t = dr.gather(mi.Int32, grid, mi.UInt32(cell), si.is_valid())
        w = dr.select(si.is_valid() & (t >= 0), (du if cu else 1 - du) * (dv if cv else 1 - dv), 0.0)
        texels.append(t)
        weights.append(w)
    total = weights[0] + weights[1] + weights[2] + weights[3]
    usable = si.is_valid() & (total > 1e-6)  # a ray landing between charts cannot be predicted
    if geometry is not None:
        for t, w in zip(texels, weights, strict=True):
            index = mi.UInt32(dr.maximum(t, 0))
            to_camera = dr.normalize(ray.o - dr.gather(mi.Point3f, geometry.position, index))
            usable &= (w <= 0) | (dr.dot(dr.gather(mi.Vector3f, geometry.normal, index), to_camera) >= min_view_cos)
    share = dr.rcp(dr.maximum(total, 1e-12) * (samples * samples))
    texels = [dr.select(w > 0, t, -1) for t, w in zip(texels, weights, strict=True)]
    weights = [w * share for w in weights]
    dr.eval(texels, weights, usable)
    texel = np.stack([np.asarray(t) for t in texels], axis=1)
    weight = np.stack([np.asarray(w) for w in weights], axis=1)
    return texel, np.ascontiguousarray(weight, np.float32), np.asarray(usable)


def unique_below(values: np.ndarray, bound: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(values, return_inverse=True)`` for integers in [0, ``bound``) (texel indices): marked and ranked,
    no sort."""
    present = np.zeros(bound, bool)
    present[values] = True
    rank = np.cumsum(present) - 1
    return np.flatnonzero(present), rank[values]


def view_footprints(fitter, frame_index: int, pose: int, cam_name: str, min_view_cos: float) -> dict[str, np.ndarray] | None:
    """The arrays of a :class:`~gra_mi.fit.optimize.ViewBatch` for one camera and frame (None: no pixel to fit);
    pixels that see a texel more obliquely than ``min_view_cos`` are left out."""
    cam = fitter.stage.camera(cam_name)
    image = load_fit_observation(fitter.capture, cam_name, frame_index)
    fitter.ls.set_frame(pose)
    geometry = fitter.relighter.geometry(pose)
    flat_pixels, (pix, tex, wgt) = pixel_footprints(
        fitter.ls, cam, fitter.atlas, image[..., 3], geometry=geometry, min_view_cos=min_view_cos
    )
    if flat_pixels.size == 0:
        return None
    lanes, entry_lane = unique_below(tex, fitter.atlas.num_texels)
    observed = image[..., :3].reshape(-1, 3)[flat_pixels].astype(np.float32)
    return {
        "lanes": lanes.astype(np.uint32), "entry_lane": entry_lane.astype(np.uint32), "entry_pixel": pix.astype(np.uint32),
        "entry_weight": wgt.astype(np.float32), "observed": observed,
        "weight": np.array(1.0 / max(float(observed.astype(np.float64).mean()), 1e-6)),
    }  # fmt: skip
