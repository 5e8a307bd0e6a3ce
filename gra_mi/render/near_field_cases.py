"""Near-field lighting where it is hardest, as Mitsuba scene dictionaries: the tiny subject lit by one emitter placed to
stress ``gra_onebounce`` (1/d² across a patch, grazing light, a shadow edge, a spot's cone edge), and the metric
Mitsuba's own tests use. tests/test_scene_files.py checks them against Mitsuba's ``direct``; benchmarks/moving_lights.py
times them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

SPP = 256


def look_at(origin, target):
    """A camera or light placement, made into a transform when the scene is built (after the variant is chosen)."""
    return ("look_at", origin, target)


def _resolved(value):
    import mitsuba as mi

    if isinstance(value, dict):
        return {k: _resolved(v) for k, v in value.items()}
    if isinstance(value, tuple) and value[:1] == ("look_at",):
        return mi.ScalarTransform4f().look_at(origin=value[1], target=value[2], up=[0, 1, 0])
    return value


def body_scene(emitters: dict, body: Path, width: int = 96, height: int = 128):
    """The tiny subject (its frame 0 PLY: ``body`` (a gra_microfacet material with a visible highlight) seen from the front, lit by ``emitters``."""
    import mitsuba as mi

    scene = {
        "type": "scene",
        "body": {
            "type": "ply", "filename": str(body), "face_normals": False,
            "bsdf": {"type": "gra_microfacet", "albedo": {"type": "rgb", "value": [0.6, 0.5, 0.4]}, "roughness": 0.35},
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
