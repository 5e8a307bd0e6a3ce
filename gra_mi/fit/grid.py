"""The closed form's roughness grid: for each candidate roughness, every texel's least-squares albedo and its squared
error over the views, from sums the views add on the device; then the roughness at the error's minimum.

Per texel and channel, with D the diffuse part per unit albedo, S the specular part at a candidate and O the
observation: the error of albedo a is Σ (a D + S − O)² = a² ΣD² + 2a ΣDS − 2a ΣDO + ΣS² − 2 ΣOS + ΣO², minimal
at a = (ΣDO − ΣDS) / ΣD² (clipped to [0, 1]). The sums are float64 (the error is a difference of large terms), of
products of float32 values, which float64 holds exactly; each view adds each of its texels once, so the sums add up
in the views' order on every run, whatever the device.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.fit.maps import DEFAULT_ALBEDO


class GridSums:
    """ΣD², ΣDO, ΣO² and, per candidate, ΣDS, ΣS², ΣOS, per texel and channel, accumulated view by view."""

    def __init__(self, num_texels: int, candidates: int):
        self.m, self.k = num_texels, candidates
        self.sums = dr.zeros(mi.Float64, (3 + 3 * candidates) * num_texels * 3)

    def add(self, texels: mi.UInt32, observed: mi.Color3f, diffuse: mi.Color3f, specs: tuple) -> None:
        """One view: its (distinct) texels, their observations, D and the S of each candidate."""
        m = dr.opaque(mi.UInt32, self.m)  # a kernel input: one kernel for every view
        for c in range(3):
            d, o = mi.Float64(diffuse[c]), mi.Float64(observed[c])
            terms = [d * d, d * o, o * o]
            for spec in specs:
                s = mi.Float64(spec[c])
                terms += [d * s, s * s, o * s]
            for j, term in enumerate(terms):
                dr.scatter_reduce(dr.ReduceOp.Add, self.sums, term, (j * m + texels) * 3 + c)
        dr.eval(self.sums)

    def error(self, ranks=None) -> np.ndarray:
        """(candidates, M) squared error of each candidate with its closed-form albedo (texels no view saw: 0); with
        ``ranks`` (:class:`~gra_mi.fit.ranks.FitRanks`), of the sums every process added."""
        sums = np.asarray(self.sums) if ranks is None else ranks.sum(self.sums)
        sums = sums.reshape(3 + 3 * self.k, self.m, 3)
        s_dd, s_do, s_oo = sums[0], sums[1], sums[2]
        s_ds, s_ss, s_os = sums[3::3], sums[4::3], sums[5::3]
        with np.errstate(invalid="ignore", divide="ignore"):
            albedo = np.clip((s_do[None] - s_ds) / s_dd[None], 0.0, 1.0)
        albedo = np.where(s_dd[None] > 0, albedo, DEFAULT_ALBEDO)
        error = s_oo[None] - 2 * albedo * s_do[None] + albedo**2 * s_dd[None] + s_ss - 2 * s_os + 2 * albedo * s_ds
        return error.sum(axis=2)


def refine_on_grid(error: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Per texel, the minimum of the parabola through the best candidate and its neighbours (clamped to the grid)."""
    m = error.shape[1]
    best = np.argmin(error, axis=0)
    lo, hi = np.clip(best - 1, 0, len(grid) - 1), np.clip(best + 1, 0, len(grid) - 1)
    e0, e1, e2 = (error[idx, np.arange(m)] for idx in (lo, best, hi))
    curvature = e0 - 2 * e1 + e2
    with np.errstate(invalid="ignore", divide="ignore"):
        shift = np.where((curvature > 1e-30) & (lo != best) & (hi != best), 0.5 * (e0 - e2) / curvature, 0.0)
    return np.clip(grid[best] + np.clip(shift, -1, 1) * (grid[1] - grid[0]), 0.0, 1.0).astype(np.float32)
