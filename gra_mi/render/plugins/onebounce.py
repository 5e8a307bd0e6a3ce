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

with one shadow ray per light and E_k the light's incident irradiance-like weight (``point``: I/d², the LEDs, in near
field by default; ``spot`` and ``projector``: I·falloff/d²; ``directional``: its irradiance), as the emitter's own
``sample_direction`` gives it; environments (``envmap``, ``constant``, ``sunsky``) arrive through a dome of far-field
lights, each with the irradiance of its cell, one shadow ray each, like a lightstage's LEDs; ``area`` lights are
sampled on their surface by their own ``sample_direction``, ``area_samples`` points per pixel sample in all, shared
among the lights in proportion to power × ``sampling_weight`` and at least one each (every light is in every
estimate), spread over each light as a rank-1 lattice shifted at random per pixel sample (unbiased, with less noise
than independent points: :mod:`gra_mi.render.lattice`), and reached by ``bsdf_samples`` directions from the BSDF (a
lattice too), the two weighted by the power heuristic as Mitsuba's ``direct`` weighs its emitter and BSDF samples: the
points carry a small light, the directions a glossy highlight or a large light close by. Each delta lobe of a material
(a mirror, a glass's reflection and transmission, a plastic's coat) sees the environment and area lights along its one
direction, one ray per lobe; the camera sees the lights' surface as Mitsuba shows it. Point emitters (a lightstage has
hundreds) are read from the scene once per render into arrays and evaluated in one symbolic Dr.Jit loop, not one
virtual call per emitter; the other delta lights follow in a second loop that calls each emitter. Point lights and
area lights that are off are dropped before the loop; lights on the far side of a surface from the viewer (by the
shading or the geometric normal) trace nothing unless the material transmits
(:meth:`~gra_mi.render.plugins.light_terms.ShadingPoint.faces`; the back of a ``twosided`` plane is lit from its own
side); points whose material has no smooth lobe skip the loops; dark cells of the dome are dropped. A see-through
material (``mask``, ``null``) is passed by a camera ray with the probability of its transmission
(:func:`first_seen_surface`) and multiplies the light of the shadow rays that cross it
(:func:`~gra_mi.render.plugins.light_terms.cross_see_through`). ``directionalarea`` emitters and participating media
are refused by name when a render starts (:mod:`gra_mi.render.scene_lights`), as is a scene without light. Derivatives
with respect to BSDF parameters (``gra_microfacet`` textures) follow Path Replay Backpropagation: the loops are
replayed in the adjoint pass with gradients enabled around the BSDF evaluation only (the directions' pdf held fixed).
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.python.ad.integrators.common import RBIntegrator

from gra_mi.render.leds import LedLayout
from gra_mi.render.plugins.light_terms import (
    SEE_THROUGH_LAYERS,
    AreaLights,
    DeltaEmitters,
    LedArrays,
    ShadingPoint,
    area_term,
    bsdf_term,
    delta_term,
    led_term,
    power_heuristic,
    scaled,
)
from gra_mi.render.scene_lights import OPTIONS, checked_option, scene_lights

# A light's term may not depend on what is differentiated (a mirror's smooth lobes are zero): no gradient, no error.
MAY_NOT_DEPEND = dr.ADFlag.Default | dr.ADFlag.AllowNoGrad


@dataclass
class Lights:
    """What one render lights with (:meth:`GraOneBounce.prepare_lights`)."""

    leds: LedArrays  # the point lights
    others: DeltaEmitters  # spot, projector, directional
    dome: LedArrays  # the environments' far-field lights
    areas: AreaLights
    delta_lobes: tuple  # the components that are delta lobes in some material (a mirror, glass), with light to see there
    see_through: bool  # a material lets light through its surface (null, mask): rays cross it


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
            delta_components(lights.objects) if seen_in_delta_lobes else (),
            see_through(lights.objects),
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
        leds, others, dome, areas, far_field = lights.leds, lights.others, lights.dome, lights.areas, self.far_field
        if lights.see_through:
            si, throughput = first_seen_surface(scene, sampler, ray, active)
        else:
            si, throughput = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active), None
        valid = active & si.is_valid()
        bsdf = si.bsdf(ray)
        at = ShadingPoint(scene, si, bsdf, mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission), lights.see_through, throughput)
        L = mi.Spectrum(0.0 if primal else state_in)  # radiance (or, in the adjoint pass, what is left of it)
        if primal and (dome.count or areas.count) and not self.hide_emitters:  # emitters seen directly, as in Mitsuba's
            L += scaled(si.emitter(scene, active).eval(si, active), throughput)  # an escaped ray's environment; a light's face
        δL = mi.Spectrum(δL if δL is not None else 0.0)  # adjoint radiance
        smooth = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)  # a mirror's points skip the lights' loops
        loops = [(leds.count, lambda k, on: led_term(at, leds, k, far_field, on), "LEDs"),
                 (others.count, lambda k, on: delta_term(at, others, k, on), "delta lights"),
                 (dome.count, lambda k, on: led_term(at, dome, k, True, on), "environment dome")]  # fmt: skip
        for count, term, what in loops:
            if count:
                L, δL = _sum_lights(mode, count, term, at, smooth, L, δL, what)
        if areas.count:
            L, δL = _sum_area_lights(mode, sampler, at, areas, valid, smooth, L, δL)
        for component in lights.delta_lobes:
            L, δL = _add_delta_lobe(mode, at, component, valid, L, δL)
        return (L if primal else δL, valid, [], L)

    def to_string(self):
        return (
            f"GraOneBounce[far_field={self.far_field}, dome_lights={self.dome_lights}, area_samples={self.area_samples}, "
            f"bsdf_samples={self.bsdf_samples}]"
        )


def _sum_area_lights(mode, sampler, at: ShadingPoint, areas: AreaLights, valid, smooth, L, δL):
    """The area lights' points, then the BSDF's directions that reach one (each weighted against the other), where the
    material has a smooth lobe. The random shifts are drawn here for every valid point, the same in the adjoint pass:
    it replays the primal pass's sampler."""
    shift = sampler.next_2d(valid)
    L, δL = _sum_lights(
        mode, areas.samples, lambda k, on: area_term(at, areas, shift, k, on), at, smooth, L, δL, "area lights",
        other_count=areas.bsdf_samples,
    )  # fmt: skip
    if areas.bsdf_samples:
        shift, shift_1d = sampler.next_2d(valid), sampler.next_1d(valid)
        L, δL = _sum_lights(
            mode, areas.bsdf_samples, lambda k, on: bsdf_term(at, areas, shift, shift_1d, k, on), at, smooth, L, δL,
            "BSDF samples towards area lights",
        )  # fmt: skip
    return L, δL


def see_through(objects: dict) -> bool:
    """Whether some material among a scene's ``objects`` (:func:`~gra_mi.render.scene_lights.scene_objects`) lets light
    through its surface (``null``, ``mask``)."""
    return any(isinstance(node, mi.BSDF) and mi.has_flag(node.flags(), mi.BSDFFlags.Null) for node in objects)


@dr.syntax
def first_seen_surface(scene, sampler, ray, active) -> tuple:
    """(the surface a camera ray shows, the weight of choosing it) where see-through surfaces stand in its way: at one
    whose transmission averages p the ray passes on with probability p (weight transmission / p) or stops there
    (weight 1 / (1 − p): the material's ``eval`` already carries its opaque part), as Mitsuba's ``path`` chooses. The
    shading that follows is done once, at the chosen surface."""
    ray, weight = mi.Ray3f(ray), mi.Spectrum(1.0)  # a camera's ray differential: the surface shown needs none
    going = mi.Bool(active)
    crossed = mi.UInt32(0)
    while dr.hint(going, label="gra_onebounce camera rays through see-through surfaces"):
        si = scene.ray_intersect(ray, mi.RayFlags.All, False, going)
        through = si.bsdf(ray).eval_null_transmission(si, going & si.is_valid())
        p = dr.mean(through)
        passes = going & si.is_valid() & (p > 0) & (crossed < SEE_THROUGH_LAYERS) & (sampler.next_1d(going) < p)
        stops = going & ~passes & si.is_valid() & (p > 0)
        stop_weight = dr.select(p < 1, dr.rcp(1 - p), 0.0)
        weight = dr.select(passes, weight * through / p, dr.select(stops, weight * stop_weight, weight))
        ray = dr.select(passes, si.spawn_ray(ray.d), ray)
        going = passes
        crossed += 1
    return scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active), weight


def delta_components(objects: dict) -> tuple[int, ...]:
    """The component indices that are a delta lobe in some surface's material among a scene's ``objects`` (each → its
    parent, :func:`~gra_mi.render.scene_lights.scene_objects`; a mirror's one, a glass's reflection and transmission, a
    plastic's coat; inside shape groups too): each is followed with one ray (:func:`_add_delta_lobe`)."""
    found = set()
    for bsdf in (node for node, parent in objects.items() if isinstance(node, mi.BSDF) and isinstance(parent, mi.Shape)):
        found |= {c for c in range(bsdf.component_count()) if mi.has_flag(bsdf.flags(c), mi.BSDFFlags.Delta)}
    return tuple(sorted(found))


def _add_delta_lobe(mode, at: ShadingPoint, component: int, valid, L, δL):
    """L ± what the material's delta lobe ``component`` sees: its one direction, and the area light or environment it
    reaches there (a delta light never is). One ray per lobe, each lobe on its own, so a glass's reflection and
    transmission are both exact rather than chosen at random; no other strategy samples a delta direction, so the
    BSDF sample's own weight is the estimate. In the adjoint pass the gradient flows through that weight."""
    primal, si = mode == dr.ADMode.Primal, at.si
    ctx = mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.Delta, component)
    middle = dr.full(mi.Point2f, 0.5, dr.width(valid))  # a delta lobe draws nothing from its samples
    with dr.resume_grad(when=not primal):
        sample, weight = at.bsdf.sample(ctx, si, middle.x, middle, valid)
        reached = valid & mi.has_flag(sample.sampled_type, mi.BSDFFlags.Delta) & (sample.pdf > 0)
        hit, passed = at.trace(si.spawn_ray(si.to_world(dr.detach(sample.wo))), reached)
        seen = scaled(scaled(dr.detach(hit.emitter(at.scene, reached).eval(hit, reached)), passed), at.throughput)
        contribution = dr.select(reached, weight * seen, 0.0)
        if not primal:
            if mode == dr.ADMode.Backward:
                dr.backward_from(δL * contribution, flags=MAY_NOT_DEPEND)
            else:
                δL += dr.forward_to(contribution, flags=MAY_NOT_DEPEND)
    return (L + dr.detach(contribution) if primal else L - dr.detach(contribution)), δL


@dr.syntax
def _sum_lights(mode, count: int, contribution_of, at: ShadingPoint, valid, L, δL, what: str, other_count: int = 0):
    """L ± Σ_k f(ωi, ωk) cosθk · weight_k over ``count`` lights (``contribution_of(k, mask)`` gives ωo, weight, mask
    and, where another strategy samples the same directions, this one's density: each term is then weighted against
    ``other_count`` × the BSDF's density by the power heuristic, from the same evaluation of the BSDF); in the adjoint
    pass the same sum is replayed with gradients around the BSDF's value only."""
    primal, bsdf, si, throughput = mode == dr.ADMode.Primal, at.bsdf, at.si, at.throughput
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
            contribution = dr.select(visible, scaled(value * weight, throughput), 0.0)
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
