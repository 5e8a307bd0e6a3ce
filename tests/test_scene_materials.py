"""What a user's own scene brings besides its lights, through gra_onebounce: materials that bend the shading normal
(``normalmap``, ``bumpmap``), see-through ones (``thindielectric``, a ``mask`` cutout), and sensors other than a
perspective camera. Each against an integrator of Mitsuba's own that computes the same light: ``direct`` where shadow
rays stop at every surface, ``volpath`` (two bounces) where they must cross see-through ones."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.render.near_field_cases import _resolved, area, image_error, look_at, point, sky

CAMERA_AT = [0.0, -2.0, 2.0]


def height_field(size: int = 128) -> np.ndarray:
    x = np.linspace(0.0, 40.0, size)
    return (0.5 + 0.5 * np.sin(x)[None, :] * np.cos(x)[:, None]).astype(np.float32)


def normal_map(size: int = 128) -> np.ndarray:
    """Tangent-space normals encoded as Mitsuba's ``normalmap`` reads them (n × 0.5 + 0.5): ripples along u."""
    tilt = 0.35 * np.sin(np.linspace(0.0, 40.0, size))[None, :].repeat(size, 0)
    return np.stack([0.5 + tilt, np.full((size, size), 0.5), np.full((size, size), 0.85)], -1).astype(np.float32)


def bitmap(data: np.ndarray) -> dict:
    import mitsuba as mi

    return {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True}


def ball_on_floor(material: dict, light: dict, sensor: dict | None = None, size: int = 24):
    """A ball of ``material`` on a grey floor under ``light``, seen from above and in front (or by ``sensor``)."""
    import mitsuba as mi

    camera = sensor or {
        "type": "perspective", "fov": 40, "to_world": mi.ScalarTransform4f().look_at(origin=CAMERA_AT, target=[0, 0, 0], up=[0, 0, 1]),
        "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgba", "rfilter": {"type": "box"}},
    }  # fmt: skip
    return mi.load_dict(_resolved({
        "type": "scene", "light": light, "camera": camera,
        "ball": {"type": "sphere", "center": [0, 0, 0.5], "radius": 0.5, "bsdf": material},
        "floor": {"type": "rectangle", "to_world": look_at([0, 0, 0], [0, 0, 1], (3, 3, 1)),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
    }))  # fmt: skip


def render(scene, integrator: dict, spp: int, seed: int = 1) -> np.ndarray:
    import mitsuba as mi

    return np.array(mi.render(scene, integrator=mi.load_dict(integrator), spp=spp, seed=seed))


def lights() -> dict:
    return {
        "point": point([1.0, -1.0, 2.0], 8.0),
        "area": area("disk", [1.0, -1.0, 2.0], [0, 0, 0.5], 0.3, 10.0),
        "sky": sky(),
    }


BENT = ["normalmap diffuse", "normalmap rough metal", "bumpmap rough plastic"]


def bent_normal_materials() -> dict:
    return {
        "normalmap diffuse": {"type": "normalmap", "normalmap": bitmap(normal_map()), "bsdf": {"type": "diffuse"}},
        "normalmap rough metal": {"type": "normalmap", "normalmap": bitmap(normal_map()), "bsdf": {"type": "roughconductor", "alpha": 0.15}},
        "bumpmap rough plastic": {"type": "bumpmap", "texture": bitmap(height_field()), "scale": 0.5, "bsdf": {"type": "roughplastic", "alpha": 0.2}},
    }  # fmt: skip


@pytest.mark.parametrize("material", BENT)
def test_bent_shading_normals_under_a_point_light_are_mitsuba_s_direct_exactly(plugins, material):
    """One point light, the same pixel samples: both integrators compute the same shadow ray and BSDF value, so the
    images agree to float precision (no light lost or added where shading and geometric normals disagree)."""
    scene = ball_on_floor(bent_normal_materials()[material], lights()["point"])
    ours = render(scene, {"type": "gra_onebounce"}, spp=64)
    direct = render(scene, {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}, spp=64)
    assert ours[..., :3].max() > 0.05
    np.testing.assert_allclose(ours, direct, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("light", ["area", "sky"])
@pytest.mark.parametrize("material", BENT)
def test_bent_shading_normals_under_area_lights_and_skies_match_direct(plugins, material, light):
    scene = ball_on_floor(bent_normal_materials()[material], lights()[light])
    ours = render(scene, {"type": "gra_onebounce"}, spp=128)
    truth = render(scene, {"type": "direct"}, spp=4096, seed=2)
    error, bias = image_error(ours, truth)
    assert error < 0.03 and abs(bias) < 0.01, (error, bias)


SEE_THROUGH = {
    "thindielectric": {"type": "thindielectric"},  # a soap bubble, a window pane: 1 − R passes straight through
    "mask": {"type": "mask", "opacity": {"type": "rgb", "value": 0.4}, "bsdf": {"type": "roughplastic", "alpha": 0.3}},
}


@pytest.mark.parametrize("light", ["point", "area", "sky"])
@pytest.mark.parametrize("material", sorted(SEE_THROUGH))
def test_see_through_materials_match_volpath(plugins, material, light):
    """Mitsuba's ``direct`` and ``path`` stop shadow rays at a thin glass or a cutout (full shadow); ``volpath`` lets
    them through as gra_onebounce does, and with two bounces computes the same direct light: camera rays that pass
    the surface see what is behind it, the floor gets the light that passes, the ball shows its own reflection."""
    scene = ball_on_floor(SEE_THROUGH[material], lights()[light])
    ours = render(scene, {"type": "gra_onebounce"}, spp=512)
    truth = render(scene, {"type": "volpath", "max_depth": 2}, spp=8192, seed=2)
    error, bias = image_error(ours, truth)
    assert error < 0.02 and abs(bias) < 0.01, (error, bias)
    shadowed = render(scene, {"type": "direct"}, spp=64)
    assert image_error(shadowed, truth)[1] < -0.02, "direct stops the light the surface lets through: not a reference here"


def sensors() -> dict:
    import mitsuba as mi

    view = mi.ScalarTransform4f().look_at(origin=CAMERA_AT, target=[0, 0, 0], up=[0, 0, 1])
    film = {"type": "hdrfilm", "width": 24, "height": 16, "pixel_format": "rgba"}
    return {
        "orthographic": {"type": "orthographic", "to_world": view @ mi.ScalarTransform4f().scale([1.5, 1.5, 1]), "film": film},
        "thinlens": {"type": "thinlens", "fov": 40, "aperture_radius": 0.1, "focus_distance": 2.8, "to_world": view, "film": film},
        "cropped, Gaussian filter": {"type": "perspective", "fov": 40, "to_world": view,
                                     "film": {**film, "rfilter": {"type": "gaussian"}, "crop_offset_x": 4, "crop_width": 16}},
    }  # fmt: skip


@pytest.mark.parametrize("sensor", ["orthographic", "thinlens", "cropped, Gaussian filter"])
def test_other_sensors_see_what_direct_sees(plugins, sensor):
    scene = ball_on_floor({"type": "roughplastic", "alpha": 0.2}, lights()["area"], sensor=sensors()[sensor])
    ours = render(scene, {"type": "gra_onebounce"}, spp=64)
    truth = render(scene, {"type": "direct"}, spp=4096, seed=2)
    assert ours.shape == truth.shape
    error, bias = image_error(ours, truth)
    assert error < 0.02 and abs(bias) < 0.01, (error, bias)


def test_an_irradiance_meter_reads_the_light_it_faces(plugins):
    """A meter on a small disk facing a sky of radiance L reads πL: the camera ray of an irradiance meter is a
    cosine-weighted direction, and gra_onebounce shows the sky along it as Mitsuba's integrators do."""
    import mitsuba as mi

    scene = mi.load_dict({
        "type": "scene", "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.7}},
        "meter": {"type": "disk", "to_world": mi.ScalarTransform4f().translate([0, 0, 0.3]).scale(0.1),
                  "sensor": {"type": "irradiancemeter", "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}}}},
    })  # fmt: skip
    reading = render(scene, {"type": "gra_onebounce"}, spp=256).ravel()
    np.testing.assert_allclose(reading, np.pi * 0.7, rtol=1e-5)
