"""The rank-1 lattice every sampled estimate in gra-mi draws its points from: N points {((j + ½) / N, j / φ mod 1)}
shifted by a uniform offset (Cranley–Patterson rotation). Each point is uniform when the shift is, so an estimate stays
unbiased, and the N points are spread over the square (less noise than independent points)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

GOLDEN = 0.6180339887498949  # the second coordinate steps by 1/φ


def fraction(x):
    """x mod 1."""
    return x - dr.floor(x)


def lattice_point(j, count, shift=None) -> mi.Point2f:
    """Point j (a Dr.Jit Float) of the ``count``-point lattice (an int, or a Float per lane), shifted by ``shift`` (a
    Point2f; none: unshifted) mod 1."""
    point = mi.Point2f((j + 0.5) / count, j * GOLDEN)
    return fraction(point + shift) if shift is not None else fraction(point)
