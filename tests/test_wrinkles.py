"""The synthetic truth's wrinkles: a function of the pose (the tracked surface's compression), not of the clock,
with the slope of a buckled sheet (checked against the sheet's arc length, integrated independently)."""

import numpy as np
import pytest


def _grid(n: int = 9):
    """A flat n×n vertex sheet in the xy-plane, 1 m wide, UVs spanning the atlas."""
    c = np.linspace(0.0, 1.0, n)
    x, y = np.meshgrid(c, c, indexing="xy")
    vertices = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1).astype(np.float32)
    quads = [(r * n + k, r * n + k + 1, (r + 1) * n + k) for r in range(n - 1) for k in range(n - 1)]
    quads += [(r * n + k + 1, (r + 1) * n + k + 1, (r + 1) * n + k) for r in range(n - 1) for k in range(n - 1)]
    uvs = 0.02 + 0.96 * vertices[:, :2]
    return vertices, np.array(quads, np.int32), uvs.astype(np.float32)


def test_a_sheet_buckled_with_the_models_slope_has_the_compressed_length(llvm_variant):
    """The model's slope for a sheet squeezed by ε, less the drape's: a sinusoid of that slope over one wavelength λ
    is 1/(1 − ε) times longer than λ (numerical arc length in float64, to second order in ε)."""
    from gra_mi.capture.wrinkles import REST_SLOPE, WrinkleModel
    from gra_mi.render.atlas import UVAtlas

    rest, faces, uvs = _grid()
    atlas = UVAtlas.build(faces, uvs, 16)
    model = WrinkleModel(atlas, faces, rest, atlas.mask.reshape(16, 16).astype(np.float32))
    for strain in (0.005, 0.02, 0.05):
        slopes = model.slopes(rest * [1.0 - strain, 1.0, 1.0])[atlas.mask.reshape(16, 16)]
        slope = float(np.median(slopes)) - REST_SLOPE  # the buckling's part
        x = np.linspace(0.0, 1.0, 200_001)  # λ = 1
        dy = slope * np.cos(2 * np.pi * x)  # y = slope/(2π) · sin(2πx)
        arc = np.trapezoid(np.sqrt(1.0 + dy**2), x)
        assert 1.0 - 1.0 / arc == pytest.approx(strain, rel=0.1)


def test_compression_is_zero_for_rigid_motion_and_stretch_and_the_strain_for_a_squeeze():
    from gra_mi.capture.wrinkles import vertex_compression

    rest, faces, _ = _grid()
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    assert np.abs(vertex_compression(rest, rest @ rotation.T + [0.3, -1.0, 2.0], faces)).max() < 1e-6
    assert np.abs(vertex_compression(rest, rest * [1.3, 1.0, 1.0], faces)).max() == 0.0
    squeezed = rest * [0.8, 1.0, 1.0]
    np.testing.assert_allclose(vertex_compression(rest, squeezed, faces), 0.2, atol=1e-6)


def test_wrinkles_are_a_function_of_the_pose_not_of_the_frame_index(llvm_variant):
    """Same pose at frames 1 and 3 → the same normal map; the rest pose → the drape's slope on cloth, flat skin; a
    squeezed pose → REST_SLOPE + 2·√ε (ε = 0.2)."""
    from gra_mi.capture.wrinkles import MAX_SLOPE, REST_SLOPE, WrinkleModel
    from gra_mi.render.atlas import UVAtlas

    rest, faces, uvs = _grid()
    atlas = UVAtlas.build(faces, uvs, 32)
    cloth = (atlas.mask.reshape(32, 32) & (np.arange(32)[None, :] < 16)).astype(np.float32)  # left half cloth
    model = WrinkleModel(atlas, faces, rest, cloth)
    squeezed = rest * [0.8, 1.0, 1.0]
    frames = [rest, squeezed, rest.copy(), squeezed.copy()]
    maps = [model.normal_map(v) for v in frames]
    np.testing.assert_array_equal(maps[1], maps[3])
    np.testing.assert_array_equal(maps[0], maps[2])
    on_cloth, on_skin = cloth > 0.5, (cloth < 0.5) & atlas.mask.reshape(32, 32)
    np.testing.assert_allclose(model.slopes(rest)[on_cloth], REST_SLOPE, rtol=1e-6)
    np.testing.assert_allclose(model.slopes(squeezed)[on_cloth], min(REST_SLOPE + 2 * np.sqrt(0.2), MAX_SLOPE), rtol=1e-5)
    assert np.abs(model.slopes(squeezed)[on_skin]).max() == 0.0
    flat_skin = maps[1][on_skin]
    np.testing.assert_allclose(flat_skin, np.broadcast_to([0.5, 0.5, 1.0], flat_skin.shape), atol=1e-6)


def test_a_capture_made_without_wrinkles_is_never_posed_with_them(tmp_path):
    """`capture --without wrinkles`: its ground-truth scene keeps the flat normal map (nothing is read or set)."""
    from types import SimpleNamespace

    from gra_mi.capture.wrinkles import pose_capture_wrinkles

    params = {"bsdf.normalmap.data": "flat"}
    capture = SimpleNamespace(folder=tmp_path, ground_truth={"without": ["wrinkles"]})
    assert pose_capture_wrinkles(params, capture, 0) is False
    assert params == {"bsdf.normalmap.data": "flat"}
    no_maps = SimpleNamespace(folder=tmp_path, ground_truth={})  # a folder without gt/cloth.exr
    assert pose_capture_wrinkles(params, no_maps, 0) is False
