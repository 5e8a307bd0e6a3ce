"""Light after the first bounce (gra_mi.render.bounce): against Mitsuba's own ``path`` integrator where the body lights
itself, the hull test's exactness, the operator's cache, culled jobs, linearity and bad options."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.stage.lightstage import uniform_pattern

from .conftest import SCENES

TINY = SCENES / "tiny_lightstage.xml"


@pytest.fixture
def tiny(variant):
    from gra_mi.render.plugins import register_plugins
    from gra_mi.stage.scene import LightstageScene

    register_plugins()
    return LightstageScene.load(TINY, frame=2)


def relighters(ls, resolution, bounces=(1, 2), rays=32, albedo=None, roughness=None, **kwargs):
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    return {
        b: Relighter(ls, resolution, albedo, roughness, transport=LightTransport(bounces=b, bounce_rays=rays), **kwargs) for b in bounces
    }


def smooth_maps(resolution: int, albedo: float = 0.8):
    u = (np.arange(resolution) + 0.5) / resolution
    roughness = (0.3 + 0.5 * u[None, :, None] * u[:, None, None]).astype(np.float32)
    return np.full((resolution, resolution, 3), albedo, np.float32), roughness


def test_two_bounces_match_mitsuba_path_on_the_tiny_subject(tiny, tmp_path):
    from gra_mi.render.path_reference import bounce_errors, path_reference

    albedo, roughness = smooth_maps(128)
    rel = relighters(tiny, 128, bounces=(1, 2, 3), albedo=albedo, roughness=roughness)
    leds = uniform_pattern(tiny.stage, 0.5)
    for cam in (0, 1):
        ours = {b: r.render(2, cam, leds).image for b, r in rel.items()}
        path = {d: path_reference(rel[1], 2, cam, leds, max_depth=d, spp=256, folder=tmp_path) for d in (2, 3, 4)}
        two = bounce_errors(ours[1], ours[2], path[2], path[3])
        three = bounce_errors(ours[1], ours[3], path[2], path[4])
        assert two["bias_one"] < -0.008, two  # the light after the first bounce is there to be found
        assert abs(two["bias_more"]) < 0.003, two
        assert abs(three["bias_more"]) < 0.003, three


@pytest.fixture(scope="module")
def posed_anny(tmp_path_factory):
    """The anny body in the hard cases' poses, in the default rig (building anny takes ~1.5 min on a fresh machine)."""
    from gra_mi.render.path_reference import HARD_CASE_CLIP, HARD_CASE_FRAMES
    from gra_mi.subject.anny_body import anny_sequence
    from gra_mi.subject.sequence import save_sequence

    folder = tmp_path_factory.mktemp("anny_hard")
    save_sequence(anny_sequence([HARD_CASE_CLIP], HARD_CASE_FRAMES), folder / "subject")
    return folder / "subject"


@pytest.mark.slow
def test_hard_cases_match_mitsuba_path(llvm_variant, posed_anny, tmp_path):
    """An armpit, the face under raised arms, the inner thighs, a hand by the hip, each lit by a point light close
    to the body: two bounces against Mitsuba's path with max_depth 3 over the subject and where the one-bounce
    light is ≥ 10 % short (the issue's goals: 1 % and 3 %)."""
    from gra_mi.render.path_reference import HARD_CASES, bounce_errors, path_reference
    from gra_mi.render.plugins import register_plugins
    from gra_mi.stage.scene import LightstageScene

    register_plugins()
    ls = LightstageScene.load(SCENES / "body_lightstage.xml", spp=1, subject=str(posed_anny))
    rel = relighters(ls, 512)
    off = np.zeros((ls.stage.num_leds, 3))
    dark_blocks = 0
    for case in HARD_CASES:
        camera, light = case.camera(), case.point_light()
        one, two = (rel[b].render(case.frame, camera, off, [light]).image for b in (1, 2))
        paths = [path_reference(rel[1], case.frame, camera, off, [light], d, 1024, tmp_path / case.name) for d in (2, 3)]
        e = bounce_errors(one, two, *paths)
        assert e["bias_one"] < -0.012, (case.name, e)  # one bounce misses ≥ 1.2 % of the light here
        assert abs(e["bias_more"]) <= 0.01, (case.name, e)
        if e["dark_blocks"]:
            assert e["dark_block_error_more"] <= 0.03 and e["added_light_error"] <= 0.01, (case.name, e)
        dark_blocks += e["dark_blocks"]
    assert dark_blocks >= 2  # the block goal was checked somewhere


def test_hull_test_finds_every_texel_a_ray_can_reach(tiny):
    """Texels the convex-hull test leaves out trace nothing: tracing them anyway hits nothing."""
    from gra_mi.render.bounce import texels_that_see_the_body, trace_operator

    (rel,) = relighters(tiny, 64, bounces=(2,), rays=64).values()
    geom, seq = rel.geometry(2), tiny.sequence
    tiny.set_frame(2)
    candidates = texels_that_see_the_body(geom, seq.vertices[2])
    everyone = trace_operator(tiny.scene, tiny.subject_shape(), geom, rel.atlas, seq.uvs, seq.faces, np.arange(rel.atlas.num_texels), 64)
    assert 0 < len(candidates) < rel.atlas.num_texels
    assert np.isin(np.unique(everyone.receivers), candidates).all()
    assert len(np.unique(everyone.receivers)) > 0.3 * len(candidates)  # and most of them do see the body


def test_light_only_adds_and_scales_linearly(tiny):
    rel = relighters(tiny, 64)
    leds = uniform_pattern(tiny.stage, 0.5)
    one, two = (rel[b].render(2, 1, leds).image[..., :3] for b in (1, 2))
    twice = rel[2].render(2, 1, 2 * leds).image[..., :3]
    assert np.all(two >= one - 1e-6) and two.sum() > one.sum() * 1.002
    np.testing.assert_allclose(twice, 2 * two, rtol=1e-4, atol=1e-6)
    dark = rel[2].render(2, 1, np.zeros_like(leds)).image[..., :3]
    assert not dark.any()


def test_operator_cache_on_disk_is_reused_and_bad_files_are_traced_again(tiny, tmp_path, monkeypatch):
    from gra_mi.render import bounce
    from gra_mi.render.bounce import BounceOperator

    leds = uniform_pattern(tiny.stage, 0.5)
    first = relighters(tiny, 64, bounces=(2,), cache_dir=tmp_path)[2]
    image = first.render(2, 1, leds).image
    (path,) = tmp_path.glob("bounce_*.npz")
    op = BounceOperator.load(path, first.atlas.num_texels, 32)
    assert op is not None and op.entries == first.bounce_operator(2).entries
    assert BounceOperator.load(path, first.atlas.num_texels, 64) is None  # another ray count
    assert BounceOperator.load(path, first.atlas.num_texels + 1, 32) is None  # another atlas

    def no_trace(*a, **k):
        raise AssertionError("traced although the cache holds the frame")

    monkeypatch.setattr(bounce, "trace_operator", no_trace)
    np.testing.assert_array_equal(relighters(tiny, 64, bounces=(2,), cache_dir=tmp_path)[2].render(2, 1, leds).image, image)
    monkeypatch.undo()
    path.write_bytes(path.read_bytes()[:100])  # cut short: traced again, the same
    np.testing.assert_array_equal(relighters(tiny, 64, bounces=(2,), cache_dir=tmp_path)[2].render(2, 1, leds).image, image)


def test_led_loop_in_the_sources_order_gives_each_ray_its_own_light(tiny):
    """The bounce's LED loop runs over the rays sorted by the texel they hit (Relighter.light_toward_receivers, through
    BounceOperator.by_source) and hands each ray its light back in the operator's order: the same as the loop run
    lane by lane in that order, under a pattern of few LEDs (packed bits) and every LED on."""
    import mitsuba as mi

    from gra_mi.render.shading import TexelLedLoop, led_cell_roughness
    from gra_mi.render.transport import BOUNCE_LEDS

    rel = relighters(tiny, 64, bounces=(2,))[2]
    op, geom = rel.bounce_operator(2), rel.geometry(2)
    assert op.entries > 0 and np.any(np.diff(op.sources.astype(np.int64)) < 0)  # the operator's order is not the loop's
    few = np.zeros((tiny.stage.num_leds, 3))
    few[:: max(tiny.stage.num_leds // 5, 1)] = 0.7
    for leds in (few, uniform_pattern(tiny.stage, 0.5)):
        got = rel.light_toward_receivers(2, op, leds, [], [], False)
        fewer = rel.leds(False).brightest(leds, BOUNCE_LEDS)  # as the bounce reduces the lighting
        rough = rel.roughness if np.array_equal(fewer, leds) else led_cell_roughness(rel.roughness, BOUNCE_LEDS)
        loop = TexelLedLoop.build(geom, rel.visibility(2, False), op.sources, rel.leds(False), fewer, op.toward_receivers())
        want = loop.run(mi.Float(rough[op.sources].astype(np.float32)))
        for a, b in zip(got, want, strict=True):
            a, b = np.array(a), np.array(b)
            assert b.max() > 0
            np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6 * b.max())


def test_smoothing_averages_noise_on_the_surface_and_nothing_across_it(tiny):
    """The received light's average over the surface (atlas.SurfaceFilter): a constant stays itself, independent
    noise shrinks (a 3 × 3 window: to under a third of its variance), no weight reaches a texel far in space or
    facing away (a chart seam, the other side of a limb), and values outside the domain never leak in."""
    import mitsuba as mi

    from gra_mi.render.atlas import SurfaceFilter

    rel = relighters(tiny, 64, bounces=(2,))[2]
    geom, atlas = rel.geometry(2), rel.atlas
    m = atlas.num_texels
    smooth = SurfaceFilter.build(atlas, geom, 1)

    def apply(values, f=smooth):
        return np.array(f.apply(mi.Color3f(*np.asarray(values, np.float32).T))).T

    np.testing.assert_allclose(apply(np.full((m, 3), 0.25)), 0.25, rtol=1e-6)
    noise = np.random.default_rng(2).normal(size=(m, 3))
    assert apply(noise).var() < noise.var() / 3
    index, weight = np.array(smooth.neighbours).reshape(m, -1), np.array(smooth.weights).reshape(m, -1)
    p, n = np.array(geom.position).T, np.array(geom.normal).T
    used = weight > 0
    far = np.linalg.norm(p[index] - p[:, None], axis=2)
    spacing = np.sort(np.linalg.norm(p[index] - p[:, None], axis=2) + np.where(used, 0, np.inf), axis=1)[:, 1]
    assert np.all(far[used] <= 2.0 * np.sqrt(2.0) * np.repeat(spacing, used.sum(1)) + 1e-6)
    assert np.all(np.sum(n[index] * n[:, None], axis=2)[used] > 0.9)
    domain = np.arange(0, m, 2)
    inside = SurfaceFilter.build(atlas, geom, 1, domain)
    values = np.full((m, 3), 1e6)
    values[domain] = 1.0
    np.testing.assert_allclose(apply(values, inside)[domain], 1.0, rtol=1e-6)
    assert not apply(values, inside)[1::2].any()  # outside the domain nothing is averaged into (no camera sees it)


def test_jobs_culled_to_their_cameras_render_the_same(tiny):
    """A job's cameras need the visibility of the texels they see and of every texel whose light reaches those."""
    full, culled = relighters(tiny, 64, bounces=(2,))[2], relighters(tiny, 64, bounces=(2,))[2]
    culled.only_for([tiny.stage.cameras[1].name])
    leds = uniform_pattern(tiny.stage, 0.5)
    np.testing.assert_allclose(culled.render(2, 1, leds).image, full.render(2, 1, leds).image, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize(("field", "value"), [("bounces", 0), ("bounces", 9), ("bounces", True), ("bounces", "2"), ("bounces", 2.0),
                                              ("bounce_rays", 0), ("bounce_rays", 10**6), ("bounce_smoothing", -1),
                                              ("bounce_smoothing", 99), ("bounce_smoothing", 1.5)])  # fmt: skip
def test_bad_transport_settings_name_the_field(field, value):
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.render.transport import LightTransport

    with pytest.raises(GraMiParameterError, match=field):
        LightTransport(**{field: value}).validate()


def test_relightnet_is_fed_the_bounces_it_was_trained_on():
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.relightnet.model import RelightNetConfig, check_input_transport
    from gra_mi.render.transport import LightTransport

    check_input_transport(RelightNetConfig(resolution=64, input_bounces=2), LightTransport(bounces=2), "rn")
    with pytest.raises(GraMiParameterError, match="trained on renders with 2 bounce.*--bounces 2"):
        check_input_transport(RelightNetConfig(resolution=64, input_bounces=2), LightTransport(), "rn")


def test_viewer_toggles_the_bounces(variant):
    from gra_mi.apps.viewer import ViewerSession, ViewSources, with_lighting
    from gra_mi.render.plugins import register_plugins

    register_plugins()
    session = ViewerSession(ViewSources(scene=TINY, uv_resolution=64))
    camera = session.ls.stage.cameras[1]
    with_lighting(session, mode="olat", olat=3)
    one = session.render(camera).image
    with_lighting(session, bounces=2)
    assert session.relighter.transport.bounces == 2
    assert session.render(camera).image.astype(int).sum() > one.astype(int).sum()
    from gra_mi.core.errors import GraMiParameterError

    with pytest.raises(GraMiParameterError, match="bounces"):
        with_lighting(session, bounces=0)
    assert session.relighter.transport.bounces == 2 and session.lighting.bounces == 2  # a refused change changes nothing


def test_relight_cli_with_two_bounces_is_brighter_where_the_body_sees_itself(tmp_path):
    from gra_mi.core.io import read_exr

    from .test_cli import run_cli

    for bounces in (1, 2):
        out = run_cli("relight", str(TINY), "--frames", "2", "--cameras", "1", "--olat", "5", "--bounces", str(bounces),
                      "--out", str(tmp_path / f"b{bounces}"))  # fmt: skip
        assert out.returncode == 0, out.stderr
    one, two = (read_exr(next((tmp_path / f"b{b}").rglob("*.exr")))[..., :3] for b in (1, 2))
    assert two.sum() > one.sum() * 1.001 and np.all(two >= one - 1e-5)
    bad = run_cli("relight", str(TINY), "--olat", "5", "--bounces", "0", "--out", str(tmp_path / "bad"))
    assert bad.returncode != 0 and "bounces" in bad.stderr


def test_fit_with_two_bounces_leaves_less_light_to_the_albedo(path_traced_fit, tmp_path):
    """The path-traced truth holds interreflections: with them modelled, the fitted albedo has less to explain."""
    from gra_mi.core.io import read_json
    from gra_mi.fit.materials import FitConfig, run_fit
    from gra_mi.render.transport import LightTransport

    run_fit(path_traced_fit / "cap", tmp_path / "fit2", FitConfig(transport=LightTransport(bounces=2)))
    one, two = (read_json(folder / "fit.json")["metrics"] for folder in (path_traced_fit / "fit", tmp_path / "fit2"))
    assert two["albedo_bias"] < one["albedo_bias"] - 0.003, (one, two)
    assert two["albedo_mae"] < one["albedo_mae"], (one, two)


def test_fewer_leds_keep_the_flux_at_the_centre_and_leave_sparse_patterns_alone(default_stage):
    from gra_mi.render.leds import LedLayout

    layout = LedLayout.of(default_stage)
    rng = np.random.default_rng(0)
    envmap_like = rng.uniform(0, 1, (default_stage.num_leds, 3))
    fewer = layout.brightest(envmap_like, 32)
    r2 = np.sum((default_stage.led_positions - default_stage.center) ** 2, axis=1)[:, None]
    np.testing.assert_allclose((fewer / r2).sum(axis=0), (envmap_like / r2).sum(axis=0), rtol=1e-12)
    assert np.count_nonzero(fewer.max(axis=1)) == 32
    olat = np.zeros_like(envmap_like)
    olat[[3, 100]] = 1.0
    np.testing.assert_array_equal(layout.brightest(olat, 32), olat)


def test_a_convex_body_has_no_light_after_the_first_bounce(variant, tmp_path):
    """A sphere never sees itself: nothing traces, and two bounces are one, bit for bit."""
    from gra_mi.render.plugins import register_plugins
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, rig_scene
    from gra_mi.subject.sequence import _uv_sphere, sequence_from_frames

    register_plugins()
    positions, uvs, faces = _uv_sphere(24, 48)
    sequence = sequence_from_frames([0.3 * positions + [0.0, 1.0, 0.0]], faces, uvs)
    ls = LightstageScene.load(rig_scene(tmp_path, sequence, default_lightstage(width=64, height=48)), spp=1)
    rel = relighters(ls, 64)
    leds = uniform_pattern(ls.stage, 0.5)
    assert rel[2].bounce_operator(0).traced == 0 and rel[2].bounce_operator(0).entries == 0
    np.testing.assert_array_equal(rel[2].render(0, 0, leds).image, rel[1].render(0, 0, leds).image)
