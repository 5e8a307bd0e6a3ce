"""Pixel footprints (gra_mi/fit/footprints.py) against an analytic reference: a textured plane seen by a tilted camera,
each sub-pixel ray intersected with the plane in float64 by hand, no ray tracer involved."""

from __future__ import annotations

from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest

RES = 32
SAMPLES = 4


def _uv(p):  # the plane's UV map: x, y ∈ [-1, 1] → a sub-square of the atlas (texels outside it are not the atlas's)
    return 0.1 + 0.25 * (p[..., 0] + 1), 0.2 + 0.25 * (p[..., 1] + 1)


@pytest.fixture
def plane(variant):
    import mitsuba as mi

    from gra_mi.render.atlas import UVAtlas
    from gra_mi.stage.envmap import rotation_y
    from gra_mi.stage.lightstage import Camera

    corners = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    uvs = np.stack(_uv(corners), axis=1)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    mesh = mi.Mesh("plane", 4, 2, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(corners.ravel().astype(np.float32))
    params["faces"] = mi.UInt32(faces.ravel().astype(np.uint32))
    params["vertex_texcoords"] = mi.Float(uvs.ravel().astype(np.float32))
    params.update()
    scene = mi.load_dict({"type": "scene", "plane": mesh})
    atlas = UVAtlas.build(faces, uvs, RES)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation_y(17.0), [0.613, -0.071, -2.37]
    camera = Camera("tilted", 41, 31, 29.3, 28.7, 20.31, 15.17, pose)

    def subject_hits(ray, flags=mi.RayFlags.UV, coherent=True):  # the plane is the scene's only shape: the subject
        return scene.ray_intersect(ray, ray_flags=flags, coherent=coherent)

    return SimpleNamespace(ls=SimpleNamespace(scene=scene, subject_hits=subject_hits), atlas=atlas, camera=camera)


def _reference(camera, atlas, alpha, texel_cos=None, min_view_cos=0.0):
    """Float64, by hand: {flat pixel: {texel: weight}} for the pixels every sub-pixel ray of which lands on the plane
    between texels the atlas holds (and, with ``texel_cos``, sees none of them more obliquely than ``min_view_cos``)."""
    grid = atlas.texel_grid()
    out = {}
    for y, x in zip(*np.nonzero(alpha >= 0.999), strict=True):
        weights, usable = defaultdict(float), True
        for j in range(SAMPLES):
            for i in range(SAMPLES):
                d = camera.rotation @ [
                    (x + (i + 0.5) / SAMPLES - camera.cx) / camera.fx,
                    (y + (j + 0.5) / SAMPLES - camera.cy) / camera.fy,
                    1.0,
                ]
                p = camera.position - camera.position[2] / d[2] * d
                su, sv = (c * RES - 0.5 for c in _uv(p))
                u0, v0 = int(np.floor(su)), int(np.floor(sv))
                corner = {}
                for cu in (0, 1):
                    for cv in (0, 1):
                        w = (su - u0 if cu else 1 - su + u0) * (sv - v0 if cv else 1 - sv + v0)
                        t = grid[min(max(v0 + cv, 0), RES - 1) * RES + min(max(u0 + cu, 0), RES - 1)]
                        if t >= 0 and w > 0:
                            corner[t] = corner.get(t, 0.0) + w
                total = sum(corner.values())
                usable &= bool(np.all(np.abs(p[:2]) <= 1)) and total > 1e-6
                for t, w in corner.items():
                    weights[t] += w / total / SAMPLES**2
                    usable &= texel_cos is None or texel_cos[t] >= min_view_cos
        if usable:
            out[int(y * alpha.shape[1] + x)] = weights
    return out


def _as_dict(flat_pixels, entries):
    out = {int(p): {} for p in flat_pixels}
    for row, texel, weight in zip(*entries, strict=True):
        out[int(flat_pixels[row])][int(texel)] = weight
    return out


def _assert_same_footprints(got, expected):
    assert got.keys() == expected.keys()
    for pixel, weights in expected.items():
        present = {t: w for t, w in weights.items() if w > 1e-6}  # float32 may drop or keep a corner of weight ~0
        assert {t: w for t, w in got[pixel].items() if w > 1e-6}.keys() == present.keys(), pixel
        np.testing.assert_allclose([got[pixel][t] for t in present], list(present.values()), atol=2e-6)
        assert sum(got[pixel].values()) == pytest.approx(1.0, abs=1e-6)


def test_footprints_match_the_analytic_plane(plane):
    from gra_mi.fit.footprints import pixel_footprints

    alpha = np.ones((plane.camera.height, plane.camera.width))
    alpha[:4] = 0.7  # partly covered pixels are not fitted
    flat_pixels, entries = pixel_footprints(plane.ls, plane.camera, plane.atlas, alpha, SAMPLES)
    expected = _reference(plane.camera, plane.atlas, alpha)
    # the case holds every kind of pixel: kept, off the plane, over the atlas's edge, not covered
    assert 200 < len(expected) < 0.8 * alpha.size and np.all(flat_pixels >= 4 * alpha.shape[1])
    _assert_same_footprints(_as_dict(flat_pixels, entries), expected)
    rows, texels, _ = entries
    assert np.all(np.diff(rows) >= 0) and np.all(np.diff(texels)[np.diff(rows) == 0] > 0)  # pixel order, texels ascending


def test_footprints_leave_out_pixels_that_see_a_texel_too_obliquely(plane):
    import mitsuba as mi

    from gra_mi.fit.footprints import pixel_footprints
    from gra_mi.render.atlas import texel_uvs

    uv = texel_uvs(RES)[plane.atlas.texel_index]
    position = np.stack([(uv[:, 0] - 0.1) / 0.25 - 1, (uv[:, 1] - 0.2) / 0.25 - 1, np.zeros(len(uv))], axis=1)
    bent = np.stack([0.8 * np.sin(3 * position[:, 0]), np.zeros(len(uv)), -np.ones(len(uv))], axis=1)  # a wavy normal map
    normal = bent / np.linalg.norm(bent, axis=1, keepdims=True)
    to_camera = plane.camera.position - position
    cos = np.sum(normal * to_camera, axis=1) / np.linalg.norm(to_camera, axis=1)
    alpha = np.ones((plane.camera.height, plane.camera.width))
    every = _reference(plane.camera, plane.atlas, alpha)
    seen = np.sort(cos[sorted({t for weights in every.values() for t in weights})])
    k = int(np.argmax(np.diff(seen)[len(seen) // 4 : 3 * len(seen) // 4])) + len(seen) // 4
    threshold = float(seen[k] + seen[k + 1]) / 2  # mid-gap: no texel is within float32 noise of it
    geometry = SimpleNamespace(position=mi.Point3f(*position.T.astype(np.float32)), normal=mi.Vector3f(*normal.T.astype(np.float32)))
    flat_pixels, entries = pixel_footprints(plane.ls, plane.camera, plane.atlas, alpha, SAMPLES, geometry, threshold)
    expected = _reference(plane.camera, plane.atlas, alpha, cos, threshold)
    assert 0 < len(expected) < len(every) - 20
    _assert_same_footprints(_as_dict(flat_pixels, entries), expected)


def test_footprints_of_nothing(plane):
    from gra_mi.fit.footprints import pixel_footprints

    flat_pixels, (rows, texels, weights) = pixel_footprints(plane.ls, plane.camera, plane.atlas, np.zeros((31, 41)), SAMPLES)
    assert flat_pixels.size == rows.size == texels.size == weights.size == 0
    with pytest.raises(ValueError, match="samples"):
        pixel_footprints(plane.ls, plane.camera, plane.atlas, np.ones((31, 41)), 0)


def test_footprints_compile_once_for_every_view(plane):
    # Camera, pixel count and the pixels themselves are kernel inputs: a fit's hundreds of views share one kernel (a
    # Python float baked into it, or Mitsuba's ray intersection fed from NumPy buffers, made one LLVM compile per view).
    import drjit as dr

    from gra_mi.fit.footprints import pixel_footprints

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        rng = np.random.default_rng(3)
        for step in range(6):
            camera = plane.camera
            camera = type(camera)(
                camera.name, camera.width, camera.height, camera.fx + step, camera.fy, camera.cx - step, camera.cy, camera.camera_to_world
            )
            alpha = (rng.random((camera.height, camera.width)) < 0.3 + 0.1 * step).astype(float)
            pixel_footprints(plane.ls, camera, plane.atlas, alpha, SAMPLES)
        kernels = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT and k["operation_count"] > 50}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(kernels) <= 2, len(kernels)  # (a NumPy buffer's alignment may pick one of two)


def test_unique_below_is_numpys_unique():
    # The footprints' texels become the view's lanes through unique_below (marked and ranked, no sort): the same keys
    # and inverse as np.unique.
    from gra_mi.fit.footprints import unique_below

    rng = np.random.default_rng(5)
    for values in (
        rng.integers(0, 500, 300),
        rng.integers(0, 7, 50),
        np.array([3]),
        np.zeros(0, np.int64),
        np.full(9, 4),
        np.array([499, 0]),
    ):
        expected_keys, expected_inverse = np.unique(values, return_inverse=True)
        keys, inverse = unique_below(values, 500)
        np.testing.assert_array_equal(keys, expected_keys)
        np.testing.assert_array_equal(inverse, expected_inverse)
