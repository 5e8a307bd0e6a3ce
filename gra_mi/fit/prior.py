"""The spatial prior of the material fit: smoothness over the body's surface, not over the UV image.

Neighbours are found in 3D among the texels of one frame (k nearest within a radius, normals agreeing), so

- texels next to each other in UV but on different charts (a chart boundary) are *not* neighbours, and
- texels on either side of a UV seam (far apart in UV, side by side on the body) *are*,

which a Laplacian on the UV grid gets both wrong. Two uses: the quadratic smoothness energy the optimiser adds to
its loss (:mod:`gra_mi.fit.optimize`), and :meth:`SurfaceGraph.fill`, which gives texels without evidence the
values of their neighbours (a confidence-weighted harmonic interpolation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NEIGHBOURS = 8  # k nearest texels considered per texel
RADIUS = 2.5  # … within this many typical texel spacings (the median nearest-neighbour distance)
MIN_NORMAL_COS = 0.5  # … and facing within 60°: two sides of a thin part (fingers, a sleeve) are not neighbours


@dataclass
class SurfaceGraph:
    """Undirected edges (i, j), i < j, between neighbouring valid texels."""

    i: np.ndarray
    j: np.ndarray
    num_texels: int
    spacing: float  # median distance between neighbouring texels (metres)

    @classmethod
    def build(cls, positions: np.ndarray, normals: np.ndarray) -> SurfaceGraph:
        from scipy.spatial import cKDTree

        m = positions.shape[0]
        k = min(NEIGHBOURS + 1, m)
        dist, idx = cKDTree(positions).query(positions, k=k)
        spacing = float(np.median(dist[:, 1])) if k > 1 else 0.0
        ok = (dist[:, 1:] < RADIUS * spacing) & (np.einsum("mc,mkc->mk", normals, normals[idx[:, 1:]]) > MIN_NORMAL_COS)
        a = np.repeat(np.arange(m), k - 1).reshape(m, k - 1)[ok]
        b = idx[:, 1:][ok]
        pairs = np.unique(np.stack([np.minimum(a, b), np.maximum(a, b)], axis=1), axis=0)
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        return cls(pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64), m, spacing)

    @property
    def num_edges(self) -> int:
        return int(self.i.size)

    def laplacian(self):
        import scipy.sparse as sp

        m = self.num_texels
        w = sp.coo_matrix((np.ones(self.num_edges), (self.i, self.j)), shape=(m, m))
        w = (w + w.T).tocsr()
        return sp.diags(np.asarray(w.sum(axis=1)).ravel()) - w

    def fill(self, values: np.ndarray, confidence: np.ndarray, strength: float, default: float) -> np.ndarray:
        """Minimise Σ c_t (x_t − v_t)² + strength · Σ_edges (x_i − x_j)², per channel.

        Confident texels keep (nearly) their values, texels with confidence 0 take a smooth interpolation of their
        neighbours'; a graph component with no confident texel at all takes ``default``.
        """
        return self.filler(confidence, strength)(values, default)

    def filler(self, confidence: np.ndarray, strength: float):
        """:meth:`fill` with the matrix factorised once, for repeated fills with the same confidence."""
        import scipy.sparse as sp
        import scipy.sparse.linalg as spl

        c = np.asarray(confidence, np.float64)
        ridge = 1e-6 * max(float(c.max()), 1e-12)  # pins components without evidence to the default
        solve = spl.factorized((sp.diags(c + ridge) + strength * self.laplacian()).tocsc())

        def fill(values: np.ndarray, default: float) -> np.ndarray:
            values = values.reshape(self.num_texels, -1).astype(np.float64)
            return np.stack([solve(c * values[:, ch] + ridge * default) for ch in range(values.shape[1])], axis=1)

        return fill
