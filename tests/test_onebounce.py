"""gra_onebounce against Mitsuba's direct integrator, analytic cases, and finite-difference gradients."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.stage.lightstage import load_calibration
from gra_mi.stage.scene import camera_xml

from .conftest import SCENES

TINY_PLY = SCENES / "subjects" / "tiny" / "frames" / "frame_0002.ply"
STAGE = load_calibration(SCENES / "rigs" / "tiny" / "calibration.json")
LEDS = [3, 10, 22, 40, 51, 60]


def bsdf_xml(kind: str) -> str:
    if kind == "diffuse":
        return '<bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.45, 0.3"/></bsdf>'
    return (
        '<bsdf type="gra_microfacet" id="mat">'
        '<texture type="bitmap" name="albedo"><string name="filename" value="ALBEDO"/><string name="filter_type" value="nearest"/></texture>'
        '<texture type="bitmap" name="roughness"><string name="filename" value="ROUGH"/><string name="filter_type" value="nearest"/></texture>'
        "</bsdf>"
    )


def make_scene(tmp_path, kind: str, leds: list[int], intensity: float = 3.0, camera: int = 1, extra_emitters: str = ""):
    import mitsuba as mi

    from gra_mi.core.io import write_exr

    rng = np.random.default_rng(0)
    write_exr(tmp_path / "albedo.exr", rng.uniform(0.2, 0.8, (8, 8, 3)))
    write_exr(tmp_path / "rough.exr", rng.uniform(0.3, 0.9, (8, 8, 1)))
    emitters = "".join(
        f'<emitter type="point"><point name="position" value="{", ".join(map(str, STAGE.led_positions[k]))}"/><rgb name="intensity" value="{intensity}"/></emitter>'
        for k in leds
    )
    xml = (
        f'<scene version="3.0.0">{camera_xml(STAGE.cameras[camera], "16")}{emitters}{extra_emitters}'
        f'<shape type="ply" id="subject"><string name="filename" value="{TINY_PLY}"/>{bsdf_xml(kind)}</shape></scene>'
    )
    xml = xml.replace("ALBEDO", str(tmp_path / "albedo.exr")).replace("ROUGH", str(tmp_path / "rough.exr"))
    return mi.load_string(xml)


def interior(alpha: np.ndarray) -> np.ndarray:
    """Pixels fully covered, with fully covered neighbours (away from silhouettes, where AA noise lives)."""
    full = alpha > 0.999
    out = full.copy()
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        out &= np.roll(full, (dy, dx), axis=(0, 1))
    return out


@pytest.mark.parametrize("kind", ["diffuse", "gra_microfacet"])
def test_matches_mitsuba_direct(plugins, tmp_path, kind):
    import mitsuba as mi

    spp = 256
    direct = mi.load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    # Reference: Mitsuba's direct integrator, one LED per scene (so it never picks an LED at random), summed.
    reference = sum(np.array(mi.render(make_scene(tmp_path, kind, [k]), integrator=direct, spp=spp, seed=1))[..., :3] for k in LEDS)
    ours = np.array(mi.render(make_scene(tmp_path, kind, LEDS), integrator=mi.load_dict({"type": "gra_onebounce"}), spp=spp, seed=1))
    mask = interior(ours[..., 3])
    assert mask.sum() > 200
    rel = np.abs(ours[..., :3] - reference)[mask] / np.maximum(reference[mask], 2e-2)
    assert rel.mean() <= 0.005, rel.mean()


def test_sphere_under_one_led_matches_lambert_closed_form(plugins):
    import drjit as dr
    import mitsuba as mi

    led = np.array([0.3, 1.2, 1.5])
    intensity, rho, radius = 5.0, 0.7, 0.4
    scene = mi.load_dict(
        {
            "type": "scene",
            "sphere": {"type": "sphere", "radius": radius, "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}},
            "led": {"type": "point", "position": led.tolist(), "intensity": {"type": "rgb", "value": intensity}},
        }
    )
    integrator = mi.load_dict({"type": "gra_onebounce"})
    # Rays from a viewpoint toward random points on the visible cap: deterministic, no pixel filter.
    rng = np.random.default_rng(0)
    eye = np.array([0.0, 0.5, 3.0])
    targets = rng.normal(size=(4000, 3))
    targets = radius * targets / np.linalg.norm(targets, axis=1, keepdims=True)
    d = targets - eye
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ray = mi.Ray3f(mi.Point3f(*np.tile(eye, (len(d), 1)).T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    integrator._lights = integrator.prepare_lights(scene)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, len(d))
    value, valid, _, _ = integrator.sample(dr.ADMode.Primal, scene, sampler, ray, None, None, mi.Bool(True))
    value, valid = np.array(value).T, np.array(valid)
    # Closed form: the first hit of each ray, then (ρ/π) I max(0, n·l) / d².
    b = d @ eye
    c = eye @ eye - radius**2
    t = -b - np.sqrt(np.maximum(b**2 - c, 0))
    hit = eye + t[:, None] * d
    n = hit / radius
    to_led = led - hit
    dist2 = np.sum(to_led**2, axis=1)
    expected = rho / np.pi * intensity * np.maximum(np.sum(n * to_led, axis=1) / np.sqrt(dist2), 0) / dist2
    hits = (b**2 - c) > 1e-3  # leave out rays that only graze the silhouette
    assert valid[hits].all()
    np.testing.assert_allclose(value[hits, 0], expected[hits], rtol=1e-4, atol=1e-6)


def test_furnace_uniform_leds_light_a_small_sphere_uniformly(plugins):
    # A constant envmap mapped onto the default 331-LED rig lights a small convex sphere at the stage centre
    # almost like a white furnace: outgoing radiance ≈ ρ · L for every point (near-field and LED discreteness
    # bound the deviation).
    import drjit as dr
    import mitsuba as mi

    from gra_mi.stage.envmap import envmap_to_leds

    stage = load_calibration(SCENES / "rigs" / "default" / "calibration.json")
    env_radiance, rho = 0.8, 0.5
    lighting = envmap_to_leds(np.full((32, 64, 3), env_radiance, np.float32), stage, normalize=False)
    scene_dict = {
        "type": "scene",
        "sphere": {
            "type": "sphere",
            "center": stage.center.tolist(),
            "radius": 0.05,
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}},
        },
    }
    for i, (p, intensity) in enumerate(zip(stage.led_positions, lighting.radiant_intensity(stage), strict=True)):
        scene_dict[f"led{i}"] = {"type": "point", "position": p.tolist(), "intensity": {"type": "rgb", "value": intensity.tolist()}}
    scene = mi.load_dict(scene_dict)
    integrator = mi.load_dict({"type": "gra_onebounce"})
    rng = np.random.default_rng(1)
    n = 2000
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = stage.center - 0.5 * d  # rays toward the centre from all around
    ray = mi.Ray3f(mi.Point3f(*origins.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))
    integrator._lights = integrator.prepare_lights(scene)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, n)
    value, valid, _, _ = integrator.sample(dr.ADMode.Primal, scene, sampler, ray, None, None, mi.Bool(True))
    value = np.array(value).T
    assert np.array(valid).all()
    np.testing.assert_allclose(value, rho * env_radiance, rtol=0.03)
    assert abs(value.mean() / (rho * env_radiance) - 1) < 0.01
    dr.eval()


SOFTBOX = (  # an area light where LED 22 stands, facing the stage centre
    '<shape type="rectangle"><transform name="to_world"><scale x="0.25" y="0.25"/><lookat origin="{}" target="0, 1, 0" '
    'up="0, 1, 0"/></transform><emitter type="area"><rgb name="radiance" value="30"/></emitter></shape>'
).format(", ".join(map(str, STAGE.led_positions[22])))
EXTRA_LIGHTS = {"leds": "", "environment": '<emitter type="constant"><rgb name="radiance" value="0.6"/></emitter>', "area": SOFTBOX}


@pytest.mark.parametrize("lights", sorted(EXTRA_LIGHTS))
def test_gradients_match_finite_differences(plugins, tmp_path, lights):
    """Path Replay Backpropagation through the LED loop, through the dome an environment becomes, and through an area
    light's samples (the adjoint pass replays the primal pass's sampler, so it draws the same points)."""
    import drjit as dr
    import mitsuba as mi

    scene = make_scene(tmp_path, "gra_microfacet", LEDS if lights == "leds" else [], extra_emitters=EXTRA_LIGHTS[lights])
    integrator = mi.load_dict({"type": "gra_onebounce"})
    params = mi.traverse(scene)
    albedo_key, rough_key = "subject.bsdf.albedo.data", "subject.bsdf.roughness.data"
    albedo = mi.TensorXf(params[albedo_key])
    rough = mi.TensorXf(params[rough_key])
    weights = mi.TensorXf(np.random.default_rng(3).uniform(0.5, 1.5, (64, 96, 3)).astype(np.float32))

    def loss_value(a, r):
        params[albedo_key], params[rough_key] = a, r
        params.update()
        image = np.array(mi.render(scene, params, integrator=integrator, spp=4, seed=2), dtype=np.float64)
        return float(np.sum(image[..., :3] * np.array(weights, dtype=np.float64)))  # float64: FD needs the digits

    dr.enable_grad(albedo, rough)
    params[albedo_key], params[rough_key] = albedo, rough
    params.update()
    # The adjoint pass must replay the primal's pixel samples for an exact comparison with finite differences
    # (mi.render insists on another seed for unbiasedness), so call render_backward with the primal's seed.
    grad_image = np.zeros((64, 96, 4), np.float32)
    grad_image[..., :3] = np.array(weights)
    integrator.render_backward(scene, params, mi.TensorXf(grad_image), sensor=0, seed=2, spp=4)
    g_albedo, g_rough = np.array(dr.grad(albedo)), np.array(dr.grad(rough))
    albedo_np, rough_np = np.array(dr.detach(albedo)), np.array(dr.detach(rough))
    # The most influential texels (a texel no camera pixel sees has zero gradient and FD).
    for grad, base, is_albedo in ((g_albedo, albedo_np, True), (g_rough, rough_np, False)):
        assert np.abs(grad).max() > 0.1, "the light reaches texels the loss weighs"
        for idx in np.argsort(np.abs(grad).ravel())[-3:]:
            eps = 1e-2
            plus, minus = base.copy().ravel(), base.copy().ravel()
            plus[idx] += eps
            minus[idx] -= eps
            a_p, a_m = (
                (mi.TensorXf(plus.reshape(base.shape)), mi.TensorXf(minus.reshape(base.shape)))
                if is_albedo
                else (mi.TensorXf(albedo_np),) * 2
            )
            r_p, r_m = (
                (mi.TensorXf(rough_np),) * 2
                if is_albedo
                else (mi.TensorXf(plus.reshape(base.shape)), mi.TensorXf(minus.reshape(base.shape)))
            )
            fd = (loss_value(a_p, r_p) - loss_value(a_m, r_m)) / (2 * eps)
            assert grad.ravel()[idx] == pytest.approx(fd, rel=1e-2, abs=1e-3)


def test_a_mirror_s_gradient_matches_finite_differences(plugins):
    """The adjoint pass through a delta lobe: a conductor's reflectance seen in a mirror plane that reflects a softbox
    and a constant sky."""
    import mitsuba as mi

    scene = mi.load_dict({
        "type": "scene",
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3, 0.4, 0.5]}},
        "box": {"type": "rectangle", "to_world": mi.ScalarTransform4f().look_at(origin=[-0.3, 0, 0.5], target=[0, 0, 0], up=[0, 1, 0]).scale([0.2, 0.2, 1]),
                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 4.0}}},
        "plane": {"type": "rectangle", "bsdf": {"type": "conductor", "specular_reflectance": {"type": "rgb", "value": [0.7, 0.8, 0.9]}}},
        "camera": {"type": "perspective", "fov": 40, "to_world": mi.ScalarTransform4f().look_at(origin=[0.4, 0, 0.8], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "pixel_format": "rgba"}},
    })  # fmt: skip
    assert_colour_gradient_matches_finite_differences(scene, "plane.bsdf.specular_reflectance.value", spp=4)


def assert_colour_gradient_matches_finite_differences(scene, key: str, spp: int, seed: int = 2) -> None:
    """gra_onebounce's adjoint pass (the primal's pixel samples replayed) against central differences, per channel of
    the RGB parameter ``key``, for a random weighting of the image; the gradient must be well away from 0."""
    import drjit as dr
    import mitsuba as mi

    integrator, params = mi.load_dict({"type": "gra_onebounce"}), mi.traverse(scene)
    base = np.array(params[key]).ravel().copy()
    width, height = scene.sensors()[0].film().size()
    weights = np.random.default_rng(4).uniform(0.5, 1.5, (height, width, 3))

    def loss_value(value):
        params[key] = mi.Color3f(*map(float, value))
        params.update()
        image = np.array(mi.render(scene, params, integrator=integrator, spp=spp, seed=seed), dtype=np.float64)
        return float(np.sum(image[..., :3] * weights))

    colour = mi.Color3f(*map(float, base))
    dr.enable_grad(colour)
    params[key] = colour
    params.update()
    grad_image = np.zeros((height, width, 4), np.float32)
    grad_image[..., :3] = weights
    integrator.render_backward(scene, params, mi.TensorXf(grad_image), sensor=0, seed=seed, spp=spp)
    grad = np.array(dr.grad(colour)).ravel()
    assert (np.abs(grad) > 1.0).all(), grad
    for channel in range(3):
        plus, minus = base.copy(), base.copy()
        plus[channel] += 1e-2
        minus[channel] -= 1e-2
        assert grad[channel] == pytest.approx((loss_value(plus) - loss_value(minus)) / 2e-2, rel=1e-2)
