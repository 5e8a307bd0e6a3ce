"""What makes a lighting of a lightstage scene's current frame light nothing, or not as meant, said before rendering:
every LED off, lit LEDs or a near-field light inside the subject. ``ls``: a loaded scene
(:class:`gra_mi.stage.scene.LightstageScene`, which calls these as it renders)."""

from __future__ import annotations

import numpy as np

AXES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)


def points_inside_subject(ls, points: np.ndarray) -> np.ndarray:
    """Which points lie inside the subject's mesh at the current frame: rays along ±x, ±y, ±z (at least five of
    six) leave it through a back face. A light there lights nothing."""
    import drjit as dr
    import mitsuba as mi

    points = np.asarray(points, np.float64).reshape(-1, 3)
    origins, directions = np.repeat(points, len(AXES), axis=0), np.tile(AXES, (len(points), 1))
    ray = mi.Ray3f(mi.Point3f(*(origins.T.astype(np.float32))), mi.Vector3f(*(directions.T.astype(np.float32))))
    si = ls.subject_hits(ray, mi.RayFlags.All, coherent=False)
    leaving = si.is_valid() & (dr.dot(si.n, ray.d) > 0)
    return np.asarray(leaving, bool).reshape(len(points), len(AXES)).sum(axis=1) >= len(AXES) - 1


def lighting_warnings(ls, intensities: np.ndarray, near_lights=None, far_field: bool = False) -> list[str]:
    """What makes a lighting of the current frame light nothing, or not as meant, in words: every LED off, lit LEDs
    inside the subject (a rig too small or off centre), a near-field light inside the subject. Far field, LEDs inside
    the subject still light it, from their directions, but at the irradiance such a small rig makes at full drive.
    ``near_lights``: one near-field light (anything with a ``position``) or a list."""
    said = []
    lit = np.flatnonzero(np.asarray(intensities).max(axis=1) > 0)
    near = [] if near_lights is None else [near_lights] if hasattr(near_lights, "position") else list(near_lights)
    if near:
        inside = points_inside_subject(ls, np.array([light.position for light in near]))
        for light, hidden in zip(near, inside, strict=True):
            if hidden:
                said.append(
                    f"the light at {np.round(light.position, 3).tolist()} m is inside the subject at frame {ls.frame}: it lights nothing"
                )
    elif not len(lit):
        said.append("every LED is off: the render is black")
    if len(lit):
        inside = int(points_inside_subject(ls, ls.stage.led_positions[lit]).sum())
        if inside and far_field:
            radius = float(np.median(ls.stage.led_distances()))
            said.append(
                f"{inside} of {len(lit)} lit LEDs are inside the subject at frame {ls.frame}: the rig ({radius:.2f} m) is smaller than the "
                "subject; far field lights from the LEDs' directions, at the irradiance of LEDs this close at full drive, "
                "so the render is far brighter than the same map on a real stage (check the rig's radius and centre)"
            )
        elif inside:
            said.append(
                f"{inside} of {len(lit)} lit LEDs are inside the subject at frame {ls.frame}: they light nothing (check the rig's radius and centre)"
            )
    return said
