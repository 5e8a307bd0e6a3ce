"""Numerical stability on hard cases: finite, bounded, and in agreement with float64 references."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.stage import envmap as em
from gra_mi.stage.lightstage import default_lightstage

from .test_brdf import ref_eval_cos


def f64(*arrays):
    import drjit as dr

    return [dr.llvm.ad.Array3f64(*a.T) if a.ndim == 2 else dr.llvm.ad.Float64(a) for a in arrays]


def test_extreme_roughness_and_grazing_angles_match_float64(plugins):
    import drjit as dr

    from gra_mi.render import brdf

    theta = np.radians([0.0, 30.0, 60.0, 85.0, 89.0, 89.99])
    phi = np.radians([0.0, 90.0, 180.0, 270.0])
    t, p = np.meshgrid(theta, phi, indexing="ij")
    dirs = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], -1).reshape(-1, 3)
    wi, wo = np.repeat(dirs, len(dirs), 0), np.tile(dirs, (len(dirs), 1))
    albedo = np.full((len(wi), 3), 0.7)
    for r in (0.0, 1e-4, 1.0):
        rough = np.full(len(wi), r)
        ours = np.array(brdf.eval_cos(*f64(albedo, rough, wi, wo))).T
        ref = ref_eval_cos(albedo, rough, wi, wo)
        assert np.isfinite(ours).all() and ours.min() >= 0
        finite = np.isfinite(ref)
        rel = np.abs(ours - ref)[finite] / np.maximum(np.abs(ref[finite]), 1e-30)
        assert rel.max() <= 1e-5, (r, rel.max())
        dr.eval()


def test_gradients_at_vanishing_roughness(plugins):
    # d(f cos)/dr: finite everywhere; below the clamp (r² < α_min) it is exactly 0, above it matches central
    # finite differences in float64.
    import drjit as dr

    from gra_mi.render import brdf

    rng = np.random.default_rng(0)
    wi = np.array([[0.3, 0.1, 0.95]])
    wi /= np.linalg.norm(wi)
    wo = rng.normal(size=(64, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    wo[0] = wi[0] * [-1, -1, 1]  # the mirror direction: the sharpest case
    wi = np.repeat(wi, 64, 0)
    albedo = np.full((64, 3), 0.5)
    for r in (0.0, 1e-3, 0.02, 0.05, 0.1, 0.3):
        a_, r_, wi_, wo_ = f64(albedo, np.full(64, r), wi, wo)
        dr.enable_grad(r_)
        value = brdf.eval_cos(a_, r_, wi_, wo_)
        dr.backward(dr.sum(value.x))
        grad = np.array(dr.grad(r_))
        assert np.isfinite(grad).all()
        if r * r < brdf.ALPHA_MIN:
            assert np.all(grad == 0)
            continue
        eps = 1e-6 * max(r, 1e-3)

        def at(x):
            return np.array(brdf.eval_cos(*f64(albedo, np.full(64, x), wi, wo))).T[:, 0]

        fd = (at(r + eps) - at(r - eps)) / (2 * eps)
        np.testing.assert_allclose(grad, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def _plane_scene(led_positions, intensities):
    import mitsuba as mi

    scene = {"type": "scene", "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(5.0)}}
    for i, (p, inten) in enumerate(zip(led_positions, intensities, strict=True)):
        scene[f"led{i}"] = {
            "type": "point",
            "position": list(map(float, p)),
            "intensity": {"type": "rgb", "value": list(map(float, inten))},
        }
    return mi.load_dict(scene)


def _texels(points, normals, geo_normals):
    import mitsuba as mi

    from gra_mi.render.atlas import TexelGeometry

    as3 = lambda a, t: t(*np.asarray(a, np.float32).T)  # noqa: E731
    return TexelGeometry(as3(points, mi.Point3f), as3(normals, mi.Vector3f), as3(geo_normals, mi.Vector3f), "test")


def test_shading_normal_disagreeing_with_geometry_does_not_leak_light(plugins):
    from gra_mi.render.leds import LedLayout
    from gra_mi.render.shading import shade_texels
    from gra_mi.render.visibility import compute_visibility

    # A floor texel (geometric normal +Y) whose skinned shading normal leans 60° toward +X.
    lean = np.radians(60.0)
    n = np.array([[np.sin(lean), np.cos(lean), 0.0]])
    leds = np.array([[1.0, -0.2, 0.0], [-1.0, 0.3, 0.0], [0.2, 1.0, 0.0]])  # below floor; behind the shading normal; fine
    intensity = np.ones((3, 3))
    scene = _plane_scene(leds, intensity)
    geom = _texels([[0.0, 0.0, 0.0]], n, [[0.0, 1.0, 0.0]])
    layout = LedLayout(leds, np.zeros(3))
    bits = int(np.array(compute_visibility(scene, geom, layout))[0])
    assert bits == 0b100, bin(bits)
    for k in range(3):
        one = np.zeros((3, 3))
        one[k] = 1.0
        radiance = shade_texels(
            geom, compute_visibility(scene, geom, layout), layout, one, np.full((1, 3), 0.5), np.full(1, 0.4), [0.0, 2.0, 2.0]
        ).radiance
        assert np.isfinite(radiance).all() and (radiance.max() > 0) == (k == 2)


def test_led_almost_touching_the_surface(plugins):
    from gra_mi.render.leds import LedLayout
    from gra_mi.render.shading import shade_texels
    from gra_mi.render.visibility import compute_visibility

    for height in (1e-2, 2e-3):
        led = np.array([[0.0, height, 0.0]])
        scene = _plane_scene(led, np.ones((1, 3)))
        p = np.array([[0.01, 0.0, 0.0]])  # a texel next to the LED's foot point
        geom = _texels(p, [[0.0, 1.0, 0.0]], [[0.0, 1.0, 0.0]])
        vis = compute_visibility(scene, geom, LedLayout(led, np.zeros(3)))
        assert int(np.array(vis)[0]) == 1
        cam = np.array([0.0, 1.0, 1.0])
        radiance = shade_texels(
            geom, vis, LedLayout(led, np.zeros(3)), np.ones((1, 3)), np.full((1, 3), 0.6), np.full(1, 0.5), cam
        ).radiance
        to_led = led - p
        d2 = np.sum(to_led**2)
        wo = to_led / np.sqrt(d2)
        wi = (cam - p) / np.linalg.norm(cam - p)
        # World +Y is the normal: in the local frame z = y. Rotate (x, y, z) -> (x, z, y) (any frame with z = n works).
        local = lambda v: v[:, [0, 2, 1]]  # noqa: E731
        expected = ref_eval_cos(np.full((1, 3), 0.6), np.full(1, 0.5), local(wi), local(wo)) / d2
        assert np.isfinite(radiance).all()
        np.testing.assert_allclose(radiance, expected, rtol=1e-4)


def test_extreme_envmap_sun_and_bad_pixels_stay_finite_and_conserve_energy():
    stage = default_lightstage()
    h = 64
    env = np.full((h, 2 * h, 3), 0.2, np.float32)
    env[h // 2 :] = 0.05  # ground
    env[20, 40] = 0.2e6  # a sun a million times the sky
    env[3, 7, 1] = np.nan
    env[5, 9] = np.inf
    env[50, 60, 2] = -3.0
    with pytest.raises(Exception, match="1 NaN and 3 Inf"):
        em.validate_envmap(env, "sun.exr")
    fixed = em.validate_envmap(env, "sun.exr", repair=True)
    for cells in em.CELL_MODES:
        lighting = em.envmap_to_leds(fixed, stage, cells=cells)
        assert np.isfinite(lighting.drive).all() and lighting.drive.min() >= 0
        assert lighting.drive.max() == pytest.approx(stage.max_led_intensity)
        raw = em.envmap_to_leds(fixed, stage, normalize=False, cells=cells)
        led_flux = (raw.radiant_intensity(stage) / stage.led_distances()[:, None] ** 2).sum(axis=0)
        env_flux = (fixed * em.pixel_solid_angles(h, 2 * h)[..., None]).sum(axis=(0, 1))
        np.testing.assert_allclose(led_flux, env_flux, rtol=1e-5)
        # The sun dominates: its cell holds most of the flux.
        share = raw.radiant_intensity(stage).sum(axis=1) / stage.led_distances() ** 2
        assert np.sort(share)[-3:].sum() / share.sum() > 0.5


def test_degenerate_and_sliver_triangles(plugins):
    import drjit as dr

    from gra_mi.render.atlas import TexelGeometry, UVAtlas
    from gra_mi.subject.sequence import vertex_normals

    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 1, 0], [2, 0, 0], [2, 1e-9, 0]], dtype=np.float64)
    faces = np.array([[0, 1, 2], [1, 3, 2], [3, 4, 1], [1, 5, 6]])  # a normal pair, a degenerate (3 == 4), a sliver
    uvs = np.array([[0.05, 0.05], [0.45, 0.05], [0.05, 0.45], [0.45, 0.45], [0.45, 0.45], [0.9, 0.05], [0.9, 0.06]])
    normals = vertex_normals(vertices, faces)
    assert np.isfinite(normals).all()
    atlas = UVAtlas.build(faces, uvs, 32)
    geom = TexelGeometry.from_frame(atlas, vertices, normals)
    for v in (geom.position, geom.normal, geom.geo_normal):
        assert np.isfinite(np.array(v)).all()
    np.testing.assert_allclose(np.linalg.norm(np.array(geom.geo_normal), axis=0), 1.0, atol=1e-5)
    dr.eval()


def test_uv_seam_texels_agree_and_unseen_texels_are_flagged(plugins):
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.scene import LightstageScene

    from .conftest import SCENES

    ls = LightstageScene.load(SCENES / "tiny_lightstage.xml", frame=2)
    relighter = Relighter(ls, resolution=256)
    view = relighter.render(2, 0, np.full((ls.stage.num_leds, 3), 1.0))
    rad = relighter.atlas.scatter(view.shading.radiance)
    mask = relighter.atlas.mask
    # The torso chart spans u ∈ [0.01, 0.49]; its seam runs along u = 0.01 and u = 0.49 (the same points in 3D).
    left, right = int(0.01 * 256) + 1, int(0.49 * 256) - 1
    rows = np.flatnonzero(mask[:, left] & mask[:, right])[10:-10]
    a, b = rad[rows, left].sum(axis=1), rad[rows, right].sum(axis=1)
    lit = (a > 1e-3) & (b > 1e-3)
    assert lit.sum() > 20
    assert np.median(np.abs(a[lit] - b[lit]) / np.maximum(a[lit], b[lit])) < 0.05
    # Texels facing away from the camera are flagged; the rasterised view is finite everywhere.
    assert 0.2 < view.shading.facing_camera.mean() < 0.9
    assert np.isfinite(view.image).all()


def test_accumulating_2000_leds_matches_float64(plugins):
    import tempfile
    from pathlib import Path

    from gra_mi.core.io import atomic_write_text
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.scene import LightstageScene, subject_scene_xml, write_rig
    from gra_mi.subject.sequence import save_sequence, tiny_subject

    tmp = Path(tempfile.mkdtemp())
    stage = default_lightstage(num_leds=2000, num_cameras=1, width=48, height=32)
    write_rig(stage, tmp / "rig")
    save_sequence(tiny_subject(2), tmp / "subject")
    atomic_write_text(tmp / "scene.xml", subject_scene_xml("rig", "subject"))
    ls = LightstageScene.load(tmp / "scene.xml")
    relighter = Relighter(ls, resolution=32)
    intensities = np.random.default_rng(0).uniform(1e-3, 2e-3, (2000, 3))
    view = relighter.render(0, 0, intensities)
    bits = np.array(relighter.visibility(0), dtype=np.uint32).reshape(-1, relighter.atlas.num_texels)
    p, n = np.array(view.geometry.position).T.astype(np.float64), np.array(view.geometry.normal).T.astype(np.float64)
    cam = stage.cameras[0].position
    checked = 0
    for t in np.random.default_rng(1).choice(relighter.atlas.num_texels, 20, replace=False):
        visible = np.array([(bits[k // 32, t] >> (k % 32)) & 1 for k in range(2000)], bool)
        if visible.sum() < 500:
            continue
        checked += 1
        # Local frame with z = n (any tangent basis: the BRDF is isotropic).
        z = n[t]
        x = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        basis = np.stack([x, y, z])
        to_led = stage.led_positions[visible] - p[t]
        d2 = np.sum(to_led**2, axis=1)
        wo = (to_led / np.sqrt(d2)[:, None]) @ basis.T
        wi = np.repeat((((cam - p[t]) / np.linalg.norm(cam - p[t])) @ basis.T)[None], len(wo), 0)
        f = ref_eval_cos(np.repeat(relighter.albedo[t][None].astype(np.float64), len(wo), 0), np.full(len(wo), 0.5), wi, wo)
        expected = np.sum(f * intensities[visible] / d2[:, None], axis=0)
        np.testing.assert_allclose(view.shading.radiance[t], expected, rtol=1e-4)
    assert checked >= 5, "texels that see 500+ LEDs were checked"
