"""A scene's environment emitters (``envmap``, ``constant``, ``sunsky``) as a dome of far-field lights, for
``gra_onebounce``.

gra-mi lights with environments the way a lightstage does (paper: envmap → LEDs): the sphere of directions is cut into
cells and each cell's light arrives as one directional light with one shadow ray. For a Mitsuba scene's own
environment emitter the cells are the Voronoi cells of a Fibonacci dome of ``count`` directions (about 4π / count sr
each), and each light's irradiance is the emitter's radiance integrated over its cell. A bitmap or a constant is
evaluated by the emitter itself (its ``to_world``, ``scale`` and filtering included) at the pixel centres of a
lat-long grid at least twice as fine as its bitmap, each weighted by its pixel's exact solid angle; a sky whose sun is
smaller than any grid's pixel (``sunsky``) is integrated through the emitter's own importance sampling, which finds
the sun. The light comes from the mean direction of the cell's light (its first moment), so a sun inside a cell
shines from the sun, and a Lambertian surface facing the whole cell receives it exactly. The flux is the emitter's
(to the grid's precision, or the samples'); what is approximated is the spread of light inside a cell: a cell's
shadow is hard, a cell holding two lights sends them from one direction, and a highlight narrower than a cell is
blurred (docs/accuracy.md: the error against Mitsuba's own integrators, and its cost, by ``count``).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from gra_mi.stage.envmap import direction_to_uv, nearest_led, pixel_directions, pixel_solid_angles
from gra_mi.stage.lightstage import fibonacci_sphere

DEFAULT_LIGHTS = 1024  # ~6° cells: diffuse light within a per cent of Mitsuba's integrators (docs/accuracy.md)
LIGHTS_RANGE = (16, 16384)
MIN_ROWS, MAX_ROWS = 64, 1024  # the integration grid: twice the bitmap's rows, within these
GRIDDED = ("EnvironmentMapEmitter", "ConstantBackgroundEmitter")  # Mitsuba's classes of envmap and constant
SAMPLED_SIDE = 1024  # the others: 1024² stratified samples of their own sampling (a sky's cell within a few per cent)
LOOKUP_ROWS = 512  # their samples find their cell through this grid's (0.35° pixels: only a border's sliver moves)


@lru_cache(maxsize=4)
def dome_cells(rows: int, count: int) -> tuple[np.ndarray, np.ndarray]:
    """(the grid's directions (rows · 2 rows, 3), the cell of the dome of ``count`` each falls in): the same for every
    render of a scene, so kept (the assignment is the costly part; callers only read them)."""
    grid = pixel_directions(rows, 2 * rows).reshape(-1, 3)
    return grid, nearest_led(grid.astype(np.float32), fibonacci_sphere(count).astype(np.float32))


def grid_index(directions: np.ndarray, rows: int) -> np.ndarray:
    """The pixel of the (rows, 2 rows) grid (:func:`dome_cells`' order) nearest each direction (N, 3)."""
    u, v = direction_to_uv(directions)
    row = np.clip(np.rint(v * (rows - 1)), 0, rows - 1).astype(np.int64)
    col = np.clip(np.floor(u * 2 * rows), 0, 2 * rows - 1).astype(np.int64)
    return row * 2 * rows + col


def grid_rows(emitter) -> int:
    """Rows of the grid an emitter is integrated on: twice its bitmap's (an ``envmap``), within [MIN_ROWS, MAX_ROWS]."""
    import mitsuba as mi

    params = mi.traverse(emitter)
    rows = 2 * int(params["data"].shape[0]) if "data" in params else MIN_ROWS
    return int(np.clip(rows, MIN_ROWS, MAX_ROWS))


def radiance_along(emitter, directions: np.ndarray) -> np.ndarray:
    """(N, 3) the emitter's radiance arriving from world ``directions`` (N, 3): its own ``eval``."""
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, directions.shape[0])
    si.wi = mi.Vector3f(*(-directions.T.astype(np.float32)))  # eval looks along -wi: from the scene outwards
    return np.array(emitter.eval(si), dtype=np.float64).T.reshape(-1, 3)


def cell_light(emitter, count: int = DEFAULT_LIGHTS) -> tuple[np.ndarray, np.ndarray]:
    """What an environment emitter sends through each cell of the dome of ``count`` lights (the Voronoi cells of
    ``fibonacci_sphere(count)``): (count, 3) the irradiance, its radiance integrated over the cell, and (count, 3) the
    first moment of its light over directions (Σ (R + G + B) · solid angle · direction), which places the cell's
    light. A bitmap or a constant is integrated on a grid; an emitter with a light too small for any grid (``sunsky``'s
    half-degree sun) through its own importance sampling."""
    if emitter.class_name() in GRIDDED:
        rows = grid_rows(emitter)
        directions, cell = dome_cells(rows, count)
        weight = np.broadcast_to(pixel_solid_angles(rows, 2 * rows), (rows, 2 * rows)).reshape(-1, 1)
        light = radiance_along(emitter, directions) * weight
    else:
        directions, light = sampled_light(emitter)
        cell = dome_cells(LOOKUP_ROWS, count)[1][grid_index(directions, LOOKUP_ROWS)]
    moment = light.sum(axis=1, keepdims=True) * directions  # the channels' sum weighs where the light is
    return tuple(np.stack([np.bincount(cell, weights=a[:, c], minlength=count) for c in range(3)], axis=1) for a in (light, moment))


def sampled_light(emitter) -> tuple[np.ndarray, np.ndarray]:
    """(directions (N, 3), each one's share of the emitter's light (N, 3)) from the emitter's own ``sample_direction``
    on a stratified grid of SAMPLED_SIDE² points: radiance over density, over N, so that the shares of any set of
    directions estimate the light it holds (the same every render: no random numbers)."""
    import drjit as dr
    import mitsuba as mi

    side = (np.arange(SAMPLED_SIDE, dtype=np.float32) + 0.5) / SAMPLED_SIDE
    u, v = np.meshgrid(side, side)
    n = u.size
    ds, weight = emitter.sample_direction(dr.zeros(mi.Interaction3f, n), mi.Point2f(u.ravel(), v.ravel()), True)
    directions = np.array(ds.d, dtype=np.float64).T.reshape(-1, 3)
    return directions, np.array(weight, dtype=np.float64).T.reshape(-1, 3) / n


def light_directions(moments: np.ndarray) -> np.ndarray:
    """Where each cell's light comes from: the mean direction of its light (a sun inside a cell: the sun's), or the cell's
    centre where it has none."""
    centres = fibonacci_sphere(moments.shape[0])
    length = np.linalg.norm(moments, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(length > 1e-12 * max(float(length.max()), 1e-300), moments / length, centres)
