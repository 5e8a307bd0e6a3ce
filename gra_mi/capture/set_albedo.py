"""How much light a set shape's BSDF reflects, as one colour for the whole shape: its diffuse lobes' and all its lobes'
directional albedo (:func:`~gra_mi.render.bounce.albedo`), averaged over its surface and the directions it is seen
from. ``from-scene`` writes a diffuse stand-in of it where a shape's own BSDF cannot be carried, and says what that
leaves out; ``export --set`` turns it into a preview material."""

from __future__ import annotations

import numpy as np


def shape_albedos(scene, shape, samples: int = 1024) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(the mean diffuse albedo of ``shape``'s BSDF, the mean albedo of all its lobes), RGB, not clipped; each None
    where no sample of it is finite. Points spread over the shape are found by rays (so that textures and vertex
    colours are read where they lie) and seen from cosine-distributed directions on their front side; a point another
    shape covers (a twin in the same place, a box on the floor) is read at the sample itself."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.bounce import albedo
    from gra_mi.render.lattice import lattice_point

    i = dr.arange(mi.Float, samples)
    ps = shape.sample_position(0.0, lattice_point(i, samples))
    si = scene.ray_intersect(mi.Ray3f(ps.p + ps.n * 1e-3, -ps.n))
    found = si.is_valid() & (si.shape == mi.ShapePtr(shape))
    at_sample = mi.SurfaceInteraction3f(ps, dr.zeros(mi.Color0f))
    at_sample.shape = mi.ShapePtr(shape)
    si = dr.select(found, si, at_sample)
    on_shape = dr.isfinite(ps.p.x) & (ps.pdf > 0)
    si.wi = mi.warp.square_to_cosine_hemisphere(lattice_point(i, samples, mi.Point2f(0.5, 0.25)))  # (its front side)
    diffuse, every = (_finite_mean(albedo(shape.bsdf(), si, on_shape, 16, only), on_shape) for only in (True, False))
    return diffuse, every


def set_material(scene, shape, samples: int = 1024) -> tuple[tuple[float, float, float], bool, float]:
    """(the mean diffuse albedo of ``shape``'s BSDF, not clipped, 0.5 where unknown; whether it reflects from both
    sides; the mean albedo of its other lobes): :func:`shape_albedos`."""
    import mitsuba as mi

    diffuse, every = shape_albedos(scene, shape, samples)
    glossy = float(max(0.0, np.mean(every) - np.mean(diffuse))) if diffuse is not None and every is not None else 0.0
    rgb = np.full(3, 0.5) if diffuse is None else np.maximum(diffuse, 0.0)
    return tuple(float(v) for v in rgb), bool(mi.has_flag(shape.bsdf().flags(), mi.BSDFFlags.BackSide)), glossy


def _finite_mean(rho, on_shape) -> np.ndarray | None:
    """The mean RGB of ``rho`` over the lanes ``on_shape`` whose values are finite (a texture's NaN or infinite texels
    say nothing of its colour); None where there are none."""
    import drjit as dr

    rho = np.array(dr.select(on_shape, rho, 0.0), np.float64).reshape(3, -1)[:, np.array(on_shape)]  # (a constant: one wide)
    rho = rho[:, np.isfinite(rho).all(axis=0)]
    return rho.mean(axis=1) if rho.shape[1] else None
