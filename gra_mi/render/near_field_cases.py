"""Near-field lighting where it is hardest, as Mitsuba scene dictionaries: the tiny subject lit by one emitter placed to
stress ``gra_onebounce`` (1/d² across a patch, grazing light, a shadow edge, a spot's cone edge), area lights, a stage
of area LEDs, balls of materials with delta lobes under a sky, and the metric Mitsuba's own tests use.
tests/test_scene_files.py checks them against Mitsuba's ``direct``; benchmarks/moving_lights.py,
benchmarks/area_lights.py and benchmarks/delta_lobes.py time them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

SPP = 256


def look_at(origin, target, scale=(1.0, 1.0, 1.0)):
    """A camera or light placement (a shape scaled by ``scale`` first), made into a transform when the scene is built
    (after the variant is chosen)."""
    return ("look_at", origin, target, scale)


def _resolved(value):
    import mitsuba as mi

    if isinstance(value, dict):
        return {k: _resolved(v) for k, v in value.items()}
    if isinstance(value, tuple) and value[:1] == ("look_at",):
        placed = mi.ScalarTransform4f().look_at(origin=value[1], target=value[2], up=[0, 1, 0])
        return placed @ mi.ScalarTransform4f().scale(list(value[3]))
    return value


def body_scene(emitters: dict, body: Path, width: int = 96, height: int = 128, roughness: float = 0.35):
    """The tiny subject (its frame 0 PLY: ``body``; a gra_microfacet material with a visible highlight, glossier with
    a lower ``roughness``) seen from the front, lit by ``emitters``."""
    import mitsuba as mi

    scene = {
        "type": "scene",
        "body": {
            "type": "ply", "filename": str(body), "face_normals": False,
            "bsdf": {"type": "gra_microfacet", "albedo": {"type": "rgb", "value": [0.6, 0.5, 0.4]}, "roughness": roughness},
        },
        "camera": {
            "type": "perspective", "fov": 50, "to_world": look_at([0.1, 1.0, 1.3], [0.1, 1.0, 0.0]),
            "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgba", "rfilter": {"type": "box"}},
        },
    }  # fmt: skip
    return mi.load_dict(_resolved(scene | emitters))


def spot(origin, target, intensity, cutoff, beam=None):
    beam = cutoff * 0.75 if beam is None else beam
    return {
        "type": "spot",
        "to_world": look_at(origin, target),
        "intensity": {"type": "rgb", "value": intensity},
        "cutoff_angle": cutoff,
        "beam_width": beam,
    }


def area(shape: str, origin, target, size, radiance) -> dict:
    """An ``area`` light on a ``rectangle`` or ``disk`` (half-extents / radius ``size`` in metres) at ``origin``
    facing ``target``; ``radiance``: a value, or an (H, W, 3) array become a bitmap texture on it."""
    import mitsuba as mi

    texture = {"type": "rgb", "value": radiance}
    if isinstance(radiance, np.ndarray):
        texture = {"type": "bitmap", "bitmap": mi.Bitmap(radiance.astype(np.float32)), "raw": True}
    scale = (size, size, 1.0) if np.isscalar(size) else (*size, 1.0)
    return {"type": shape, "to_world": look_at(origin, target, scale), "emitter": {"type": "area", "radiance": texture}}


def point(position, intensity):
    return {"type": "point", "position": position, "intensity": {"type": "rgb", "value": intensity}}


def mean_relative_error(ours, reference, floor: float) -> float:
    """Mitsuba's test metric: mean over covered pixels of |ours − ref| / max(ref, floor)."""
    covered = reference[..., 3] > 0.999
    return float((np.abs(ours[..., :3] - reference[..., :3])[covered] / np.maximum(reference[..., :3][covered], floor)).mean())


HARD_CASES = {
    # 5 cm in front of the chest: 1/d² at its steepest across the lit patch.
    "light_5cm_from_the_chest": {"light": point([0.0, 1.0, 0.20], 0.02)},
    # Almost in the plane of the chest: light arrives at grazing angles.
    "grazing": {"light": point([-1.2, 1.05, 0.17], 3.0)},
    # Beside the arm at shoulder height: the arm throws a shadow edge across the torso.
    "hidden_by_the_arm": {"light": point([0.9, 1.2, 0.05], 2.0)},
    # A narrow spot whose cone edge crosses the chest.
    "spot_cone_edge": {"light": spot([0.0, 1.0, 1.0], [0.12, 1.0, 0.0], 8.0, cutoff=9.0, beam=6.0)},
    "directional": {"light": {"type": "directional", "direction": [-0.5, -0.3, -1.0], "irradiance": {"type": "rgb", "value": 1.5}}},
}


def area_cases() -> dict[str, dict]:
    """Area lights around the tiny subject: a small softbox beside the head, a textured disk (warm to cool, one corner
    dark) 30 cm from the chest, a window of 1 m² 1.5 m away at the side (soft shadows of the arms)."""
    u, v = np.meshgrid(np.linspace(0, 1, 16), np.linspace(0, 1, 8))
    gradient = np.stack([6 * u + 1, 4 * np.ones_like(u), 6 * (1 - u) + 1], -1) * (1 - 0.9 * (u * v)[..., None])
    return {
        "softbox": area("rectangle", [0.6, 1.3, 0.7], [0.1, 1.0, 0.0], (0.15, 0.1), 5.0),
        "textured_disk": area("disk", [-0.25, 0.95, 0.45], [0.0, 1.0, 0.0], 0.08, gradient),
        "window": area("rectangle", [1.3, 1.2, 0.8], [0.0, 1.0, 0.0], 0.5, 1.5),
    }


def area_stage(count: int = 96, seed: int = 0) -> dict[str, dict]:
    """A lightstage built of ``count`` area lights (disks 3 cm across, 1.1 m from the subject's centre on a Fibonacci
    sphere, none below 20 cm from the floor, each facing the centre) under a drive pattern: tinted radiances spread
    over two orders of magnitude, one in five off. Light that many emitters share: what ``area_samples`` divides."""
    rng = np.random.default_rng(seed)
    k = np.arange(count) + 0.5
    y = 1.0 - 1.4 * k / count  # cos of the polar angle from +y: down to 20 cm above the floor
    ring = np.sqrt(1.0 - y**2)
    azimuth = np.pi * (3.0 - np.sqrt(5.0)) * k
    centre = np.array([0.0, 1.0, 0.0])
    places = centre + 1.1 * np.stack([ring * np.cos(azimuth), y, ring * np.sin(azimuth)], -1)
    radiance = 10.0 ** rng.uniform(0, 2, count)[:, None] * rng.uniform(0.6, 1.0, (count, 3))
    radiance[rng.random(count) < 0.2] = 0.0
    return {f"led_{i:03d}": area("disk", list(places[i]), list(centre), 0.015, radiance[i].tolist()) for i in range(count)}


def sky_bitmap(height: int = 32):
    """A smooth sky brighter above, with a broad warm lamp low on one side: (H, 2H, 3)."""
    import mitsuba as mi

    from gra_mi.stage.envmap import pixel_directions

    d = pixel_directions(height, 2 * height)
    sky = 0.3 + 0.7 * np.clip(d[..., 1:2], 0, 1) * np.array([0.6, 0.8, 1.0])
    lamp = 6.0 * np.exp((d @ np.array([0.8, 0.2, 0.57]) - 1.0) / 0.02)[..., None] * np.array([1.0, 0.8, 0.5])
    return mi.Bitmap((sky + lamp).astype(np.float32))


def sky() -> dict:
    """The sky turned (to_world) and scaled, as a user's scene might hold it."""
    import mitsuba as mi

    turned = mi.ScalarTransform4f().rotate([0, 1, 0], 35).rotate([1, 0, 0], 10)
    return {"type": "envmap", "bitmap": sky_bitmap(), "scale": 1.5, "to_world": turned}


DELTA_MATERIALS = {  # Mitsuba materials with a delta lobe
    "mirror": {"type": "conductor"},
    "gold": {"type": "conductor", "material": "Au"},
    "plastic": {"type": "plastic", "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.4, 0.6]}},
    "glass": {"type": "dielectric"},
}


def ball_scene(material: dict, size: int = 64):
    """A ball of ``material`` under :func:`sky` and a softbox (a chrome ball, as a lightstage calibrates with), seen
    on a ``size`` × ``size`` film."""
    import mitsuba as mi

    return mi.load_dict(_resolved({
        "type": "scene", "sky": sky(),
        "softbox": area("rectangle", [0.6, 0.5, 0.8], [0, 0, 0], (0.15, 0.1), 6.0),
        "ball": {"type": "sphere", "radius": 0.3, "bsdf": material},
        "camera": {"type": "perspective", "fov": 30, "to_world": look_at([0, 0, 1.5], [0, 0, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "pixel_format": "rgba", "rfilter": {"type": "box"}}},
    }))  # fmt: skip


def image_error(image: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(mean relative error, relative bias of the mean) over the pixels the subject covers in ``truth``, the floor at
    5 % of the truth's 95th percentile there."""
    covered = truth[..., 3] > 0.999
    error = mean_relative_error(image, truth, floor=0.05 * float(np.percentile(truth[..., :3][covered], 95)))
    return error, float(image[..., :3][covered].mean() / truth[..., :3][covered].mean() - 1)
