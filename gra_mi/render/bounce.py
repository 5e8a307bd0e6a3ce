"""Light after the first bounce, in UV space (docs/accuracy.md, "Interreflections").

Light transport is linear, so the light a texel receives from the rest of the body is a fixed, sparse texel-to-texel
operator per frame geometry, traced once and cached like the visibility:

    P[x, y] = Σ_k [ray k of texel x first hits the body at texel y] · T(cosθx,k) T(cosθy,k) / K

from K cosine-distributed rays per texel (closest hit, its UV looked up in the atlas; T is the diffuse layer's Fresnel
transmission, :func:`~gra_mi.render.brdf.diffuse_transmission`). With E the one-bounce diffuse radiance per unit albedo
that leaves each texel along its normal (the view-independent part of the LED sum), the light that leaves the body
per unit T after b bounces is U = Σ_{j < b−1} (a ⊙ P)^j (a ⊙ E), and a texel's radiance toward a camera gains
a(x) T(ω_view) (P U)(x). Both ends of every extra segment are the diffuse layer (Lambert with its Fresnel
transmission); the specular lobes of later bounces are left out (docs/accuracy.md measures what that costs).

Rays that first hit the set (the scene's other shapes: a floor, a wall) bring the light the set reflects, as a
Lambertian surface of its BSDF's diffuse albedo toward the ray (:func:`albedo`: a diffuse BSDF's reflectance, a
plastic's diffuse lobe under its coat; a one-sided BSDF seen from behind reflects nothing), lit by the LEDs and near
lights it sees (:class:`SetHits`), plus its glossy lobes' light, Mitsuba's own BSDF evaluated at the hit toward each
light (:class:`SetGlossyLobe`; a delta lobe, a mirror's, is left out). The light the body sends to the set and back is
left out.

Only texels whose hemisphere sees the body (or the set) trace rays. A point of the body above a texel's tangent plane
is exactly what one of its rays can hit (the first surface along the segment to that point lies above the plane too),
so comparing the plane with the vertices of the body's convex hull (and the corners of the set's boxes) decides it,
exactly and without a ray: the top of the head and most of the chest and back trace nothing and receive nothing.
"""

from __future__ import annotations

import hashlib
import zipfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.io import atomic_path
from gra_mi.core.runtime import concat
from gra_mi.render import brdf
from gra_mi.render.atlas import SurfaceFilter, TexelGeometry, UVAtlas
from gra_mi.render.lattice import fraction, lattice_point
from gra_mi.render.shading import local_view
from gra_mi.render.transport import DEFAULT_RAYS
from gra_mi.render.visibility import RAY_EPSILON

PLASTIC_STEP = 0.7548776662466927  # 1/ρ (the plastic number): a 1-D lattice's step, independent of 1/φ's
CHUNK_RAYS = 1 << 20  # rays per kernel: bounds the surface interactions held at once (~100 MB)


SET_CELL = 0.01
"""Metres: the smallest cell of the set whose reflected light is computed once (:meth:`SetHits.grouped`)."""
SET_CELL_ANGLE = 0.05
"""Radians: a cell of the set is at most this wide as its rays' texels see it, and as its nearest LED sees it
(:meth:`SetHits.grouped`): far finer than the rays' own spacing, and than the light's changes over the set."""
SET_ALBEDO_SAMPLES = 8
"""BSDF samples per set hit for its diffuse albedo (:func:`albedo`): a Lambertian BSDF's is exact at any count;
a coated one's noise averages out over a texel's rays."""
SET_ALBEDO_VERSION = "diffuse-albedo+glossy"  # in the cache key: operators cached with eval_diffuse_reflectance
SET_HIT_FIELDS = ("receivers", "direction", "cell", "reflectance", "glossy")
SET_CELL_FIELDS = ("cell_position", "cell_normal", "cell_geo_normal")
SET_FIELDS = SET_HIT_FIELDS + SET_CELL_FIELDS
RAW_HITS = ("receivers", "distance", "direction", "position", "normal", "geo_normal", "reflectance", "glossy")


@dataclass
class SetHits:
    """The rays of a bounce operator that first hit the set, on a side of it that reflects: the set sends back along
    each the light it takes in from the LEDs and near lights (:meth:`~gra_mi.render.relighter.Relighter.set_light`),
    times its diffuse albedo; that light is computed once per cell of the set, at one of its hits. A hit on a BSDF with
    a glossy lobe adds that lobe's light toward each light, per hit (:class:`SetGlossyLobe`)."""

    receivers: np.ndarray  # (S,) uint32: the texel whose ray it is
    direction: np.ndarray  # (S, 3) float32: the ray's unit direction (world), from the receiver toward the set
    cell: np.ndarray  # (S,) uint32: the cell it hit
    reflectance: np.ndarray  # (S, 3) float32: the set's BSDF's diffuse albedo where it hit, toward the receiver
    glossy: np.ndarray  # (S,) bool: whether that BSDF has a glossy lobe (evaluated toward each light: SetGlossyLobe)
    cell_position: np.ndarray  # (C, 3) float32: a hit in each cell
    cell_normal: np.ndarray  # (C, 3) float32: the set's shading normal there, turned toward that hit's receiver
    cell_geo_normal: np.ndarray  # (C, 3) float32: its geometric normal, turned the same way

    @classmethod
    def empty(cls) -> SetHits:
        vectors = [np.zeros((0, 3), np.float32) for _ in range(5)]
        return cls(np.zeros(0, np.uint32), vectors[0], np.zeros(0, np.uint32), vectors[1], np.zeros(0, bool), *vectors[2:])

    @classmethod
    def grouped(cls, raw: dict[str, np.ndarray], led_positions: np.ndarray | None) -> SetHits:
        """The hits (``raw``: :data:`RAW_HITS`) grouped in cells, by place and normal. A cell is :data:`SET_CELL` wide
        near its rays' texels or near an LED, and twice as wide each time both are twice as far
        (:data:`SET_CELL_ANGLE`): a floor under a body is hit by millions of rays at 512² and far fewer cells, the
        body's shadow by its feet stays sharp to a centimetre, and so does the light pooled under a low LED."""
        from scipy.spatial import cKDTree

        reach = raw["distance"]
        if led_positions is not None and len(led_positions) and len(reach):
            reach = np.minimum(reach, cKDTree(led_positions).query(raw["position"], workers=-1)[0])
        level = np.ceil(np.log2(np.maximum(SET_CELL_ANGLE * reach / SET_CELL, 1.0)))
        where = np.floor(raw["position"] / (SET_CELL * 2.0 ** level[:, None]))
        key = np.concatenate([level[:, None], where, np.round(raw["normal"] * 4)], axis=1).astype(np.int64)
        first, inverse = _distinct_rows(key)
        cells = (raw[f][first] for f in ("position", "normal", "geo_normal"))
        return cls(raw["receivers"], raw["direction"], inverse.astype(np.uint32), raw["reflectance"], raw["glossy"], *cells)

    @property
    def count(self) -> int:
        return int(self.receivers.size)

    def subset(self, keep: np.ndarray) -> SetHits:
        """The hits ``keep`` selects, and only their cells."""
        used, cell = np.unique(self.cell[keep], return_inverse=True)
        cells = (getattr(self, f)[used] for f in SET_CELL_FIELDS)
        cell = cell.reshape(-1).astype(np.uint32)
        return SetHits(self.receivers[keep], self.direction[keep], cell, self.reflectance[keep], self.glossy[keep], *cells)

    @cached_property
    def geometry(self) -> tuple[TexelGeometry, mi.UInt32]:
        """The cells as texels of their own (for the LED visibility and the LED loop), and each hit's cell."""
        p, n, ng = (np.ascontiguousarray(getattr(self, f), np.float32) for f in SET_CELL_FIELDS)
        digest = hashlib.sha1(b"set cells")
        for values in (p, n, ng):
            digest.update(values.tobytes())
        geom = TexelGeometry(mi.Point3f(*p.T), mi.Vector3f(*n.T), mi.Vector3f(*ng.T), digest.hexdigest()[:16])
        return geom, mi.UInt32(self.cell)


def _distinct_rows(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the first row of each distinct row of ``key``, each row's distinct row), as ``np.unique(key, axis=0)`` gives
    them but about 10× faster: the rows hashed to one integer (FNV-1a), checked against their group's first row (a
    collision, most unlikely, falls back to the exact sort)."""
    h = np.full(len(key), 0xCBF29CE484222325, np.uint64)
    with np.errstate(over="ignore"):
        for column in key.T:
            h = (h ^ column.astype(np.uint64)) * np.uint64(0x100000001B3)
    _, first, inverse = np.unique(h, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    if not (key[first][inverse] == key).all():
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        return first, inverse.reshape(-1)
    # In the keys' order, as the exact sort gives them: neighbouring cells' shadow rays then run side by side (in the
    # hashes' order the cells' visibility traced 2× slower).
    order = np.lexsort(key[first].T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse]


@dataclass
class BounceOperator:
    """The sparse operator P of one frame's geometry: one entry per ray that hit the body (misses are not stored),
    sorted by the texel whose ray it is (each texel's sum then adds its rays in one order: the same image every run)."""

    receivers: np.ndarray  # (E,) uint32: the texel whose ray it is
    sources: np.ndarray  # (E,) uint32: the texel the ray hit
    direction: np.ndarray  # (E, 3) float32: the ray's unit direction (world), from the receiver toward the source
    num_texels: int
    rays: int
    traced: int  # texels that traced rays (their hemisphere sees the body)
    domain: np.ndarray | None = None  # the texels it answers for (:meth:`restricted`); None: every texel
    set_hits: SetHits = field(default_factory=SetHits.empty)  # the rays that hit the set

    @property
    def entries(self) -> int:
        return int(self.receivers.size)

    @property
    def nbytes(self) -> int:
        return int(self.receivers.nbytes + self.sources.nbytes + self.direction.nbytes) + sum(
            getattr(self.set_hits, f).nbytes for f in SET_FIELDS
        )

    def rays_to_gather(self) -> tuple[mi.UInt32, mi.Vector3f, mi.UInt32 | None]:
        """(receivers, directions, where each one's light is) of every ray that brings light, sorted by receiver (each
        texel's sum then adds its rays in one order: the same image every run). Light along the rays comes for those
        that hit the body, then those that hit the set (:func:`light_along_rays`); None: in that order already."""
        if getattr(self, "_gathered", (None,))[0] != mi.variant():
            r = np.concatenate([self.receivers, self.set_hits.receivers]).astype(np.uint32)
            order = np.argsort(r, kind="stable") if self.set_hits.count else np.arange(len(r))
            d = np.ascontiguousarray(np.concatenate([self.direction, self.set_hits.direction])[order].T)
            where = mi.UInt32(order.astype(np.uint32)) if self.set_hits.count else None
            self._gathered = (mi.variant(), mi.UInt32(r[order]), mi.Vector3f(*d), where)
        return self._gathered[1:]

    def device(self) -> tuple[mi.UInt32, mi.UInt32, mi.Vector3f]:
        """(receivers, sources, directions) as Dr.Jit arrays, uploaded once per variant."""
        if getattr(self, "_device", (None,))[0] != mi.variant():
            d = np.ascontiguousarray(self.direction.T)
            self._device = (mi.variant(), mi.UInt32(self.receivers), mi.UInt32(self.sources), mi.Vector3f(*d))
        return self._device[1:]

    def gather_diffuse(self, geom: TexelGeometry, light: mi.Color3f) -> mi.Color3f:
        """(1/K) Σ_k T(cosθx,k) L_k per texel: the light along each ray (``light``, per entry) that the receiving
        texel's diffuse layer takes in, per unit albedo and T(ω_view) (0 where a texel traced nothing)."""
        if self.entries + self.set_hits.count == 0:  # a body that sees neither itself (a convex one) nor a set
            return dr.zeros(mi.Color3f, self.num_texels)
        r, d, where = self.rays_to_gather()
        light = light if where is None else dr.gather(mi.Color3f, light, where)
        cos_x = dr.dot(d, dr.gather(mi.Vector3f, geom.normal, r))
        out = dr.zeros(mi.Color3f, self.num_texels)
        dr.scatter_reduce(dr.ReduceOp.Add, out, light * (brdf.diffuse_transmission(cos_x) / self.rays), r)
        return out

    def specular_response(self, geom: TexelGeometry, viewer, roughness: mi.Float, light: mi.Color3f) -> mi.Color3f:
        """(π/K) Σ_k f_spec(ω_view, ω_k) L_k per texel: the receivers' specular lobe lit by the light along their rays
        (the cosine-distributed rays' estimate of ∫ f_spec L cos dω), toward ``viewer`` (a camera position)."""
        if self.entries + self.set_hits.count == 0:
            return dr.zeros(mi.Color3f, self.num_texels)
        r, d, where = self.rays_to_gather()
        light = light if where is None else dr.gather(mi.Color3f, light, where)
        frame = mi.Frame3f(dr.gather(mi.Vector3f, geom.normal, r))
        wi = local_view(frame, dr.gather(mi.Point3f, geom.position, r), viewer)
        wo = frame.to_local(d)
        _, spec = brdf.PreparedBRDF(mi.Color3f(1.0), dr.gather(mi.Float, roughness, r), wi).eval_parts(wo)
        # spec = f_spec cosθo; the ray's pdf is cosθo / π. Rays left the texel above its horizon: cosθo > 0.
        value = spec * (dr.pi / self.rays) * dr.rcp(dr.maximum(wo.z, 1e-6))
        out = dr.zeros(mi.Color3f, self.num_texels)
        dr.scatter_reduce(dr.ReduceOp.Add, out, value * light, r)
        return out

    def restricted(self, receivers: np.ndarray) -> BounceOperator:
        """The entries of the rays of ``receivers`` only (a job's cameras need no others)."""
        keep = np.isin(self.receivers, receivers)
        picked = (self.receivers[keep], self.sources[keep], self.direction[keep])
        domain = np.unique(np.asarray(receivers, np.int64))
        on_set = self.set_hits.subset(np.isin(self.set_hits.receivers, receivers))
        return BounceOperator(*picked, self.num_texels, self.rays, self.traced, domain, on_set)

    def smoothed(self, atlas: UVAtlas, geom: TexelGeometry, received: mi.Color3f, radius: int) -> mi.Color3f:
        """``received`` (per texel, e.g. :meth:`gather_diffuse`'s) averaged over the same surface within ``radius``
        texels (:class:`~gra_mi.render.atlas.SurfaceFilter`, built once per operator and radius; 0: unchanged)."""
        if radius == 0 or self.entries == 0:
            return received
        filters = self.__dict__.setdefault("_filters", {})
        if radius not in filters:
            filters[radius] = SurfaceFilter.build(atlas, geom, radius, self.domain)
        return filters[radius].apply(received)

    def toward_receivers(self) -> mi.Vector3f:
        """Per entry: the direction from the source texel back to the receiver (world)."""
        return -self.device()[2]

    def by_source(self) -> tuple[np.ndarray, mi.Vector3f, tuple[mi.UInt32, mi.UInt32], mi.UInt32]:
        """The entries ordered by the texel their rays hit, for the LED loop over the sources: neighbouring lanes then
        walk the same LEDs and read neighbouring memory (about 1.5× faster than in the operator's order). Returns (the
        sources, the directions toward the receivers, (the distinct sources, each entry's index among them), where
        each entry of the operator went), kept with the operator and uploaded once per variant."""
        if getattr(self, "_by_source", (None,))[0] != mi.variant():
            order = np.argsort(self.sources, kind="stable")
            where = np.empty(len(order), np.uint32)
            where[order] = np.arange(len(order), dtype=np.uint32)
            texels, index = np.unique(self.sources[order], return_inverse=True)
            toward = mi.Vector3f(*np.ascontiguousarray(-self.direction[order].T))
            distinct = (mi.UInt32(texels.astype(np.uint32)), mi.UInt32(index.astype(np.uint32)))
            self._by_source = (mi.variant(), self.sources[order], toward, distinct, mi.UInt32(where))
        return self._by_source[1:]

    def sources_of(self, texels: np.ndarray) -> np.ndarray:
        """The texels whose light reaches ``texels`` in one bounce (sorted)."""
        picked = np.isin(self.receivers, np.asarray(texels, np.int64))
        return np.unique(self.sources[picked]).astype(np.int64)

    def closure(self, texels: np.ndarray, bounces: int) -> np.ndarray:
        """``texels`` and every texel whose light reaches them within ``bounces − 1`` extra bounces: where the
        one-bounce light (and its visibility) must be known to shade ``texels`` with ``bounces`` bounces."""
        needed = frontier = np.asarray(texels, np.int64)
        for _ in range(bounces - 1):
            frontier = np.setdiff1d(self.sources_of(frontier), needed)
            if not len(frontier):
                break
            needed = np.union1d(needed, frontier)
        return needed

    def save(self, path: Path) -> None:
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                on_set = {f"set_{f}": getattr(self.set_hits, f) for f in SET_FIELDS}
                np.savez(fh, receivers=self.receivers, sources=self.sources, direction=self.direction,
                         meta=np.array([self.num_texels, self.rays, self.traced], np.int64), **on_set)  # fmt: skip

    @classmethod
    def load(cls, path: Path, num_texels: int, rays: int) -> BounceOperator | None:
        """The operator cached at ``path``, or None if it is missing, cut short or not of this atlas and ray count."""
        try:
            with np.load(path, allow_pickle=False) as data:
                meta = data["meta"]
                # A file from before the set was traced has none: its key says there was no set (operator_key)
                on_set = SetHits(*(data[f"set_{f}"] for f in SET_FIELDS)) if "set_receivers" in data else SetHits.empty()
                op = cls(data["receivers"], data["sources"], data["direction"], int(meta[0]), int(meta[1]), int(meta[2]), None, on_set)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return None
        entries, hits = op.receivers.size, op.set_hits
        shapes = op.sources.shape == (entries,) and op.direction.shape == (entries, 3) and op.receivers.ndim == 1
        cells = len(hits.cell_position)
        shapes &= hits.receivers.ndim == 1 and hits.cell.shape == (hits.count,) and int(hits.cell.max(initial=0)) < max(cells, 1)
        shapes &= all(getattr(hits, f).shape == (hits.count, 3) for f in ("direction", "reflectance"))
        shapes &= hits.glossy.shape == (hits.count,)
        shapes &= all(getattr(hits, f).shape == (cells, 3) for f in SET_CELL_FIELDS)
        receivers = np.concatenate([op.receivers, hits.receivers]) if shapes else np.zeros(0)
        in_range = shapes and (receivers.size == 0 or int(max(op.sources.max(initial=0), receivers.max())) < num_texels)
        return op if (in_range and op.num_texels == num_texels and op.rays == rays) else None


def texels_that_see_the_body(geom: TexelGeometry, vertices: np.ndarray) -> np.ndarray:
    """Indices of the texels some point of the body (or the set) lies above the tangent plane (geometric normal) of: the
    only ones a ray can bring light after the first bounce to. Exact, from the vertices of the convex hull of
    ``vertices`` (the body's, and the corners of the set's bounding boxes: :func:`set_corners`)."""
    from scipy.spatial import ConvexHull, QhullError

    vertices = np.asarray(vertices, np.float64)
    try:
        corners = vertices[ConvexHull(vertices).vertices]
    except (QhullError, ValueError):  # a flat or degenerate body: every vertex is a corner
        corners = vertices
    p = np.array(geom.position, np.float64).T
    ng = np.array(geom.geo_normal, np.float64).T
    above = np.empty(len(p))
    for s in range(0, len(p), 8192):
        n = ng[s : s + 8192]
        above[s : s + 8192] = (n @ corners.T).max(axis=1) - np.sum(p[s : s + 8192] * n, axis=1)
    # A ray leaves RAY_EPSILON above the plane, so what it hits lies at least that far above it.
    return np.flatnonzero(above > 0.5 * RAY_EPSILON)


def trace_operator(
    scene: mi.Scene, subject: mi.Shape, geom: TexelGeometry, atlas: UVAtlas, uvs: np.ndarray, faces: np.ndarray,
    texels: np.ndarray, rays: int = DEFAULT_RAYS, seed: int = 0, led_positions: np.ndarray | None = None,
) -> BounceOperator:  # fmt: skip
    """Trace ``rays`` cosine-distributed rays from each of ``texels`` (a shifted Fibonacci lattice per texel: stratified
    and deterministic) and keep those that first hit ``subject`` (its ``faces`` and per-vertex ``uvs``) from its front,
    and those that first hit another shape of the scene (the set) on a side that reflects (:class:`SetHits`, its cells
    sized by the distance to the nearest of ``led_positions``)."""
    texels = np.asarray(texels, np.uint32)
    mesh = (
        mi.UInt32(atlas.nearest_texel().astype(np.uint32)),
        mi.Point2f(*np.asarray(uvs, np.float32).T),
        [mi.UInt32(np.ascontiguousarray(faces[:, k], np.uint32)) for k in range(3)],
    )
    per_chunk = max(CHUNK_RAYS // rays, 1)
    parts = [np.zeros(0, np.uint32), np.zeros(0, np.uint32), np.zeros((0, 3), np.float32), _no_raw_hits()]
    chunks = [parts]
    for start in range(0, len(texels), per_chunk):
        chunk = texels[start : start + per_chunk]
        chunks.append(_trace_chunk(scene, mi.ShapePtr(subject), geom, atlas.resolution, mesh, chunk, rays, seed))
    receivers, sources, direction = (np.concatenate([c[k] for c in chunks]) for k in range(3))
    on_set = SetHits.grouped({f: np.concatenate([c[3][f] for c in chunks]) for f in RAW_HITS}, led_positions)
    return BounceOperator(receivers, sources, direction, dr.width(geom.position), rays, len(texels), None, on_set)


def _trace_chunk(scene, subject_ptr, geom, resolution, mesh, chunk, rays, seed):
    lookup, uv_table, face_columns = mesh
    n = len(chunk)
    lane = dr.arange(mi.UInt32, n * rays)
    i = lane // rays
    k = lane - i * rays
    t = dr.gather(mi.UInt32, mi.UInt32(chunk), i)
    p = dr.gather(mi.Point3f, geom.position, t)
    frame = mi.Frame3f(dr.gather(mi.Vector3f, geom.normal, t))
    ng = dr.gather(mi.Vector3f, geom.geo_normal, t)
    # A Fibonacci lattice shifted per texel (Cranley–Patterson): stratified over the hemisphere, uncorrelated between
    # neighbouring texels, the same on every run.
    shift = mi.Point2f(mi.sample_tea_float32(t, 2 * seed), mi.sample_tea_float32(t, 2 * seed + 1))
    local = mi.warp.square_to_cosine_hemisphere(lattice_point(mi.Float(k), rays, shift))
    d = frame.to_world(local)
    above = (dr.dot(d, ng) > 0) & (local.z > 0)
    origin = mi.Point3f(p + ng * RAY_EPSILON)
    pi = scene.ray_intersect_preliminary(mi.Ray3f(origin, d), coherent=False, active=above)
    hit = above & pi.is_valid() & (pi.shape == subject_ptr)
    on_set = _set_hits(scene, t, origin, d, above & pi.is_valid() & (pi.shape != subject_ptr))
    # The hit's UV from its triangle's barycentrics (no full surface interaction: only the texel is needed).
    b1, b2 = pi.prim_uv.x, pi.prim_uv.y
    corner = [dr.gather(mi.Point2f, uv_table, dr.gather(mi.UInt32, f, pi.prim_index, hit), hit) for f in face_columns]
    uv = corner[0] * (1.0 - b1 - b2) + corner[1] * b1 + corner[2] * b2
    col = mi.UInt32(dr.clip(mi.Int32(dr.floor(uv.x * resolution)), 0, resolution - 1))
    row = mi.UInt32(dr.clip(mi.Int32(dr.floor(uv.y * resolution)), 0, resolution - 1))
    source = dr.gather(mi.UInt32, lookup, row * resolution + col, hit)
    # Light leaves the source's diffuse layer only above its own horizon (its texel's shading normal).
    hit &= dr.dot(dr.gather(mi.Vector3f, geom.normal, source, hit), d) < 0
    keep = dr.compress(hit)
    out = (dr.gather(mi.UInt32, t, keep), dr.gather(mi.UInt32, source, keep), dr.gather(mi.Vector3f, d, keep))
    dr.eval(*out)
    return np.array(out[0]), np.array(out[1]), _rows(out[2]), on_set


def _rows(v) -> np.ndarray:
    return np.array(v, np.float32).T.reshape(-1, 3)


def _no_raw_hits() -> dict[str, np.ndarray]:
    kinds = {"receivers": np.uint32, "glossy": bool}
    return {f: np.zeros(0 if f in ("receivers", "distance", "glossy") else (0, 3), kinds.get(f, np.float32)) for f in RAW_HITS}


def _set_hits(scene: mi.Scene, texel: mi.UInt32, origin: mi.Point3f, d: mi.Vector3f, on_set: mi.Bool) -> dict[str, np.ndarray]:
    """The rays ``on_set`` (first hits on the set), traced again for their full surface interaction (only these: a body
    without a set traces nothing more), and kept where the set's BSDF reflects light back toward the ray's texel:
    :data:`RAW_HITS`."""
    lanes = dr.compress(on_set)
    if dr.width(lanes) == 0:
        return _no_raw_hits()
    o, direction = dr.gather(mi.Point3f, origin, lanes), dr.gather(mi.Vector3f, d, lanes)
    si = scene.ray_intersect(mi.Ray3f(o, direction), ray_flags=mi.RayFlags.All, coherent=False)
    bsdf = si.bsdf()
    front = mi.Frame3f.cos_theta(si.wi) > 0
    # A one-sided BSDF (Mitsuba's diffuse) is black from behind; a two-sided one reflects on both sides.
    reflects = si.is_valid() & (front | mi.has_flag(bsdf.flags(), mi.BSDFFlags.BackSide))
    side = dr.select(front, 1.0, -1.0)
    reflectance = albedo(bsdf, si, reflects, SET_ALBEDO_SAMPLES)
    glossy = has_glossy_lobe(bsdf)
    # (a NaN texel's albedo is NaN: such a hit says nothing, and is dropped)
    keep = dr.compress(reflects & dr.all(dr.isfinite(reflectance)) & ((dr.max(reflectance) > 0) | glossy))
    fields = (
        dr.gather(mi.UInt32, texel, dr.gather(mi.UInt32, lanes, keep)), dr.gather(mi.Float, si.t, keep), dr.gather(mi.Vector3f, direction, keep),
        dr.gather(mi.Point3f, si.p, keep), dr.gather(mi.Vector3f, mi.Vector3f(si.sh_frame.n * side), keep),
        dr.gather(mi.Vector3f, mi.Vector3f(si.n * side), keep), dr.gather(mi.Color3f, reflectance, keep), dr.gather(mi.Bool, glossy, keep),
    )  # fmt: skip
    dr.eval(*fields)
    values = (
        np.array(fields[0], np.uint32),
        np.array(fields[1], np.float32),
        *(_rows(f) for f in fields[2:-1]),
        np.array(fields[-1], bool),
    )
    return dict(zip(RAW_HITS, values, strict=True))


def albedo(bsdf: mi.BSDF, si: mi.SurfaceInteraction3f, active: mi.Bool, samples: int, diffuse_only: bool = True) -> mi.Color3f:
    """The light ``bsdf`` reflects toward ``si.wi`` per unit of light arriving evenly from every direction: its
    directional albedo, the integral of f cosθ over the directions it reflects from (transmitted and passed-through
    light left out), at ``samples`` points of a shifted lattice per lane. ``diffuse_only``: its diffuse lobes' (Mitsuba's
    ``eval`` with only those enabled, over cosine-distributed directions: a diffuse BSDF's reflectance exactly, at any
    count; a plastic's diffuse lobe under its coat); otherwise every lobe's (``bsdf.sample``'s weights: a metal's too).
    (Mitsuba's ``eval_diffuse_reflectance`` falls back to π f(ω, n) for BSDFs without a diffuse lobe: a polished metal's
    peak, 100 at α 0.05 facing its normal, or nothing seen obliquely.)"""
    lanes = dr.width(si.p)
    rng = mi.PCG32(lanes, mi.UInt64(0), dr.arange(mi.UInt64, lanes))
    shift, lobe_shift = mi.Point2f(rng.next_float32(), rng.next_float32()), rng.next_float32()
    context, total = mi.BSDFContext(), mi.Color3f(0.0)
    side = dr.sign(mi.Frame3f.cos_theta(si.wi))
    if diffuse_only:
        context.type_mask = mi.BSDFFlags.DiffuseReflection
    for k in range(samples):
        point = lattice_point(mi.Float(k), samples, shift)
        if diffuse_only:  # cosine-distributed on the side it is seen from: eval (f cosθ) / pdf (cosθ / π)
            wo = mi.warp.square_to_cosine_hemisphere(point)
            wo = mi.Vector3f(wo.x, wo.y, wo.z * side)
            weight = bsdf.eval(context, si, wo, active) * (dr.pi / dr.abs(wo.z))
        else:
            lobe = fraction(lobe_shift + k * PLASTIC_STEP)  # (the lobe choice and the direction: two independent lattices)
            bs, weight = bsdf.sample(context, si, lobe, point, active)
            wo = bs.wo
        total += dr.select(active & (mi.Frame3f.cos_theta(wo) * side > 0), weight, 0.0)  # (a NaN texel's stays NaN: dropped)
    return total / samples


def has_glossy_lobe(bsdf: mi.BSDF) -> mi.Bool:
    """Whether a set hit's BSDF has a glossy lobe, whose light the set sends toward each light (:class:`SetGlossyLobe`).
    A delta lobe (a mirror, smooth glass) is left out: a point light's reflection in it is met by no ray."""
    return mi.has_flag(bsdf.flags(), mi.BSDFFlags.GlossyReflection)


class SetGlossyLobe:
    """The glossy lobes of the set's BSDF at its hits, as a material of the LED loop (``front``, ``eval_parts``):
    Mitsuba's own ``eval`` (f cosθ) with only the glossy lobes enabled, at each hit's surface, in its cell's frame."""

    def __init__(self, si: mi.SurfaceInteraction3f):
        self.si, self.bsdf = si, si.bsdf()
        self.context = mi.BSDFContext()
        self.context.type_mask = mi.BSDFFlags.GlossyReflection
        self.front = si.is_valid() & (mi.Frame3f.cos_theta(si.wi) > 0)

    def eval_parts(self, wo: mi.Vector3f) -> tuple[mi.Color3f, mi.Color3f]:
        value = self.bsdf.eval(self.context, self.si, wo, self.front)
        return mi.Color3f(0.0), dr.select(dr.isfinite(value), value, 0.0)  # (a NaN texel of a roughness map: no light)


def glossy_surfaces(
    scene: mi.Scene, hits: SetHits, frame_geom: TexelGeometry, cells: TexelGeometry
) -> tuple[np.ndarray, mi.SurfaceInteraction3f]:
    """(the glossy hits, their surfaces): each such ray traced again from its texel (the same origin as the operator's
    trace, the same direction, so the same hit), its surface put in its cell's frame (the frame the LED loop's
    directions are in), seen from the receiver."""
    index = np.flatnonzero(hits.glossy)
    r, d = mi.UInt32(hits.receivers[index]), mi.Vector3f(*np.ascontiguousarray(hits.direction[index].T))
    origin = dr.gather(mi.Point3f, frame_geom.position, r) + dr.gather(mi.Vector3f, frame_geom.geo_normal, r) * RAY_EPSILON
    si = scene.ray_intersect(mi.Ray3f(origin, d), ray_flags=mi.RayFlags.All, coherent=False)
    si.sh_frame = mi.Frame3f(dr.gather(mi.Vector3f, cells.normal, mi.UInt32(hits.cell[index])))
    si.wi = si.sh_frame.to_local(-d)
    return index, si


def set_corners(scene: mi.Scene, subject: mi.Shape) -> np.ndarray:
    """(8 S, 3) the corners of the bounding boxes of the scene's shapes besides ``subject``: with the body's vertices,
    points whose hull holds everything a ray can hit."""
    boxes = [s.bbox() for s in scene.shapes() if s.id() != subject.id()]
    return np.array([[(b.min if (k >> a) & 1 == 0 else b.max)[a] for a in range(3)] for b in boxes for k in range(8)], np.float64).reshape(
        -1, 3
    )


def set_materials_digest(scene: mi.Scene, subject: mi.Shape) -> str:
    """A hash of the set's shapes with everything Mitsuba exposes of them (BSDF parameters, textures, vertex
    attributes): what the light the set reflects depends on, beyond the geometry the frame's digest holds."""
    from gra_mi.stage.scene import shape_order

    digest = hashlib.sha1(SET_ALBEDO_VERSION.encode())
    for shape in sorted((s for s in scene.shapes() if s.id() != subject.id()), key=shape_order):
        digest.update(f"{shape.class_name()}:{shape.bsdf().class_name()}".encode())
        params = mi.traverse(shape)
        for key in sorted(params.keys()):
            digest.update(key.encode())
            value = params[key]
            value = value.matrix if hasattr(value, "matrix") else value
            try:
                digest.update(np.ascontiguousarray(np.array(value), np.float32).tobytes())
            except (TypeError, ValueError):  # not numeric: its text
                digest.update(repr(value).encode())
    return digest.hexdigest()[:16]


def light_along_rays(
    op: BounceOperator, geom: TexelGeometry, albedo: mi.Color3f, first: tuple, bounces: int, from_set: mi.Color3f | None = None
) -> mi.Color3f:
    """L_k: the radiance arriving along each ray after up to ``bounces`` bounces in all, for the rays that hit the body
    and then those that hit the set (:meth:`BounceOperator.rays_to_gather`). ``first`` = (diffuse per unit albedo,
    specular) that each body ray's source texel sends toward the receiver under the one-bounce lighting; the later
    bounces' light leaves the sources through their diffuse layer only. ``from_set``: what the set sends back along
    its rays (None: nothing)."""
    from_set = dr.zeros(mi.Color3f, op.set_hits.count) if from_set is None else from_set
    if op.entries == 0:
        return from_set
    _, s, d = op.device()
    source_albedo = dr.gather(mi.Color3f, albedo, s)
    light = source_albedo * first[0] + first[1]
    # Held, not left lazy: the scatters and gathers that read it (gather_diffuse, the smoothing, a later bounce) would
    # each compute it inside their own kernels.
    light = _with_set(light, from_set)
    dr.eval(light)
    if bounces > 2:
        # T(cosθy) toward the receiver, times the source's albedo: how a source's own indirect light leaves toward x.
        toward = source_albedo * brdf.diffuse_transmission(-dr.dot(d, dr.gather(mi.Vector3f, geom.normal, s)))
        term = light
        for _ in range(bounces - 2):
            term = _with_set(toward * dr.gather(mi.Color3f, op.gather_diffuse(geom, term), s), dr.zeros(mi.Color3f, op.set_hits.count))
            light += term
            dr.eval(term, light)
    return light


def _with_set(body: mi.Color3f, on_set: mi.Color3f) -> mi.Color3f:
    return body if dr.width(on_set) == 0 else concat(mi.Color3f, [body, on_set])


def operator_key(geom: TexelGeometry, rays: int, seed: int, set_materials: str = "") -> str:
    """The cache key of a frame's operator: its geometry (the set's included), the rays, and what else its set hits
    hold (:func:`set_materials_digest` and the LEDs that size its cells; "" with no set, the key of operators traced
    before the set reflected light)."""
    extra = f"_{set_materials}" if set_materials else ""
    return hashlib.sha1(f"{geom.digest}_{rays}_{seed}{extra}".encode()).hexdigest()[:16]
