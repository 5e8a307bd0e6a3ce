"""UV-space one-bounce rendering, part 1: the UV atlas and per-frame texel geometry (paper Sec. 3.1, Supp. "Details about
Microfacet Rendering").

The paper shades in the 512² UV space of the tracked mesh. Pieces, in the order they are used:

- :class:`UVAtlas` — once per topology: which triangle and barycentrics each texel centre falls in (Mitsuba's
  ``eval_parameterization``), and a validity mask. UVs never change across frames, so this is never redone.
- :class:`TexelGeometry` — per frame: texel positions, shading normals and geometric normals, interpolated from the
  frame's vertices with the cached barycentrics (~1 ms).
- :class:`~gra_mi.render.visibility.VisibilityCache` (visibility.py) — per frame and LED layout: one bit per (texel, LED), "the LED is above the texel's
  horizon and nothing blocks the segment". It depends only on geometry, so it is reused across envmaps, cameras,
  materials and fitting iterations, in memory and on disk.
- :func:`~gra_mi.render.shading.shade_texels` (shading.py) — per view: Σ over LEDs that are on of bit · I/d² · f(ωi, ωk) cosθk, in one Dr.Jit loop
  over LED arrays. Changing the envmap only changes the intensities: nothing is re-traced.
- :func:`~gra_mi.render.rasterize.rasterize_to_camera` (rasterize.py) — the texture seen by a camera, with alpha: the image-space coarse render.

Texel (row i, column j) of an R×R texture sits at uv = ((j + ½)/R, (i + ½)/R); row 0 is v ≈ 0, as Mitsuba's
bitmap textures read it (docs/conventions.md).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

logger = logging.getLogger(__name__)


def texel_uvs(resolution: int) -> np.ndarray:
    """Texel-centre UVs, (R·R, 2), row-major (row i = v index)."""
    c = (np.arange(resolution) + 0.5) / resolution
    u, v = np.meshgrid(c, c, indexing="xy")
    return np.stack([u.ravel(), v.ravel()], axis=1)


MIN_RESOLUTION = 8  # the smallest UV texture a stage takes: below it a body's layout holds few texel centres, or none


@dataclass
class UVAtlas:
    """Texel → (triangle, barycentrics) for the texels the mesh's UV atlas covers."""

    resolution: int
    texel_index: np.ndarray  # (M,) flat index (row * R + col) of each valid texel
    faces: np.ndarray  # (M, 3) vertex indices of its triangle
    barycentrics: np.ndarray  # (M, 3)
    device_arrays: dict = field(default_factory=dict, repr=False, compare=False)
    """Mitsuba variant → (face columns, barycentric columns) as Dr.Jit arrays, filled by :meth:`on_device`; (variant,
    "grid") → :meth:`texel_grid` on the device."""
    _nearest: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def num_texels(self) -> int:
        return int(self.texel_index.size)

    @property
    def mask(self) -> np.ndarray:
        m = np.zeros(self.resolution * self.resolution, bool)
        m[self.texel_index] = True
        return m.reshape(self.resolution, self.resolution)

    @classmethod
    def build(cls, faces: np.ndarray, uvs: np.ndarray, resolution: int = 512) -> UVAtlas:
        """Rasterise the atlas with Mitsuba's UV-space point location (needs a variant set)."""
        mesh = mi.Mesh("atlas", uvs.shape[0], faces.shape[0], has_vertex_texcoords=True)
        params = mi.traverse(mesh)
        # Geometry is irrelevant for the UV look-up; put the UVs in the plane so the mesh is valid.
        params["vertex_positions"] = mi.Float(np.concatenate([uvs, np.zeros((uvs.shape[0], 1))], axis=1).ravel().astype(np.float32))
        params["faces"] = mi.UInt32(faces.ravel().astype(np.uint32))
        params["vertex_texcoords"] = mi.Float(uvs.ravel().astype(np.float32))
        params.update()
        query = texel_uvs(resolution)
        si = mesh.eval_parameterization(mi.Point2f(*query.T.astype(np.float32)))
        valid = np.array(si.is_valid())
        prim = np.array(si.prim_index)[valid]
        tri = faces[prim]
        # Barycentrics of the texel centre in the UV triangle (float64: tiny triangles are common).
        a, b, c = (uvs[tri[:, k]].astype(np.float64) for k in range(3))
        p = query[valid]
        v0, v1, v2 = b - a, c - a, p - a
        d00, d01, d11 = np.sum(v0 * v0, 1), np.sum(v0 * v1, 1), np.sum(v1 * v1, 1)
        d20, d21 = np.sum(v2 * v0, 1), np.sum(v2 * v1, 1)
        denom = d00 * d11 - d01 * d01
        ok = np.abs(denom) > 1e-30  # degenerate UV triangles cannot hold a texel
        denom = np.where(ok, denom, 1.0)
        w1 = (d11 * d20 - d01 * d21) / denom
        w2 = (d00 * d21 - d01 * d20) / denom
        bary = np.clip(np.stack([1 - w1 - w2, w1, w2], axis=1), 0.0, 1.0)
        bary /= bary.sum(axis=1, keepdims=True)
        index = np.flatnonzero(valid)[ok]
        return cls(resolution, index, tri[ok].astype(np.int64), bary[ok])

    def bake_vertex_attribute(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Interpolate a per-vertex attribute (V, C) into an (R, R, C) texture (``fill`` outside the atlas)."""
        out = np.full((self.resolution * self.resolution, values.shape[1]), fill, dtype=np.float32)
        out[self.texel_index] = np.einsum("mk,mkc->mc", self.barycentrics, values[self.faces])
        return out.reshape(self.resolution, self.resolution, values.shape[1])

    def scatter(self, texel_values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(M, C) values of the valid texels → (R, R, C) texture."""
        out = np.full((self.resolution * self.resolution, texel_values.shape[1]), fill, dtype=np.float32)
        out[self.texel_index] = texel_values
        return out.reshape(self.resolution, self.resolution, texel_values.shape[1])

    def gather(self, texture: np.ndarray) -> np.ndarray:
        """(R, R, C) texture → (M, C) values at the valid texels."""
        return texture.reshape(self.resolution * self.resolution, -1)[self.texel_index]

    def texel_grid(self) -> np.ndarray:
        """(R·R,) the valid-texel index at each texel of the texture, -1 outside the atlas."""
        grid = np.full(self.resolution * self.resolution, -1, np.int64)
        grid[self.texel_index] = np.arange(self.num_texels)
        return grid

    def texel_grid_on_device(self) -> mi.Int32:
        """:meth:`texel_grid` as a Dr.Jit array, uploaded once per variant."""
        key = (mi.variant(), "grid")
        if key not in self.device_arrays:
            self.device_arrays[key] = mi.Int32(self.texel_grid().astype(np.int32))
        return self.device_arrays[key]

    def dilated(self, texels: np.ndarray, radius: int) -> np.ndarray:
        """``texels`` and every valid texel within ``radius`` texels of one in the atlas (a (2·radius + 1)² window),
        sorted."""
        if radius == 0:
            return np.asarray(texels, np.int64)
        from scipy.ndimage import binary_dilation

        picked = np.zeros(self.resolution * self.resolution, bool)
        picked[self.texel_index[np.asarray(texels, np.int64)]] = True
        grown = binary_dilation(picked.reshape(self.resolution, self.resolution), np.ones((2 * radius + 1,) * 2, bool))
        return np.flatnonzero(grown.ravel()[self.texel_index])

    def nearest_texel(self) -> np.ndarray:
        """(R·R,) the valid-texel index at each texel of the texture, the nearest valid one's where the texel is
        outside the atlas: a UV looked up at a chart's edge (a ray's hit) lands on the chart, not on the background."""
        if self._nearest is None:
            from scipy.ndimage import distance_transform_edt

            lookup = self.texel_grid()
            if self.num_texels and self.num_texels < lookup.size:
                _, (rows, cols) = distance_transform_edt(~self.mask, return_indices=True)
                lookup = lookup[(rows * self.resolution + cols).ravel()]
            self._nearest = lookup
        return self._nearest

    def on_device(self) -> tuple[list[mi.UInt32], list[mi.Float]]:
        """The three vertex-index columns of ``faces`` and of ``barycentrics`` as Dr.Jit arrays, uploaded once per variant."""
        cache = self.device_arrays
        if mi.variant() not in cache:
            cache[mi.variant()] = (
                [mi.UInt32(np.ascontiguousarray(self.faces[:, k], np.uint32)) for k in range(3)],
                [mi.Float(np.ascontiguousarray(self.barycentrics[:, k], np.float32)) for k in range(3)],
            )
        return cache[mi.variant()]


@dataclass
class TexelGeometry:
    """Per-frame surface at the valid texels (float32 Dr.Jit arrays)."""

    position: mi.Point3f
    normal: mi.Vector3f  # interpolated shading normal
    geo_normal: mi.Vector3f  # the triangle's normal
    digest: str  # hash of the frame's vertices, the atlas's texels and the set (keys the visibility and bounce caches)

    @classmethod
    def from_frame(cls, atlas: UVAtlas, vertices: np.ndarray, normals: np.ndarray, surroundings: str = "") -> TexelGeometry:
        """Interpolate the frame's mesh at the texels, on the Dr.Jit device (on a GPU the NumPy version of this cost
        more than tracing the frame's visibility). ``surroundings``: a hash of what else the rays meet (the scene's set:
        :attr:`~gra_mi.stage.scene.LightstageScene.set_digest`), part of the digest."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces, bary = atlas.on_device()
        verts = mi.Point3f(*vertices.T)
        norms = mi.Vector3f(*np.asarray(normals, np.float32).T)
        v0, v1, v2 = (dr.gather(mi.Point3f, verts, f) for f in faces)
        p = bary[0] * v0 + bary[1] * v1 + bary[2] * v2
        n = bary[0] * dr.gather(mi.Vector3f, norms, faces[0])
        n += bary[1] * dr.gather(mi.Vector3f, norms, faces[1]) + bary[2] * dr.gather(mi.Vector3f, norms, faces[2])
        n /= dr.maximum(dr.norm(n), 1e-12)
        ng = dr.cross(v1 - v0, v2 - v0)
        length = dr.norm(ng)
        # Sliver triangles have no reliable geometric normal: fall back to the shading normal.
        ng = dr.select(length > 1e-20, ng / dr.maximum(length, 1e-20), n)
        dr.eval(p, n, ng)
        # The atlas is part of the key: the same frame at another UV resolution has other texels (and other bits).
        key = hashlib.sha1(vertices.tobytes())
        key.update(np.ascontiguousarray(atlas.texel_index, np.int64).tobytes())
        key.update(np.ascontiguousarray(atlas.faces, np.int64).tobytes())
        key.update(surroundings.encode())
        return cls(mi.Point3f(p), mi.Vector3f(n), mi.Vector3f(ng), key.hexdigest()[:16])


@dataclass
class SurfaceFilter:
    """A weighted average of a per-texel quantity over each texel's UV neighbours that lie on the same surface: within
    ``radius`` texels in the atlas, near in space (a Gaussian in world distance, σ = ``radius`` × the texel's own
    spacing, cut at 2σ: texels across a chart seam are far) and facing the same way (normals within ~25°). For a
    quantity that varies slowly over the surface and is estimated per texel with noise (the light after the first
    bounce, from K rays each): averaging (2·radius + 1)² estimates cuts the noise up to that factor in variance."""

    neighbours: mi.UInt32  # (N · W,) the W window entries of each output texel (the texel itself where a slot is empty)
    weights: mi.Float  # (N · W,) normalised per output texel
    width: int  # W
    rows: mi.UInt32 | None = None  # (N,) the output texels (a domain's); None: every texel, in order
    count: int = 0  # texels of the atlas (the output's size)

    @classmethod
    def build(cls, atlas: UVAtlas, geom: TexelGeometry, radius: int, domain: np.ndarray | None = None) -> SurfaceFilter:
        """``domain``: the texels whose values exist (None: all); only they are averaged, and only they are averaged
        into (elsewhere the output is 0: a job's cameras see no texel outside it)."""
        r, m = atlas.resolution, atlas.num_texels
        rows = np.arange(m) if domain is None else np.unique(np.asarray(domain, np.int64))
        p, n = np.array(geom.position, np.float64).T, np.array(geom.normal, np.float64).T
        grid = atlas.texel_grid()
        valid = np.ones(m, bool) if domain is None else np.isin(np.arange(m), rows)
        row, col = np.divmod(atlas.texel_index[rows], r)

        def at(dr_, dc):  # the texel at each output texel's offset (dr_, dc) in the atlas, -1 where none
            rr, cc = row + dr_, col + dc
            inside = (rr >= 0) & (rr < r) & (cc >= 0) & (cc < r)
            out = np.full(len(rows), -1, np.int64)
            out[inside] = grid[rr[inside] * r + cc[inside]]
            return out

        def distance(other):
            return np.where(other >= 0, np.linalg.norm(p[rows] - p[np.maximum(other, 0)], axis=1), np.inf)

        spacing = np.min([distance(at(*o)) for o in ((0, 1), (0, -1), (1, 0), (-1, 0))], axis=0)
        sigma = radius * np.where(np.isfinite(spacing), spacing, 0.0)
        offsets = [(a, b) for a in range(-radius, radius + 1) for b in range(-radius, radius + 1)]
        index = np.empty((len(rows), len(offsets)), np.int64)
        weight = np.zeros((len(rows), len(offsets)))
        for k, (a, b) in enumerate(offsets):
            other = at(a, b)
            d2 = np.square(distance(other))
            same = (other >= 0) & valid[np.maximum(other, 0)] & (np.sum(n[rows] * n[np.maximum(other, 0)], axis=1) > 0.9)
            close = same & (d2 <= 4.0 * sigma**2)
            index[:, k] = np.where(close, other, rows)
            weight[:, k] = np.where(close, np.exp(-0.5 * d2 / np.maximum(sigma, 1e-12) ** 2), 0.0)
        centre = len(offsets) // 2
        weight[:, centre] = 1.0  # a texel always counts itself (also where its spacing is unknown)
        weight /= weight.sum(axis=1, keepdims=True)
        neighbours, weights = mi.UInt32(index.ravel().astype(np.uint32)), mi.Float(weight.ravel().astype(np.float32))
        return cls(neighbours, weights, len(offsets), None if domain is None else mi.UInt32(rows.astype(np.uint32)), m)

    def apply(self, values: mi.Color3f) -> mi.Color3f:
        averaged = dr.block_sum(dr.gather(mi.Color3f, values, self.neighbours) * self.weights, self.width)
        if self.rows is None:
            return averaged
        out = dr.zeros(mi.Color3f, self.count)
        dr.scatter(out, averaged, self.rows)
        return out
