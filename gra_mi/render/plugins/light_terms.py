"""The terms ``gra_onebounce`` sums at a shading point, and the lights they read.

A term is one light, one point on a light or one direction from the material: ``*_term(at, …, k, active)`` gives
(ωo in the local frame, the incident weight — irradiance-like for a delta light, radiance / pdf for a sample —, the
mask of lanes it reaches, and this strategy's density where another strategy samples the same directions, else
None). :class:`ShadingPoint` holds what every term reads: the surface, its material, which side light may come from
(:meth:`ShadingPoint.faces`), and whether shadow rays cross see-through surfaces (``null``, ``mask``:
:func:`cross_see_through`), multiplying their transmission instead of stopping at them.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.render.lattice import fraction, lattice_point
from gra_mi.render.leds import LedLayout

SEE_THROUGH_LAYERS = 16  # see-through surfaces a ray crosses at most; the next one counts as opaque


class LedArrays:
    """The LEDs that are on, as Dr.Jit arrays (``count`` is a Python int: the loop length)."""

    def __init__(self, leds: LedLayout, intensities: np.ndarray):
        on = np.flatnonzero(np.max(intensities, axis=1) > 0)
        self.count = int(on.size)
        self.index = mi.UInt32(on.astype(np.uint32))
        pos, inten = leds.as_lights(intensities)  # far field: directions from the stage centre, irradiance there
        pos, inten = pos[on], inten[on]
        self.position = mi.Point3f(*(pos.T.astype(np.float32))) if self.count else mi.Point3f()
        self.intensity = mi.Color3f(*(inten.T.astype(np.float32))) if self.count else mi.Color3f()


class DeltaEmitters:
    """The scene's other delta lights (spot, projector, directional) as one array of emitter pointers."""

    def __init__(self, emitters: list):
        self.count = len(emitters)
        self.pointers = mi.EmitterPtr(emitters) if emitters else None


class AreaLights:
    """The scene's area lights that are on, and how many of the ``samples`` points per pixel sample each gets: a share
    in proportion to its weight (:func:`~gra_mi.render.scene_lights.area_weights`), at least one (:func:`points_per_light`),
    so every light is in every estimate. ``bsdf_samples`` directions from the BSDF may hit one."""

    def __init__(self, emitters: list, weights: np.ndarray, samples: int, bsdf_samples: int):
        self.count, self.bsdf_samples = len(emitters), bsdf_samples
        self.samples = 0  # points per pixel sample over all lights: the loop's length
        if not emitters:
            return
        self.pointers = mi.EmitterPtr(emitters)
        points = points_per_light(weights, samples)
        self.samples = int(points.sum())
        # Point t of the loop: which light, which of that light's points, out of how many.
        light = np.repeat(np.arange(self.count), points)
        self.light_of = mi.UInt32(light.astype(np.uint32))
        self.index_on = mi.Float((np.arange(self.samples) - np.repeat(np.cumsum(points) - points, points)).astype(np.float32))
        self.points_on = mi.Float(points[light].astype(np.float32))
        # A light a BSDF direction hits is known by its pointer (a registry id): its count of points, looked up by that id.
        ids = np.array(dr.reinterpret_array(mi.UInt32, self.pointers), dtype=np.int64)
        table = np.zeros(ids.max() + 1, dtype=np.float32)
        table[ids] = points
        self.points_by_id = mi.Float(table)

    def points_of(self, emitter, active):
        """How many points each pixel sample draws on ``emitter`` (0 for none, or for a light that is off)."""
        ids = dr.reinterpret_array(mi.UInt32, emitter)
        known = active & (ids < dr.width(self.points_by_id))
        return dr.gather(mi.Float, self.points_by_id, ids, known)


def points_per_light(weights: np.ndarray, samples: int) -> np.ndarray:
    """``samples`` points shared among lights in proportion to ``weights`` (rounded), at least one each: a light too
    dim for a point of its own still gets one, so no pixel sample leaves a light out (choosing lights at random
    instead is several times noisier on a stage of small lights)."""
    share = weights / weights.sum() if weights.sum() > 0 else np.full(len(weights), 1.0 / len(weights))
    return np.maximum(1, np.rint(samples * share)).astype(np.int64)


def power_heuristic(ours, other):
    """Veach's power heuristic for a strategy of density ``ours`` beside one of density ``other`` (counts folded in)."""
    return dr.select(ours > 0, dr.square(ours) / (dr.square(ours) + dr.square(other)), 0.0)


@dataclass
class ShadingPoint:
    """Where a camera ray stopped, as every term reads it."""

    scene: mi.Scene
    si: mi.SurfaceInteraction3f
    bsdf: mi.BSDFPtr
    transmits: mi.Bool  # the material has a transmission lobe: lit from behind too
    see_through: bool  # the scene has see-through materials: shadow rays cross them
    throughput: mi.Spectrum | None = None  # the weight of choosing this surface behind see-through ones (None: 1)

    def faces(self, wo, direction):
        """Whether light arriving along ``direction`` (``wo`` in the local frame) can reach the viewer: from the
        viewer's side of the surface (the back of a ``twosided`` plane seen from behind included), or from the other
        side where the material transmits; the shading and the geometric normal must agree on the side (no light leaks
        between them). Elsewhere the material is black: no ray is traced."""
        si = self.si
        shading = wo.z * si.wi.z > 0
        geometric = dr.dot(si.n, direction) * dr.dot(si.n, si.to_world(si.wi)) > 0
        return (wo.z != 0) & (shading == geometric) & (shading | self.transmits)

    def reach(self, ray, active) -> tuple:
        """(the lanes whose light travels ``ray`` to its end, the transmission of the see-through surfaces it crossed
        or None where the scene has none)."""
        if not self.see_through:
            return active & ~self.scene.ray_test(ray, active), None
        ray, passed = cross_see_through(self.scene, ray, active)
        return active & ~self.scene.ray_test(ray, active) & (dr.max(passed) > 0), passed

    def trace(self, ray, active) -> tuple:
        """(the first opaque surface along ``ray``, or a miss; the transmission of the see-through surfaces before it,
        or None where the scene has none)."""
        if not self.see_through:
            return self.scene.ray_intersect(ray, active), None
        ray, passed = cross_see_through(self.scene, ray, active)
        return self.scene.ray_intersect(ray, active), passed


def scaled(value, factor):
    """value × factor, or value where there is no factor (None: no see-through surface in the way)."""
    return value if factor is None else value * factor


@dr.syntax
def cross_see_through(scene, ray, active) -> tuple:
    """(``ray`` from beyond the see-through surfaces it crosses, its end unchanged; the product of their transmission,
    ``eval_null_transmission``): a ``null`` surface lets all light through, a ``mask`` 1 − opacity. It stops at the
    first opaque surface, or after :data:`SEE_THROUGH_LAYERS`."""
    passed = mi.Spectrum(1.0)
    going = mi.Bool(active)
    crossed = mi.UInt32(0)
    while dr.hint(going, label="gra_onebounce see-through surfaces"):
        si = scene.ray_intersect(ray, mi.RayFlags.All, False, going)
        through = si.bsdf(ray).eval_null_transmission(si, going & si.is_valid())
        going &= si.is_valid() & (dr.max(through) > 0) & (crossed < SEE_THROUGH_LAYERS)
        passed = dr.select(going, passed * through, passed)
        onward = si.spawn_ray(ray.d)
        onward.maxt = ray.maxt - si.t
        ray = dr.select(going, onward, ray)
        crossed += 1
    return ray, passed


def area_term(at: ShadingPoint, areas: AreaLights, shift, t, active):
    """Point t of the loop: point j of the n a light gets, lattice point j of n
    (:func:`~gra_mi.render.lattice.lattice_point`) on it drawn by the emitter's own ``sample_direction``. With BSDF
    samples the sum weighs it against theirs (:func:`bsdf_term`)."""
    si = at.si
    light = dr.gather(mi.UInt32, areas.light_of, t, active)
    count = dr.gather(mi.Float, areas.points_on, t, active)
    emitter = dr.gather(mi.EmitterPtr, areas.pointers, light, active)
    ds, weight = emitter.sample_direction(si, lattice_point(dr.gather(mi.Float, areas.index_on, t, active), count, shift), active)
    wo = si.to_local(ds.d)
    facing = active & (ds.pdf > 0) & at.faces(wo, ds.d) & (dr.max(weight) > 0)
    visible, passed = at.reach(si.spawn_ray_to(ds.p), facing)
    return wo, scaled(weight / count, passed), visible, count * ds.pdf if areas.bsdf_samples else None


def bsdf_term(at: ShadingPoint, areas: AreaLights, shift, shift_1d, k, active):
    """BSDF sample k (a lattice point, as the lights'), and the radiance / pdf of the area light it reaches, weighted
    against the lights' own samples of that direction: where a light's surface sampling is poor (a large light close
    by, a glossy highlight) the BSDF's is good. Smooth lobes only (the delta lobes have a ray each); on the side
    :meth:`ShadingPoint.faces` allows, as the lights' samples."""
    si, count = at.si, areas.bsdf_samples
    j = mi.Float(k)
    sample, _ = at.bsdf.sample(mi.BSDFContext(), si, fraction(j / count + shift_1d), lattice_point(j, count, shift), active)
    direction = si.to_world(sample.wo)
    smooth = ~mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta)
    facing = active & smooth & (sample.pdf > 0) & at.faces(sample.wo, direction)
    hit, passed = at.trace(si.spawn_ray(direction), facing)
    facing &= hit.is_valid()  # an environment is the dome's
    emitter = hit.emitter(at.scene, facing)  # null where the surface emits nothing: no radiance, no pdf
    radiance = emitter.eval(hit, facing)
    light_pdf = areas.points_of(emitter, facing) * emitter.pdf_direction(si, mi.DirectionSample3f(at.scene, hit, si), facing)
    weight = radiance * power_heuristic(count * sample.pdf, light_pdf) / (count * sample.pdf)
    return sample.wo, scaled(weight, passed), facing & (dr.max(radiance) > 0), None


def delta_term(at: ShadingPoint, emitters: DeltaEmitters, k, active):
    """Delta emitter k (spot, projector, directional): its own ``sample_direction``, exact."""
    si = at.si
    emitter = dr.gather(mi.EmitterPtr, emitters.pointers, k, active)
    ds, weight = emitter.sample_direction(si, dr.full(mi.Point2f, 0.5, dr.width(si.p)), active)
    wo = si.to_local(ds.d)
    facing = active & at.faces(wo, ds.d) & (dr.max(weight) > 0)
    visible, passed = at.reach(si.spawn_ray_to(ds.p), facing)
    return wo, scaled(weight, passed), visible, None


def led_term(at: ShadingPoint, leds: LedArrays, k, far_field: bool, active):
    """LED k (a point light, or a dome's far-field light): I/d², exact."""
    si = at.si
    p = dr.gather(mi.Point3f, leds.position, k, active)
    intensity = dr.gather(mi.Color3f, leds.intensity, k, active)
    if far_field:
        wo_world, dist2 = mi.Vector3f(p), mi.Float(1.0)
    else:
        offset = p - si.p
        dist2 = dr.squared_norm(offset)
        wo_world = offset * dr.rsqrt(dist2)
    wo = si.to_local(wo_world)
    facing = active & at.faces(wo, wo_world)
    visible, passed = at.reach(si.spawn_ray(wo_world) if far_field else si.spawn_ray_to(p), facing)
    return wo, scaled(intensity / dist2, passed), visible, None
