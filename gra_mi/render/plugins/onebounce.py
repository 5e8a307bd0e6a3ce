"""``gra_onebounce``: deterministic one-bounce lighting from every point-light LED (paper Eq. 1, Supp. "Details
about Microfacet Rendering").

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Description
   * - ``far_field``
     - bool
     - Treat LEDs as directional lights seen from ``stage_center`` (for comparison). Default: false (near field).
   * - ``stage_center``
     - point
     - Where the far-field directions and irradiances are measured. Default: (0, 1, 0).
   * - ``hide_emitters``
     - boolean
     - Camera rays that escape see nothing instead of the environment (as in Mitsuba's integrators). Default: false.
   * - ``dome_lights``
     - integer
     - How many far-field lights carry the scene's environment emitters (``envmap``, ``constant``, ``sunsky``),
       each the light of its cell of the sphere (:mod:`gra_mi.render.dome`). Default: 1024.
   * - ``area_samples``
     - integer
     - Points sampled on the ``area`` lights per pixel sample (one shadow ray each), shared among them in proportion
       to their power × their ``sampling_weight``, at least one each. Default: 16.
   * - ``bsdf_samples``
     - integer
     - Directions drawn from the BSDF per pixel sample that may reach an ``area`` light (one ray each), weighted
       against the lights' points by the power heuristic; 0: the points alone. Default: 4.

At each camera hit the integrator sums over the scene's delta lights:

    L = Σ_k  f(ωi, ωk) cosθk · E_k · V_k

with one shadow ray per light and E_k the light's incident irradiance-like weight (``point``: I/d², the LEDs, in
near field by default; ``spot`` and ``projector``: I·falloff/d²; ``directional``: its irradiance), as the emitter's
own ``sample_direction`` gives it; environments (``envmap``, ``constant``, ``sunsky``) arrive through a dome of
far-field lights, each with the irradiance of its cell, one shadow ray each, like a lightstage's LEDs; ``area`` lights
are sampled on their surface by their own ``sample_direction``, ``area_samples`` points per pixel sample in all,
shared among the lights in proportion to power × ``sampling_weight`` and at least one each (every light is in every
estimate), spread over each light as a rank-1 lattice shifted at random per pixel sample (unbiased, with less
noise than independent points: :mod:`gra_mi.render.lattice`), and
reached by ``bsdf_samples`` directions from the BSDF (a lattice too), the two weighted by the power heuristic as
Mitsuba's ``direct`` weighs its emitter and BSDF samples: the points carry a small light, the directions a glossy
highlight or a large light close by. Each delta lobe of a material (a mirror, a glass's reflection and transmission, a
plastic's coat) sees the environment and area lights along its one direction, one ray per lobe; the camera sees the lights' surface as Mitsuba shows it. Point emitters (a lightstage has hundreds) are read
from the scene once per render into arrays and evaluated in one symbolic Dr.Jit loop, not one virtual call per
emitter; the other delta lights follow in a second loop that calls each emitter. Point lights and area lights that
are off are dropped before the loop; lights on the far side of a surface from the viewer (by the shading or the
geometric normal) trace nothing unless the material transmits (:func:`lit_side`; the back of a ``twosided`` plane is
lit from its own side); points whose material has no smooth lobe skip the loops; dark cells of the dome are dropped.
``directionalarea`` emitters, media and see-through (``null``, ``mask``) materials are refused by name when a render
starts (:mod:`gra_mi.render.scene_lights`), as is a scene without light. Derivatives with respect to BSDF parameters
(``gra_microfacet`` textures) follow Path Replay Backpropagation: the loops are replayed in the adjoint pass with
gradients enabled around the BSDF evaluation only (the directions' pdf held fixed).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.python.ad.integrators.common import RBIntegrator

from gra_mi.render.lattice import fraction, lattice_point
from gra_mi.render.leds import LedLayout
from gra_mi.render.scene_lights import OPTIONS, checked_option, scene_lights, scene_objects

# A light's term may not depend on what is differentiated (a mirror's smooth lobes are zero): no gradient, no error.
MAY_NOT_DEPEND = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad


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


def lit_side(si, wo, direction, transmits):
    """Whether light arriving along ``direction`` (``wo`` in the local frame) can reach the viewer at ``si``: from the
    viewer's side of the surface (the back of a ``twosided`` plane seen from behind included), or from the other side
    where the material transmits; the shading and the geometric normal must agree on the side (no light leaks between
    them). Elsewhere the material is black: no ray is traced."""
    shading = wo.z * si.wi.z > 0
    geometric = dr.dot(si.n, direction) * dr.dot(si.n, si.to_world(si.wi)) > 0
    return (wo.z != 0) & (shading == geometric) & (shading | transmits)


def power_heuristic(ours, other):
    """Veach's power heuristic for a strategy of density ``ours`` beside one of density ``other`` (counts folded in)."""
    return dr.select(ours > 0, dr.square(ours) / (dr.square(ours) + dr.square(other)), 0.0)


def area_contribution(scene, si, transmits, areas: AreaLights, shift, t, active):
    """(ωo in the local frame, incident radiance / pdf over the samples, mask, this strategy's density there) for
    point t of the loop: point j of the n a light gets, lattice point j of n (:func:`~gra_mi.render.lattice.lattice_point`)
    on it drawn by the emitter's own ``sample_direction``. With BSDF samples the sum weighs it against theirs
    (:func:`bsdf_contribution`)."""
    light = dr.gather(mi.UInt32, areas.light_of, t, active)
    count = dr.gather(mi.Float, areas.points_on, t, active)
    emitter = dr.gather(mi.EmitterPtr, areas.pointers, light, active)
    ds, weight = emitter.sample_direction(si, lattice_point(dr.gather(mi.Float, areas.index_on, t, active), count, shift), active)
    wo = si.to_local(ds.d)
    facing = active & (ds.pdf > 0) & lit_side(si, wo, ds.d, transmits) & (dr.max(weight) > 0)
    visible = facing & ~scene.ray_test(si.spawn_ray_to(ds.p), facing)
    return wo, weight / count, visible, count * ds.pdf if areas.bsdf_samples else None


def bsdf_contribution(scene, si, transmits, bsdf, areas: AreaLights, shift, shift_1d, k, active):
    """(ωo, the radiance of the area light it reaches / pdf over the samples, mask, None) for BSDF sample k (a lattice point,
    as the lights'), weighted against the lights' own samples of that direction: where a light's surface sampling is
    poor (a large light close by, a glossy highlight) the BSDF's is good. Smooth lobes only (the delta lobes have a ray
    each: :func:`_add_delta_lobe`); on the side :func:`lit_side` allows, as the lights' samples."""
    count = areas.bsdf_samples
    j = mi.Float(k)
    sample, _ = bsdf.sample(mi.BSDFContext(), si, fraction(j / count + shift_1d), lattice_point(j, count, shift), active)
    direction = si.to_world(sample.wo)
    smooth = ~mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta)
    facing = active & smooth & (sample.pdf > 0) & lit_side(si, sample.wo, direction, transmits)
    hit = scene.ray_intersect(si.spawn_ray(direction), facing)
    facing &= hit.is_valid()  # an environment is the dome's
    emitter = hit.emitter(scene, facing)  # null where the surface emits nothing: no radiance, no pdf
    radiance = emitter.eval(hit, facing)
    light_pdf = areas.points_of(emitter, facing) * emitter.pdf_direction(si, mi.DirectionSample3f(scene, hit, si), facing)
    weight = radiance * power_heuristic(count * sample.pdf, light_pdf) / (count * sample.pdf)
    return sample.wo, weight, facing & (dr.max(radiance) > 0), None


def delta_contribution(scene, si, transmits, emitters: DeltaEmitters, k, active):
    """(ωo in the local frame, incident weight, mask, None: no other strategy) for delta emitter k: its own
    ``sample_direction``, exact."""
    emitter = dr.gather(mi.EmitterPtr, emitters.pointers, k, active)
    ds, weight = emitter.sample_direction(si, dr.full(mi.Point2f, 0.5, dr.width(si.p)), active)
    wo = si.to_local(ds.d)
    facing = active & lit_side(si, wo, ds.d, transmits) & (dr.max(weight) > 0)
    visible = facing & ~scene.ray_test(si.spawn_ray_to(ds.p), facing)
    return wo, weight, visible, None


def led_contribution(scene, si, transmits, leds: LedArrays, k, far_field: bool, active):
    """(ωo in the local frame, incident irradiance-like weight I/d², mask, None: no other strategy) for LED k at the
    shading point."""
    p = dr.gather(mi.Point3f, leds.position, k, active)
    intensity = dr.gather(mi.Color3f, leds.intensity, k, active)
    if far_field:
        wo_world = mi.Vector3f(p)
        dist2 = mi.Float(1.0)
    else:
        offset = p - si.p
        dist2 = dr.squared_norm(offset)
        wo_world = offset * dr.rsqrt(dist2)
    wo = si.to_local(wo_world)
    facing = active & lit_side(si, wo, wo_world, transmits)
    if far_field:
        ray = si.spawn_ray(wo_world)
    else:
        ray = si.spawn_ray_to(p)
    visible = facing & ~scene.ray_test(ray, facing)
    return wo, intensity / dist2, visible, None


@dataclass
class Lights:
    """What one render lights with (:meth:`GraOneBounce.prepare_lights`)."""

    leds: LedArrays  # the point lights
    others: DeltaEmitters  # spot, projector, directional
    dome: LedArrays  # the environments' far-field lights
    areas: AreaLights
    delta_lobes: tuple  # the components that are delta lobes in some material (a mirror, glass), with light to see there


class GraOneBounce(RBIntegrator):
    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.far_field = bool(props.get("far_field", False))
        center = props.get("stage_center", mi.ScalarPoint3f(0.0, 1.0, 0.0))
        self.stage_center = np.array([center[0], center[1], center[2]], dtype=np.float64)
        self.dome_lights, self.area_samples, self.bsdf_samples = (
            checked_option(name, props.get(name, default)) for name, (_, default) in OPTIONS.items()
        )
        self._lights = None

    def prepare_lights(self, scene: mi.Scene) -> Lights:
        """The scene's lights as the loops read them (checked: a light gra-mi cannot compute stops here, by name): its
        point lights, its other delta lights, its environments' dome (unit directions, so irradiance is I / 1²), its
        area lights; and which material components are delta lobes that may see an environment or area light."""
        lights = scene_lights(scene, dome_lights=self.dome_lights)
        dome = LedLayout(lights.dome_directions, np.zeros(3), far_field=True)
        seen_in_delta_lobes = lights.environments or lights.areas
        return Lights(
            LedArrays(LedLayout(lights.positions, self.stage_center, self.far_field), lights.intensities),
            DeltaEmitters(lights.others),
            LedArrays(dome, lights.dome_irradiance),
            AreaLights(lights.areas, lights.area_weights, self.area_samples, self.bsdf_samples),
            delta_components(scene) if seen_in_delta_lobes else (),
        )

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        with self._lights_of(scene):
            return super().render(scene, sensor, seed, spp, develop, evaluate)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        with self._lights_of(scene):
            return super().render_backward(scene, params, grad_in, sensor, seed, spp)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        with self._lights_of(scene):
            return super().render_forward(scene, params, sensor, seed, spp)

    @contextmanager
    def _lights_of(self, scene):
        """The scene's lights for the length of one render, then let go: held longer they would keep its emitters
        alive, and every emitter alive is traced by each call on an emitter pointer."""
        self._lights = self.prepare_lights(scene)
        try:
            yield
        finally:
            self._lights = None

    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        primal = mode == dr.ADMode.Primal
        lights = self._lights if self._lights is not None else self.prepare_lights(scene)
        leds, others, dome, areas = lights.leds, lights.others, lights.dome, lights.areas
        far_field = self.far_field

        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
        valid = active & si.is_valid()
        bsdf = si.bsdf(ray)
        L = mi.Spectrum(0.0 if primal else state_in)  # radiance (or, in the adjoint pass, what is left of it)
        if primal and (dome.count or areas.count) and not self.hide_emitters:  # emitters seen directly, as in Mitsuba's
            L += si.emitter(scene, active).eval(si, active)  # an escaped ray's environment; an area light's surface
        δL = mi.Spectrum(δL if δL is not None else 0.0)  # adjoint radiance
        smooth = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)  # a mirror's points skip the lights' loops
        transmits = mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)  # lit from behind too
        if leds.count:
            L, δL = _sum_lights(
                mode,
                leds.count,
                lambda k, on: led_contribution(scene, si, transmits, leds, k, far_field, on),
                bsdf,
                si,
                smooth,
                L,
                δL,
                "LEDs",
            )
        if others.count:
            L, δL = _sum_lights(
                mode,
                others.count,
                lambda k, on: delta_contribution(scene, si, transmits, others, k, on),
                bsdf,
                si,
                smooth,
                L,
                δL,
                "delta lights",
            )
        if dome.count:
            L, δL = _sum_lights(
                mode,
                dome.count,
                lambda k, on: led_contribution(scene, si, transmits, dome, k, True, on),
                bsdf,
                si,
                smooth,
                L,
                δL,
                "environment dome",
            )
        if areas.count:
            L, δL = self._sum_area_lights(mode, scene, sampler, si, bsdf, areas, valid, smooth, L, δL)
        for component in lights.delta_lobes:
            L, δL = _add_delta_lobe(mode, scene, si, bsdf, component, valid, L, δL)
        return (L if primal else δL, valid, [], L)

    def _sum_area_lights(self, mode, scene, sampler, si, bsdf, areas: AreaLights, valid, smooth, L, δL):
        """The area lights' points, then the BSDF's directions that reach one (each weighted against the other), where
        the material has a smooth lobe. The random shifts are drawn here for every valid point, the same in the adjoint
        pass: it replays the primal pass's sampler."""
        shift, transmits = sampler.next_2d(valid), mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)
        L, δL = _sum_lights(
            mode, areas.samples, lambda k, on: area_contribution(scene, si, transmits, areas, shift, k, on), bsdf, si,
            smooth, L, δL, "area lights", other_count=areas.bsdf_samples,
        )  # fmt: skip
        if areas.bsdf_samples:
            shift, shift_1d = sampler.next_2d(valid), sampler.next_1d(valid)
            L, δL = _sum_lights(
                mode, areas.bsdf_samples, lambda k, on: bsdf_contribution(scene, si, transmits, bsdf, areas, shift, shift_1d, k, on), bsdf,
                si, smooth, L, δL, "BSDF samples towards area lights",
            )  # fmt: skip
        return L, δL

    def to_string(self):
        return (
            f"GraOneBounce[far_field={self.far_field}, dome_lights={self.dome_lights}, area_samples={self.area_samples}, "
            f"bsdf_samples={self.bsdf_samples}]"
        )


def delta_components(scene) -> tuple[int, ...]:
    """The component indices that are a delta lobe in some surface's material of ``scene`` (a mirror's one, a glass's
    reflection and transmission, a plastic's coat; inside shape groups too): each is followed with one ray
    (:func:`_add_delta_lobe`)."""
    parents = scene_objects(scene)
    found = set()
    for bsdf in (node for node, parent in parents.items() if isinstance(node, mi.BSDF) and isinstance(parent, mi.Shape)):
        found |= {c for c in range(bsdf.component_count()) if mi.has_flag(bsdf.flags(c), mi.BSDFFlags.Delta)}
    return tuple(sorted(found))


def _add_delta_lobe(mode, scene, si, bsdf, component: int, valid, L, δL):
    """L ± what the material's delta lobe ``component`` sees: its one direction, and the area light or environment it
    reaches there (a delta light never is). One ray per lobe, each lobe on its own, so a glass's reflection and
    transmission are both exact rather than chosen at random; no other strategy samples a delta direction, so the
    BSDF sample's own weight is the estimate. In the adjoint pass the gradient flows through that weight."""
    primal = mode == dr.ADMode.Primal
    ctx = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.Delta, component)
    middle = dr.full(mi.Point2f, 0.5, dr.width(valid))  # a delta lobe draws nothing from its samples
    with dr.resume_grad(when=not primal):
        sample, weight = bsdf.sample(ctx, si, middle.x, middle, valid)
        reached = valid & mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta) & (sample.pdf > 0)
        hit = scene.ray_intersect(si.spawn_ray(si.to_world(dr.detach(sample.wo))), reached)
        contribution = dr.select(reached, weight * dr.detach(hit.emitter(scene, reached).eval(hit, reached)), 0.0)
        if not primal:
            if mode == dr.ADMode.Backward:
                dr.backward_from(δL * contribution, flags=MAY_NOT_DEPEND)
            else:
                δL += dr.forward_to(contribution, flags=MAY_NOT_DEPEND)
    return (L + dr.detach(contribution) if primal else L - dr.detach(contribution)), δL


@dr.syntax
def _sum_lights(mode, count: int, contribution_of, bsdf, si, valid, L, δL, what: str, other_count: int = 0):
    """L ± Σ_k f(ωi, ωk) cosθk · weight_k over ``count`` lights (``contribution_of(k, mask)`` gives ωo, weight, mask
    and, where another strategy samples the same directions, this one's density: each term is then weighted against
    ``other_count`` × the BSDF's density by the power heuristic, from the same evaluation of the BSDF); in the adjoint
    pass the same sum is replayed with gradients around the BSDF's value only."""
    primal = mode == dr.ADMode.Primal
    ctx = mi.BSDFContext()
    k = mi.UInt32(0)
    n = mi.UInt32(count)
    while dr.hint(valid & (k < n), label=f"gra_onebounce {what} ({mode.name})"):
        wo, weight, visible, density = contribution_of(k, valid)
        with dr.resume_grad(when=not primal):
            if dr.hint(density is None, mode="scalar"):
                value = bsdf.eval(ctx, si, wo, visible)
            else:
                value, bsdf_pdf = bsdf.eval_pdf(ctx, si, wo, visible)
                value *= power_heuristic(density, other_count * dr.detach(bsdf_pdf))
            contribution = value * weight
            contribution = dr.select(visible, contribution, 0.0)
            if dr.hint(not primal, mode="scalar"):
                if dr.hint(mode == dr.ADMode.Backward, mode="scalar"):
                    dr.backward_from(δL * contribution, flags=MAY_NOT_DEPEND)
                else:
                    δL += dr.forward_to(contribution, flags=MAY_NOT_DEPEND)
        L = L + dr.detach(contribution) if primal else L - dr.detach(contribution)
        k += 1
    return L, δL


def register() -> None:
    mi.register_integrator("gra_onebounce", lambda props: GraOneBounce(props))
