"""Per-LED visibility of every texel (paper Supp. "Details about Microfacet Rendering"): one bit per (texel, LED),
"the LED is above the texel's horizon and nothing blocks the segment". It depends only on geometry and the LED layout,
so :class:`VisibilityCache` reuses it across envmaps, cameras, materials and fitting iterations, in memory and on disk.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.io import atomic_path
from gra_mi.core.runtime import opaque, segment
from gra_mi.render.atlas import TexelGeometry
from gra_mi.render.leds import LedLayout

# Shadow rays start this far (metres) off the surface along the geometric normal, and stop this far short of the
# LED: enough to clear float32 self-intersection on a 2 m stage, far below a texel's size (~3 mm at 512²).
RAY_EPSILON = 1e-4


def compute_visibility(
    scene: mi.Scene, geom: TexelGeometry, leds: LedLayout, texels: np.ndarray | None = None, lit: np.ndarray | None = None
) -> mi.UInt32:
    """Bit-packed visibility, word-major: bit (k % 32) of word ``(k // 32) * M + t`` is LED k at texel t.

    Rays are traced LED-major (all texels for one LED, then the next) in groups of up to 32 LEDs per kernel, which
    keeps them coherent; pairs below the texel's horizon (shading or geometric) trace nothing. Far field, each ray goes
    towards the LED's direction from the stage centre, until it leaves the LED's sphere about the centre. ``texels``: trace only these (sorted indices);
    the others' bits stay 0 (:func:`texels_seen_by`: a job's cameras cannot see them). ``lit``: trace only these LEDs
    (an OLAT's one; None: every LED); the others' bits stay 0, which shades the same while they are off.
    """
    m = dr.width(geom.position)
    num_leds, far_field = leds.num_leds, leds.far_field
    words = (num_leds + 31) // 32
    bits = dr.zeros(mi.UInt32, words * m)
    targets, _ = leds.as_lights(np.zeros((num_leds, 3)))
    target_arr = mi.Point3f(*targets.T.astype(np.float32))
    # Far field, a ray ends where it leaves the sphere through its LED about the centre: what lies inside it (the body,
    # a floor) shadows, a set beyond the LEDs (a room) does not.
    reach_arr = mi.Float(np.linalg.norm(leds.positions - leds.center, axis=1).astype(np.float32))
    centre = opaque(mi.Point3f, leds.center)
    subset = None if texels is None else mi.UInt32(np.asarray(texels, np.uint32))
    count = m if texels is None else len(texels)
    lit = np.arange(num_leds) if lit is None else np.asarray(lit, np.int64)
    if count == 0:
        return bits
    lanes = dr.opaque(mi.UInt32, count)  # a kernel input: a culled frame's count would otherwise compile new kernels
    for w in range(words):
        group = lit[(lit >= 32 * w) & (lit < 32 * w + 32)]  # this word's LEDs to trace
        if group.size == 0:
            continue
        i = dr.arange(mi.UInt32, group.size * count)
        g = i // lanes  # which of the group's LEDs (count > 0: no division by zero in the masked tail)
        t = i - g * lanes if subset is None else dr.gather(mi.UInt32, subset, i - g * lanes)
        k = dr.gather(mi.UInt32, mi.UInt32(group.astype(np.uint32)), g)
        j = k - 32 * w  # its bit in the word
        target = dr.gather(mi.Point3f, target_arr, k)
        p = dr.gather(mi.Point3f, geom.position, t)
        n = dr.gather(mi.Vector3f, geom.normal, t)
        ng = dr.gather(mi.Vector3f, geom.geo_normal, t)
        if far_field:
            d = mi.Vector3f(target)
            dist = _sphere_exit(p - centre, d, dr.gather(mi.Float, reach_arr, k))
        else:
            offset = target - p
            dist = dr.norm(offset)
            d = offset / dist
        facing = (dr.dot(n, d) > 0) & (dr.dot(ng, d) > 0)
        origin = p + ng * RAY_EPSILON
        maxt = dist if far_field else dist * (1.0 - RAY_EPSILON) - RAY_EPSILON
        ray = segment(origin, d, maxt)
        blocked = scene.ray_test(ray, coherent=True, active=facing)
        word = dr.select(facing & ~blocked, mi.UInt32(1) << j, mi.UInt32(0))
        dr.scatter_reduce(dr.ReduceOp.Add, bits, word, t + w * m)
        dr.eval(bits)
    return bits


def _sphere_exit(offset, d, radius):
    """How far a ray from ``offset`` (from the sphere's centre) along unit ``d`` runs before it leaves the sphere of
    ``radius``; from outside the sphere, unbounded (a rig smaller than the subject: nothing to stop at)."""
    b = dr.dot(d, offset)
    c = dr.squared_norm(offset) - radius * radius
    return dr.select(c < 0, -b + dr.safe_sqrt(b * b - c), dr.inf)


def texels_seen_by(geom: TexelGeometry, cameras, margin: float = 8.0) -> np.ndarray:
    """The texels some camera of ``cameras`` can see: in front of the camera, inside its image (with ``margin`` pixels
    for the rasteriser's bilinear lookups) and facing it. Every other texel reflects nothing toward those cameras
    (the BRDF is zero below the horizon) or falls outside their images, so their visibility need not be traced: the
    renders are the same, pixel for pixel."""
    p = np.array(geom.position, np.float64).T
    n = np.array(geom.normal, np.float64).T
    seen = np.zeros(len(p), bool)
    for cam in cameras:
        local = (p - cam.position) @ cam.rotation  # camera axes (OpenCV: z forward)
        z = np.maximum(local[:, 2], 1e-9)
        u, v = cam.fx * local[:, 0] / z + cam.cx, cam.fy * local[:, 1] / z + cam.cy
        inside = (local[:, 2] > 0) & (u > -margin) & (u < cam.width + margin) & (v > -margin) & (v < cam.height + margin)
        seen |= inside & (np.sum(n * (cam.position - p), axis=1) > 0)
    return np.flatnonzero(seen)


class VisibilityCache:
    """Visibility bits per (frame geometry, :class:`LedLayout`): in memory, and on disk under ``folder`` if given.
    An entry traced for a subset of texels (the cameras of a job) serves any later request for a subset of it; one
    traced for the LEDs that were lit (an OLAT's one) is extended by the LEDs a later lighting adds, only those traced.
    ``keep``: hold at most this many entries in memory, the least recently used dropped (read again from disk when
    asked for): a fit streaming thousands of frames holds a few, not all. Only entries of every LED go to disk."""

    def __init__(self, folder: str | Path | None = None, keep: int | None = None):
        self.folder = None if folder is None else Path(folder)
        self.keep = keep
        # key → (bits, the texels traced (None: all), the LEDs traced (None: all))
        self._memory: dict[str, tuple[mi.UInt32, np.ndarray | None, np.ndarray | None]] = {}
        self.hits = 0
        self.misses = 0

    def get(
        self, scene, geom: TexelGeometry, leds: LedLayout, texels: np.ndarray | None = None, lit: np.ndarray | None = None
    ) -> mi.UInt32:
        """The bits for ``texels`` (None: all) and the LEDs ``lit`` (None: all): a cached entry covering them, else
        traced (and kept). ``scene``: the ``mi.Scene`` at ``geom``'s frame, or a function that returns it, called only
        if bits must be traced."""
        base = f"{geom.digest}_{leds.digest}"
        lit = None if lit is None or len(lit) == leds.num_leds else np.unique(np.asarray(lit, np.int64))
        for key, (bits, covered, traced) in self._memory.items():
            if key.startswith(base) and _covers(covered, texels) and _covers(traced, lit):
                self.hits += 1
                self._memory[key] = self._memory.pop(key)  # most recently used last
                return bits
        key = base if texels is None else f"{base}_{hashlib.sha1(np.asarray(texels, np.int64).tobytes()).hexdigest()[:12]}"
        cached = self._read(base) if texels is not None else None  # a full trace on disk serves any subset
        if cached is not None:
            key, texels = base, None
        else:
            cached = self._read(key)
        if cached is not None:
            bits, traced = mi.UInt32(cached), None
            self.hits += 1
        else:
            bits, traced = self._trace(scene, geom, leds, key, texels, lit)
        self._memory.pop(key, None)
        self._memory[key] = (bits, None if texels is None else np.asarray(texels), traced)
        while self.keep is not None and len(self._memory) > max(self.keep, 1):
            del self._memory[next(iter(self._memory))]
        return bits

    def _trace(self, scene, geom, leds, key: str, texels, lit) -> tuple[mi.UInt32, np.ndarray | None]:
        """Trace what the entry ``key`` lacks of ``lit``'s LEDs (all of them, if there is no entry), merged into it."""
        bits, traced = self._memory.get(key, (None, None, np.zeros(0, np.int64)))[::2]
        wanted = np.arange(leds.num_leds) if lit is None else lit
        missing = np.setdiff1d(wanted, traced)
        new = compute_visibility(scene if isinstance(scene, mi.Scene) else scene(), geom, leds, texels, missing)
        self.misses += 1
        bits = new if bits is None else bits | new
        dr.eval(bits)
        traced = np.union1d(traced, missing)
        if len(traced) < leds.num_leds:
            return bits, traced
        if self.folder is not None:  # every LED: kept on disk too
            with atomic_path(self.folder / f"vis_{key}.npy") as tmp:
                with open(tmp, "wb") as fh:
                    np.save(fh, np.array(bits, dtype=np.uint32))
        return bits, None

    def _read(self, key: str) -> np.ndarray | None:
        path = None if self.folder is None else self.folder / f"vis_{key}.npy"
        if path is None or not path.is_file():
            return None
        try:
            return np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError):  # a cache file cut short: trace again and rewrite it
            return None


def _covers(covered: np.ndarray | None, wanted: np.ndarray | None) -> bool:
    """Whether an entry's texels (or LEDs) ``covered`` (None: all) include ``wanted`` (None: all)."""
    return covered is None or (wanted is not None and bool(np.isin(wanted, covered).all()))
