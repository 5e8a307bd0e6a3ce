"""UV-space rendering: atlas, visibility cache, texel shading against the image-space integrator, relight CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gra_mi.stage.lightstage import olat_pattern, uniform_pattern

from .conftest import SCENES
from .test_cli import run_cli

TINY = SCENES / "tiny_lightstage.xml"


@pytest.fixture
def tiny(variant):
    from gra_mi.render.plugins import register_plugins
    from gra_mi.stage.scene import LightstageScene

    register_plugins()
    return LightstageScene.load(TINY, frame=2)


def test_atlas_covers_the_uv_layout(tiny):
    from gra_mi.render.atlas import UVAtlas

    seq = tiny.sequence
    atlas = UVAtlas.build(seq.faces, seq.uvs, 64)
    # The tiny subject's charts fill [0.01, 0.49] and [0.51, 0.99] in u, [0.02, 0.98] in v.
    assert 0.75 < atlas.mask.mean() < 0.95
    assert not atlas.mask[:, 32].any(), "the gap between the charts stays empty"
    np.testing.assert_allclose(atlas.barycentrics.sum(axis=1), 1.0, atol=1e-9)
    assert atlas.barycentrics.min() >= 0
    # Baking the UVs themselves reproduces the texel centres.
    baked = atlas.bake_vertex_attribute(seq.uvs.astype(np.float64))
    centres = (np.arange(64) + 0.5) / 64
    np.testing.assert_allclose(baked[atlas.mask][:, 0], np.broadcast_to(centres[None, :], (64, 64))[atlas.mask], atol=1e-5)
    np.testing.assert_allclose(baked[atlas.mask][:, 1], np.broadcast_to(centres[:, None], (64, 64))[atlas.mask], atol=1e-5)


def test_visibility_cache_keys_the_whole_led_layout(tiny, tmp_path):
    """Positions, stage centre and near/far field all change the bits, so all three key the cache: a far-field rig
    with another centre (the same LED positions) is traced again, never served the first one's bits."""
    from gra_mi.render.atlas import TexelGeometry, UVAtlas
    from gra_mi.render.leds import LedLayout
    from gra_mi.render.visibility import VisibilityCache, compute_visibility

    seq = tiny.sequence
    geom = TexelGeometry.from_frame(UVAtlas.build(seq.faces, seq.uvs, 32), seq.vertices[2], seq.normals[2])
    near, far = LedLayout.of(tiny.stage), LedLayout.of(tiny.stage, far_field=True)
    moved = LedLayout(tiny.stage.led_positions, tiny.stage.center + np.array([0.0, 0.8, 0.0]), far_field=True)
    assert len({near.digest, far.digest, moved.digest}) == 3
    cache = VisibilityCache(tmp_path)
    bits = {name: np.array(cache.get(tiny.scene, geom, leds)) for name, leds in (("far", far), ("moved", moved))}
    assert cache.misses == 2 and not np.array_equal(bits["far"], bits["moved"])
    np.testing.assert_array_equal(bits["moved"], np.array(compute_visibility(tiny.scene, geom, moved)))
    again = VisibilityCache(tmp_path)  # from disk
    np.testing.assert_array_equal(np.array(again.get(tiny.scene, geom, moved)), bits["moved"])
    assert again.hits == 1


def test_visibility_matches_one_ray_per_pair(tiny):
    import mitsuba as mi

    from gra_mi.render.atlas import TexelGeometry, UVAtlas
    from gra_mi.render.leds import LedLayout
    from gra_mi.render.visibility import RAY_EPSILON, compute_visibility

    seq = tiny.sequence
    atlas = UVAtlas.build(seq.faces, seq.uvs, 64)
    geom = TexelGeometry.from_frame(atlas, seq.vertices[2], seq.normals[2])
    leds = tiny.stage.led_positions
    bits = np.array(compute_visibility(tiny.scene, geom, LedLayout.of(tiny.stage))).reshape(-1, atlas.num_texels)
    # Reference: texel-major rays built in NumPy, one scene.ray_test per (texel, LED) pair.
    rng = np.random.default_rng(0)
    texels = rng.choice(atlas.num_texels, 300, replace=False)
    p, n, ng = (np.array(a).T[texels].astype(np.float64) for a in (geom.position, geom.normal, geom.geo_normal))
    pp = np.repeat(p, len(leds), 0)
    nn, gg = np.repeat(n, len(leds), 0), np.repeat(ng, len(leds), 0)
    target = np.tile(leds, (len(texels), 1))
    d = target - pp
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    facing = (np.sum(nn * d, 1) > 0) & (np.sum(gg * d, 1) > 0)
    origin = pp + gg * RAY_EPSILON
    ray = mi.Ray3f(mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    ray.maxt = mi.Float((dist * (1 - RAY_EPSILON) - RAY_EPSILON).astype(np.float32))  # (Ray3f's third argument is its time)
    blocked = np.array(tiny.scene.ray_test(ray))
    expected = (facing & ~blocked).reshape(len(texels), len(leds))
    ours = np.stack([(bits[k // 32, texels] >> (k % 32)) & 1 for k in range(len(leds))], axis=1).astype(bool)
    assert (ours != expected).mean() < 1e-3
    assert 0.2 < expected.mean() < 0.8, "some LEDs are hidden, some seen"
    assert (expected & ~facing.reshape(expected.shape)).sum() == 0


def test_cache_reuses_visibility_across_lighting_and_cameras(tiny, tmp_path):
    from gra_mi.render.relighter import Relighter

    relighter = Relighter(tiny, resolution=64, cache_dir=tmp_path / "vis")
    a = relighter.render(3, 0, uniform_pattern(tiny.stage, 0.5))
    relighter.render(3, 1, olat_pattern(tiny.stage, 7))
    relighter.render(3, 2, uniform_pattern(tiny.stage, 0.2))
    assert relighter.cache.misses == 1 and relighter.cache.hits == 2
    # On disk: a new relighter (another process) finds it without tracing.
    other = Relighter(tiny, resolution=64, cache_dir=tmp_path / "vis")
    b = other.render(3, 0, uniform_pattern(tiny.stage, 0.5))
    assert other.cache.misses == 0
    np.testing.assert_array_equal(a.image, b.image)
    # A cache file cut short (a full disk, a killed copy) is traced again and rewritten, not a crash.
    for path in (tmp_path / "vis").glob("vis_*.npy"):
        path.write_bytes(path.read_bytes()[:40])
    third = Relighter(tiny, resolution=64, cache_dir=tmp_path / "vis")
    np.testing.assert_array_equal(third.render(3, 0, uniform_pattern(tiny.stage, 0.5)).image, a.image)
    assert third.cache.misses == 1


def test_an_olat_traces_its_one_led_and_later_lightings_add_only_theirs(tiny, tmp_path, monkeypatch):
    """No work for LEDs that are off: an OLAT's render traces one LED's rays (the image as with every LED traced);
    another OLAT traces one more; a lighting of every LED then traces the rest, and the merged bits are a full
    trace's, bit for bit, which alone goes to disk."""
    from gra_mi.render import visibility
    from gra_mi.render.relighter import Relighter

    traced = []
    original = visibility.compute_visibility

    def counting(scene, geom, leds, texels=None, lit=None):
        traced.append(leds.num_leds if lit is None else len(lit))
        return original(scene, geom, leds, texels, lit)

    monkeypatch.setattr(visibility, "compute_visibility", counting)
    full, lean = Relighter(tiny, resolution=64), Relighter(tiny, resolution=64, cache_dir=tmp_path / "vis")
    full.visibility(3, False)
    for led in (7, 40):
        np.testing.assert_array_equal(
            lean.render(3, 0, olat_pattern(tiny.stage, led)).image, full.render(3, 0, olat_pattern(tiny.stage, led)).image
        )
    assert traced == [tiny.stage.num_leds, 1, 1] and not list((tmp_path / "vis").glob("vis_*"))
    lean.render(3, 0, olat_pattern(tiny.stage, 7) + olat_pattern(tiny.stage, 40))  # covered: nothing traced
    uniform = uniform_pattern(tiny.stage, 0.5)
    np.testing.assert_array_equal(lean.render(3, 0, uniform).image, full.render(3, 0, uniform).image)
    assert traced == [tiny.stage.num_leds, 1, 1, tiny.stage.num_leds - 2]
    np.testing.assert_array_equal(np.array(lean.visibility(3, False)), np.array(full.visibility(3, False)))
    assert len(list((tmp_path / "vis").glob("vis_*.npy"))) == 1


def test_cached_visibility_leaves_the_mesh_where_it_is(tiny, tmp_path):
    """The mesh moves (a BVH rebuild) only when a frame's bits must be traced, and they are traced at that frame."""
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.visibility import compute_visibility

    relighter = Relighter(tiny, resolution=64, cache_dir=tmp_path / "vis")
    traced = np.array(relighter.visibility(3))
    assert tiny.frame == 3 and relighter.cache.misses == 1
    tiny.set_frame(0)
    np.testing.assert_array_equal(np.array(relighter.visibility(3)), traced)
    assert tiny.frame == 0 and relighter.cache.misses == 1
    tiny.set_frame(3)
    np.testing.assert_array_equal(np.array(compute_visibility(tiny.scene, relighter.geometry(3), relighter.leds())), traced)


def test_shading_is_linear_in_led_intensities_and_off_leds_cost_nothing(tiny):
    from gra_mi.render.relighter import Relighter

    relighter = Relighter(tiny, resolution=64)
    one = relighter.render(2, 0, olat_pattern(tiny.stage, 3)).shading.radiance
    two = relighter.render(2, 0, olat_pattern(tiny.stage, 40)).shading.radiance
    both = relighter.render(2, 0, olat_pattern(tiny.stage, 3) + olat_pattern(tiny.stage, 40)).shading.radiance
    np.testing.assert_allclose(both, one + two, rtol=1e-5, atol=1e-7)
    dark = relighter.render(2, 0, np.zeros((tiny.stage.num_leds, 3)))
    assert dark.shading.radiance.max() == 0 and dark.image[..., :3].max() == 0


def test_leds_that_are_on_packed_per_lane_sum_to_every_led_on(tiny):
    """A pattern's LEDs are packed into their own visibility words (shading.lane_visibility); with every LED on the
    cache's own layout is walked. Two complementary patterns of 33 and 31 LEDs (two packed words and one) must sum to
    every LED on, for the whole atlas and for a subset of lanes in any order (a fit's view, a bounce's sources)."""
    import mitsuba as mi

    from gra_mi.render.relighter import Relighter
    from gra_mi.render.shading import TexelLedLoop

    relighter = Relighter(tiny, resolution=64)
    rng = np.random.default_rng(1)
    intensity = rng.uniform(0.5, 2.0, (tiny.stage.num_leds, 3))
    first = np.zeros(tiny.stage.num_leds, bool)
    first[rng.choice(tiny.stage.num_leds, 33, replace=False)] = True
    patterns = {"all": intensity, "a": intensity * first[:, None], "b": intensity * ~first[:, None]}
    shaded = {k: relighter.render(2, 0, p).shading for k, p in patterns.items()}
    for part in ("diffuse_unit", "specular"):
        whole = getattr(shaded["all"], part)
        np.testing.assert_allclose(getattr(shaded["a"], part) + getattr(shaded["b"], part), whole, rtol=1e-5, atol=1e-6 * whole.max())
    lanes = rng.permutation(relighter.atlas.num_texels)[:500].repeat(2)
    geom, vis, leds = relighter.geometry(2), relighter.visibility(2, False), relighter.leds(False)
    camera = tiny.stage.camera(0).position
    rough = mi.Float(relighter.roughness[lanes].astype(np.float32))
    run = {k: [np.array(x) for x in TexelLedLoop.build(geom, vis, lanes, leds, p, camera).run(rough)] for k, p in patterns.items()}
    for k in range(2):
        np.testing.assert_allclose(run["a"][k] + run["b"][k], run["all"][k], rtol=1e-5, atol=1e-6 * run["all"][k].max())
        np.testing.assert_allclose(run["all"][k].T, getattr(shaded["all"], ("diffuse_unit", "specular")[k])[lanes], rtol=1e-5, atol=1e-7)
    dark = TexelLedLoop.build(geom, vis, lanes, leds, np.zeros_like(intensity), camera).run(rough)
    assert all(np.array(x).max() == 0 for x in dark)
    # Repeated lanes (a bounce's rays share sources) packed once per texel and spread: the very same bits.
    distinct = tuple(mi.UInt32(a.astype(np.uint32)) for a in np.unique(lanes, return_inverse=True))
    for p in patterns.values():
        once = TexelLedLoop.build(geom, vis, lanes, leds, p, camera, distinct=distinct)
        per_lane = TexelLedLoop.build(geom, vis, lanes, leds, p, camera)
        np.testing.assert_array_equal(np.array(once.visibility), np.array(per_lane.visibility))


def test_led_loop_outputs_come_back_evaluated_together(tiny):
    """Each output of a Dr.Jit loop evaluated on its own (a NumPy read, the fit's backward pass) runs the whole loop
    again: TexelLedLoop.run evaluates them at once, held or not (``hold``), with or without the derivative, and the
    un-held loop (a bounce's, run once) gives the held one's values."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.relighter import Relighter
    from gra_mi.render.shading import TexelLedLoop

    relighter = Relighter(tiny, resolution=64)
    lanes = np.random.default_rng(2).permutation(relighter.atlas.num_texels)[:300]
    geom, vis, leds = relighter.geometry(2), relighter.visibility(2, False), relighter.leds(False)
    intensity = uniform_pattern(tiny.stage, 0.5)
    rough = mi.Float(relighter.roughness[lanes].astype(np.float32))
    held, lazy = (TexelLedLoop.build(geom, vis, lanes, leds, intensity, tiny.stage.camera(0).position, hold=h) for h in (True, False))
    for loop in (held, lazy):
        for derivative in (False, True):
            parts = loop.run(rough, roughness_derivative=derivative)
            assert len(parts) == 2 + derivative
            assert all(c.state == dr.VarState.Evaluated for part in parts for c in part)
    for a, b in zip(held.run(rough, True), lazy.run(rough, True), strict=True):
        np.testing.assert_allclose(np.array(a), np.array(b), rtol=1e-6, atol=1e-9)


def test_joined_led_loops_give_each_loop_its_own_values(tiny):
    """A fit's step joins its views' loops into one kernel (TexelLedLoop.concat): each lane must walk its own loop's
    LEDs (its frame's visibility, its lighting: every LED, a pattern, one OLAT, none; its own light after the first
    bounce) and get, bit for bit, what its own loop gives; joined loops join again."""
    import mitsuba as mi

    from gra_mi.render.relighter import Relighter
    from gra_mi.render.shading import TexelLedLoop

    relighter = Relighter(tiny, resolution=64)
    rng = np.random.default_rng(3)
    n, m = tiny.stage.num_leds, relighter.atlas.num_texels
    intensity = rng.uniform(0.5, 2.0, (n, 3))
    olat, pattern = np.zeros((n, 3)), intensity * (rng.uniform(size=n) < 0.5)[:, None]
    olat[7] = 3.0
    cases = [(0, 0, intensity, None), (2, 1, pattern, None), (1, 2, olat, (rng.uniform(size=(m, 3)), rng.uniform(size=(m, 3)))),
             (2, 0, np.zeros((n, 3)), None), (0, 1, intensity * 0.5, None)]  # fmt: skip
    loops, roughness = [], []
    for frame, cam, lighting, indirect in cases:
        lanes = rng.choice(m, int(rng.integers(50, 400)))
        geom, vis = relighter.geometry(frame), relighter.visibility(frame, False)
        loops.append(TexelLedLoop.build(geom, vis, lanes, relighter.leds(False), lighting, tiny.stage.camera(cam).position, indirect))
        roughness.append(rng.uniform(0.05, 0.9, lanes.size).astype(np.float32))
    own = [[np.array(x) for x in loop.run(mi.Float(r), roughness_derivative=True)] for loop, r in zip(loops, roughness, strict=True)]
    joined = TexelLedLoop.concat([TexelLedLoop.concat(loops[:2]), TexelLedLoop.concat(loops[2:])])
    together = [np.array(x) for x in joined.run(mi.Float(np.concatenate(roughness)), roughness_derivative=True)]
    starts = np.cumsum([0] + [loop.count for loop in loops])
    for k, parts in enumerate(own):
        for part, whole in zip(parts, together, strict=True):
            np.testing.assert_array_equal(whole[:, starts[k] : starts[k + 1]], part)
    assert any(np.abs(part).max() > 0 for part in own[2]) and all(np.abs(part).max() == 0 for part in own[3][1:])


def test_uv_render_agrees_with_image_space_render(tiny, tmp_path):
    import mitsuba as mi

    from gra_mi.core.io import write_exr
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.scene import camera_xml

    relighter = Relighter(tiny, resolution=256)
    u = (np.arange(256) + 0.5) / 256
    # Spatially varying but smooth: resampling a noisy roughness map would differ through the BRDF's nonlinearity.
    relighter.roughness_tex = (0.3 + 0.5 * u[None, :, None] * u[:, None, None]).astype(np.float32)
    relighter.roughness = relighter.atlas.gather(relighter.roughness_tex)[:, 0]
    intensities = uniform_pattern(tiny.stage, 0.5)
    cam = tiny.stage.cameras[1]
    ours = relighter.render(2, 1, intensities).image
    write_exr(tmp_path / "albedo.exr", relighter.albedo_tex)
    write_exr(tmp_path / "rough.exr", relighter.roughness_tex)
    emitters = "".join(
        f'<emitter type="point"><point name="position" value="{", ".join(map(str, p))}"/><rgb name="intensity" value="{i[0]}"/></emitter>'
        for p, i in zip(tiny.stage.led_positions, intensities, strict=True)
    )
    ply = SCENES / "subjects" / "tiny" / "frames" / "frame_0002.ply"
    xml = (
        f'<scene version="3.0.0">{camera_xml(cam, "64")}{emitters}<shape type="ply"><string name="filename" value="{ply}"/>'
        f'<bsdf type="gra_microfacet"><texture type="bitmap" name="albedo"><string name="filename" value="{tmp_path / "albedo.exr"}"/></texture>'
        f'<texture type="bitmap" name="roughness"><string name="filename" value="{tmp_path / "rough.exr"}"/></texture></bsdf></shape></scene>'
    )
    reference = np.array(mi.render(mi.load_string(xml), integrator=mi.load_dict({"type": "gra_onebounce"}), spp=256))
    covered = (ours[..., 3] > 0.5) & (reference[..., 3] > 0.999)
    rel = np.abs(ours[..., :3] - reference[..., :3])[covered] / np.maximum(reference[..., :3][covered], 2e-2)
    # Resampling error: the UV path interpolates shaded radiance, the image path interpolates the material.
    assert rel.mean() < 0.01 and np.median(rel) < 5e-3, (rel.mean(), np.median(rel))


def test_texel_geometry_matches_float64_numpy(tiny):
    """Texel positions, shading normals and geometric normals (interpolated on the device) against float64 NumPy."""
    from gra_mi.render.relighter import Relighter

    relighter = Relighter(tiny, resolution=64)
    atlas, geom = relighter.atlas, relighter.geometry(1)
    vertices, normals = tiny.sequence.vertices[1].astype(np.float64), tiny.sequence.normals[1].astype(np.float64)
    b, f = atlas.barycentrics, atlas.faces
    p = np.einsum("mk,mkc->mc", b, vertices[f])
    n = np.einsum("mk,mkc->mc", b, normals[f])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ng = np.cross(vertices[f[:, 1]] - vertices[f[:, 0]], vertices[f[:, 2]] - vertices[f[:, 0]])
    ng /= np.linalg.norm(ng, axis=1, keepdims=True)
    for ours, ref in ((geom.position, p), (geom.normal, n), (geom.geo_normal, ng)):
        np.testing.assert_allclose(np.array(ours).T, ref, atol=2e-6)


def test_rasterise_matches_a_numpy_bilinear_lookup(tiny):
    """The device-side rasterisation against float64 NumPy: bilinear in UV (texel centres, clamped), normalised by the
    interpolated mask, alpha = the pixel hits the subject. The camera's rays are built once and reused."""
    import mitsuba as mi

    from gra_mi.render.rasterize import rasterize_to_camera

    cam = tiny.stage.cameras[0]
    rng = np.random.default_rng(0)
    texture = rng.random((32, 32, 3)).astype(np.float32)
    mask = rng.random((32, 32)) > 0.3
    image = rasterize_to_camera(tiny, cam, texture, mask, samples=1)
    assert tiny.camera_rays(cam) is tiny.camera_rays(cam)
    si = tiny.scene.ray_intersect(tiny.camera_rays(cam), ray_flags=mi.RayFlags.UV, coherent=True)
    uv = np.array(si.uv, dtype=np.float64).T
    hit = np.array(si.is_valid())

    def bilinear(grid, uv):
        r = grid.shape[0]
        x = np.clip(uv[:, 0] * r - 0.5, 0, r - 1)
        y = np.clip(uv[:, 1] * r - 0.5, 0, r - 1)
        x0, y0 = np.minimum(np.floor(x).astype(int), r - 2), np.minimum(np.floor(y).astype(int), r - 2)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        g = grid.astype(np.float64)
        return (g[y0, x0] * (1 - fx) + g[y0, x0 + 1] * fx) * (1 - fy) + (g[y0 + 1, x0] * (1 - fx) + g[y0 + 1, x0 + 1] * fx) * fy

    weight = mask[..., None].astype(np.float64)
    num, cov = bilinear(texture * weight, uv), bilinear(weight, uv)
    expected = np.where(cov > 1e-6, num / np.maximum(cov, 1e-6), 0.0) * hit[:, None]
    got = image.reshape(-1, 4)
    assert hit.any() and not hit.all()
    np.testing.assert_array_equal(got[:, 3], hit.astype(np.float32))
    ok = cov[:, 0] > 1e-3  # where the mask barely reaches, the ratio of two tiny numbers is ill-conditioned
    np.testing.assert_allclose(got[ok, :3], expected[ok], atol=2e-4)


def test_subpixel_rays_match_the_camera_model(tiny):
    """Rays through any point of a pixel, built on the device, against float64 NumPy from the intrinsics."""
    cam = tiny.stage.cameras[1]
    ray = tiny.camera_rays(cam, (0.2, 0.9))
    ys, xs = np.mgrid[0 : cam.height, 0 : cam.width]
    d_cam = np.stack([(xs + 0.2 - cam.cx) / cam.fx, (ys + 0.9 - cam.cy) / cam.fy, np.ones(xs.shape)], axis=-1).reshape(-1, 3)
    d = d_cam @ cam.rotation.T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(np.array(ray.d).T, d, atol=1e-6)
    np.testing.assert_allclose(np.array(ray.o).T.reshape(-1, 3)[0], cam.position, atol=1e-6)
    origin, centre = cam.pixel_rays()
    np.testing.assert_allclose(np.array(tiny.camera_rays(cam).d).T, centre.reshape(-1, 3), atol=1e-6)
    np.testing.assert_allclose(np.array(tiny.camera_rays(cam).o).T.reshape(-1, 3)[0], origin, atol=1e-6)


def test_rig_cameras_share_one_tracing_kernel(tiny):
    """Every rig camera's kept centre rays are traced by one kernel. (Rays made from NumPy arrays gave Mitsuba's
    tracing kernel code that depends on the buffers' alignment: an LLVM compile for about every camera.)"""
    import drjit as dr
    import mitsuba as mi

    tiny.stage.cameras[:] = [cam.resized(4.0) for cam in tiny.stage.cameras]  # large buffers, as a real rig's

    def trace(cam):
        si = tiny.scene.ray_intersect(tiny.camera_rays(cam), ray_flags=mi.RayFlags.UV, coherent=True)
        dr.eval(si.uv, si.is_valid())

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for cam in tiny.stage.cameras:
            dr.eval(tiny.camera_rays(cam))
        trace(tiny.stage.cameras[0])  # (the first trace numbers its constants in another order)
        dr.kernel_history()
        for cam in tiny.stage.cameras:
            trace(cam)
        kernels = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(tiny.stage.cameras) > 3 and len(kernels) == 1, kernels


def test_antialiased_alpha_is_the_coverage_mitsuba_renders(tiny):
    """Alpha of the 3×3 rasterisation against Mitsuba's own box-filtered alpha at 1024 spp: partial at silhouettes,
    exact (0 or 1) away from them; the colour is premultiplied by it."""
    import mitsuba as mi

    from gra_mi.render.rasterize import rasterize_to_camera

    cam = tiny.stage.cameras[0]
    texture = np.full((32, 32, 3), 0.5, np.float32)
    image = rasterize_to_camera(tiny, cam, texture)
    integrator = mi.load_dict({"type": "direct"})  # the film is RGBA with a box filter: alpha is the coverage
    alpha_ref = np.array(mi.render(tiny.scene, sensor=tiny.sensor_index(cam.name), integrator=integrator, spp=1024), np.float64)[..., 3]
    alpha = image[..., 3]
    edge = (alpha_ref > 0.02) & (alpha_ref < 0.98)
    assert edge.sum() > 20 and ((alpha > 0) & (alpha < 1)).sum() > 0.5 * edge.sum()
    assert np.abs(alpha - alpha_ref).mean() < 0.01 and np.abs(alpha - alpha_ref)[edge].mean() < 0.12
    np.testing.assert_allclose(image[..., :3], np.repeat(0.5 * alpha[..., None], 3, axis=2), atol=1e-5)


def test_far_field_converges_to_near_field_for_a_distant_rig(tiny):
    from gra_mi.render.relighter import DEFAULT_ROUGHNESS, Relighter
    from gra_mi.render.shading import led_cell_roughness

    relighter_near = Relighter(tiny, resolution=64)
    relighter_far = Relighter(tiny, resolution=64, far_field=True)
    pattern = uniform_pattern(tiny.stage, 0.5)
    near = relighter_near.render(2, 0, pattern).shading.radiance
    far = relighter_far.render(2, 0, pattern).shading.radiance
    lit = near.sum(axis=1) > 1e-3
    error_2m = np.mean(np.abs(far - near)[lit]) / np.mean(near[lit])
    assert error_2m > 0.01, "a 2 m stage is near field: the approximation shows"
    # Push the LEDs 100x further away (intensities scaled by 100² to keep the irradiance): the two agree.
    stage = tiny.stage
    original = stage.led_positions.copy()
    stage.led_positions = stage.center + (original - stage.center) * 100.0
    try:
        # Far field also widens each lobe to the LEDs' spacing (it samples an environment): near field gets the same lobes.
        widened = led_cell_roughness(np.full((64, 64, 1), DEFAULT_ROUGHNESS, np.float32), stage.num_leds)
        far_rig = Relighter(tiny, resolution=64, roughness=widened)
        near_far = far_rig.render(2, 0, pattern * 100.0**2).shading.radiance
        far_far = Relighter(tiny, resolution=64, far_field=True).render(2, 0, pattern * 100.0**2).shading.radiance
    finally:
        stage.led_positions = original
    assert np.mean(np.abs(far_far - near_far)[lit]) / np.mean(near_far[lit]) < 0.02


def test_relight_cli(tmp_path, llvm_variant):
    from gra_mi.core.io import read_exr, write_exr

    write_exr(tmp_path / "sky.exr", np.ones((16, 32, 3), np.float32))
    out = run_cli(
        "relight",
        str(TINY),
        "--frames",
        "0:3",
        "--cameras",
        "0,cam02",
        "--envmap",
        str(tmp_path / "sky.exr"),
        "--olat",
        "4",
        "--uv-resolution",
        "64",
        "--save-uv",
        "--background",
        "--fidelity",
        "--out",
        str(tmp_path / "r"),
    )
    assert out.returncode == 0, out.stderr
    assert "visibility traced 6 time(s)" in out.stdout  # 3 frames × (the envmap far field, the OLAT near field)
    image = read_exr(tmp_path / "r" / "sky" / "cam02" / "frame_0001.exr")
    assert image.shape == (64, 96, 4) and image[..., :3].max() > 0
    for name in ("uv_radiance", "uv_normal", "uv_position", "uv_view_dir", "uv_mask"):
        assert (tmp_path / "r" / "olat004" / "cam00" / f"{name}_0002.exr").exists()
    assert (tmp_path / "r" / "sky" / "cam00.mp4").exists()
    fidelity = json.loads((tmp_path / "r" / "envmap_fidelity.json").read_text())
    assert set(fidelity) == {"sky"} and fidelity["sky"]["normals"] >= 200
    assert fidelity["sky"]["max_rel_error"] < 0.02  # a constant sky: every normal sees the same irradiance; 64 LEDs match it
    bad = run_cli("relight", str(TINY), "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "at least one --envmap" in bad.stderr


def test_visibility_traced_only_where_the_jobs_cameras_see_gives_the_same_images(tiny):
    """A relight's cameras cannot see texels behind them, outside their images or facing away: tracing only the rest
    changes no pixel, and traces about half the texels."""
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.visibility import texels_seen_by

    rng = np.random.default_rng(3)
    intensities = rng.uniform(0.2, 1.0, (tiny.stage.num_leds, 3))
    full, culled = Relighter(tiny, resolution=64), Relighter(tiny, resolution=64)
    culled.only_for(["cam01"])
    for frame in (0, 3):
        for far in (False, True):
            np.testing.assert_array_equal(
                culled.render(frame, "cam01", intensities, far_field=far).image,
                full.render(frame, "cam01", intensities, far_field=far).image,
            )
    seen = texels_seen_by(full.geometry(3), [tiny.stage.camera("cam01")])
    assert 0.2 < len(seen) / int(full.atlas.mask.sum()) < 0.7, "one camera sees about half the body"
    # Every texel traced after that is a new trace; a later job with any cameras reuses it.
    misses = culled.cache.misses
    culled.only_for(None)
    culled.visibility(3, False)
    assert culled.cache.misses == misses + 1
    culled.only_for(["cam02"])
    culled.visibility(3, False)
    assert culled.cache.misses == misses + 1


def test_cache_on_disk_serves_culled_jobs_and_holds_a_bounded_number(tiny, tmp_path):
    """A full trace another process left on disk (a fit's cache) serves a later culled job without tracing; ``keep``
    bounds how many frames stay in memory, the rest read back from disk unchanged."""
    from gra_mi.render.relighter import Relighter

    fit = Relighter(tiny, resolution=32, cache_dir=tmp_path / "vis")
    full_bits = {frame: np.array(fit.visibility(frame, False)) for frame in (0, 1, 2)}
    relight = Relighter(tiny, resolution=32, cache_dir=tmp_path / "vis")
    relight.only_for(["cam01"])
    relight.cache.keep = 2
    for frame in (0, 1, 2, 0):
        np.testing.assert_array_equal(np.array(relight.visibility(frame, False)), full_bits[frame])
    assert relight.cache.misses == 0 and len(relight.cache._memory) == 2


def test_columns_reads_vectors_of_any_size_without_compiling(llvm_variant):
    """``np.array`` of a 3-vector compiles a kernel per array size (its offsets are literals), which a fit with
    thousands of differently sized views kept in memory; :func:`columns` reads the components and compiles none."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.core.runtime import columns

    rng = np.random.default_rng(1)
    values = {n: rng.random((n, 3)).astype(np.float32) for n in (5, 97, 1000)}
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clear
        for expected in values.values():
            np.testing.assert_array_equal(columns(mi.Color3f(*expected.T)), expected)
        assert not [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


def test_training_sees_a_texture_as_the_evaluation_rasteriser_shows_it(tiny):
    """RelightNet's training lookup (torch ``sample_texture`` with the atlas mask) equals the evaluation's device
    rasteriser at one sample per pixel, chart borders included: no seam the network could learn to brighten. Without
    the mask a constant texture comes out darker on the border pixels (the empty texels beyond a chart bleed in)."""
    import torch

    from gra_mi.render.atlas import UVAtlas
    from gra_mi.render.bridge import camera_uv_grid, sample_texture
    from gra_mi.render.rasterize import rasterize_to_camera

    cam = tiny.stage.cameras[0]
    atlas = UVAtlas.build(tiny.sequence.faces, tiny.sequence.uvs, 32)
    mask = atlas.mask
    texture = np.random.default_rng(1).random((32, 32, 3)).astype(np.float32) * mask[..., None]
    grid, hit = camera_uv_grid(tiny, cam)
    as_torch = torch.from_numpy(texture).permute(2, 0, 1)[None]
    mask_torch = torch.from_numpy(mask.astype(np.float32))[None, None]
    trained = sample_texture(as_torch, grid, mask_torch)[0].permute(1, 2, 0).numpy()
    shown = rasterize_to_camera(tiny, cam, texture, mask, samples=1)
    on = hit[0, 0].numpy() > 0.5
    assert on.sum() > 100
    np.testing.assert_allclose(trained[on], shown[..., :3][on], atol=1e-4)
    flat = torch.from_numpy(np.repeat(mask[None, None].astype(np.float32), 3, axis=1))
    np.testing.assert_allclose(sample_texture(flat, grid, mask_torch)[0, :, on].numpy(), 1.0, atol=1e-5)
    assert sample_texture(flat, grid)[0, :, on].numpy().min() < 0.9, "unmasked, the border darkens"
