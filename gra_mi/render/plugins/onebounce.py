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

At each camera hit the integrator sums over the scene's ``point`` emitters (the LEDs):

    L = Σ_k  f(ωi, ωk) cosθk · I_k / d_k² · V_k

with one shadow ray per LED (near field: inverse-square falloff from the LED's position). The LEDs are read from the
scene once per render into arrays (positions, intensities) and evaluated in one symbolic Dr.Jit loop, not one
virtual call per emitter. LEDs that are off are dropped before the loop; LEDs below the shading point's horizon
(shading or geometric normal) trace nothing. Other emitter types are ignored. Derivatives with respect to BSDF
parameters (``gra_microfacet`` textures) follow Path Replay Backpropagation: the loop is replayed in the adjoint
pass with gradients enabled around the BSDF evaluation only.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.python.ad.integrators.common import RBIntegrator

from gra_mi.render.leds import LedLayout


def point_lights(scene: mi.Scene) -> tuple[np.ndarray, np.ndarray]:
    """Positions (L, 3) and radiant intensities (L, 3) of the scene's point emitters, in emitter order."""
    emitters = [e for e in scene.emitters() if e.class_name() == "PointLight"]
    if not emitters:
        return np.zeros((0, 3)), np.zeros((0, 3))
    n = len(emitters)
    # One vectorised call over all LEDs: a point light's sample_direction from the origin gives its position and
    # I / d² (d = its distance to the origin).
    it = dr.zeros(mi.Interaction3f, n)
    ds, weight = mi.EmitterPtr(emitters).sample_direction(it, dr.full(mi.Point2f, 0.5, n), True)
    positions = np.array(ds.p, dtype=np.float64).T.reshape(n, 3)
    intensities = np.array(weight, dtype=np.float64).T.reshape(n, 3) * np.sum(positions**2, axis=1, keepdims=True)
    return positions, intensities


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


def led_contribution(scene, si, leds: LedArrays, k, far_field: bool, active):
    """(ωo in the local frame, incident irradiance-like weight I/d², mask) for LED k at the shading point."""
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
    # Below the shading or the geometric horizon: nothing to trace.
    facing = active & (wo.z > 0) & (dr.dot(si.n, wo_world) > 0)
    if far_field:
        ray = si.spawn_ray(wo_world)
    else:
        ray = si.spawn_ray_to(p)
    visible = facing & ~scene.ray_test(ray, facing)
    return wo, intensity / dist2, visible


class GraOneBounce(RBIntegrator):
    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.far_field = bool(props.get("far_field", False))
        center = props.get("stage_center", mi.ScalarPoint3f(0.0, 1.0, 0.0))
        self.stage_center = np.array([center[0], center[1], center[2]], dtype=np.float64)
        self._leds = None

    def prepare_leds(self, scene: mi.Scene) -> LedArrays:
        positions, intensities = point_lights(scene)
        return LedArrays(LedLayout(positions, self.stage_center, self.far_field), intensities)

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        self._leds = self.prepare_leds(scene)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        self._leds = self.prepare_leds(scene)
        return super().render_backward(scene, params, grad_in, sensor, seed, spp)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        self._leds = self.prepare_leds(scene)
        return super().render_forward(scene, params, sensor, seed, spp)

    @dr.syntax
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        primal = mode == dr.ADMode.Primal
        leds = self._leds if self._leds is not None else self.prepare_leds(scene)
        far_field = self.far_field
        ctx = mi.BSDFContext()

        # ---------------------- Camera ray --------------------------
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=True, active=active)
        valid = active & si.is_valid()
        bsdf = si.bsdf(ray)

        # ---------------------- Sum over LEDs ----------------------
        L = mi.Spectrum(0.0 if primal else state_in)  # radiance (or, in the adjoint pass, what is left of it)
        δL = mi.Spectrum(δL if δL is not None else 0.0)  # adjoint radiance
        k = mi.UInt32(0)  # LED index among those that are on
        count = mi.UInt32(leds.count)
        while dr.hint(valid & (k < count), label=f"gra_onebounce LEDs ({mode.name})"):
            wo, weight, visible = led_contribution(scene, si, leds, k, far_field, valid)
            with dr.resume_grad(when=not primal):
                contribution = bsdf.eval(ctx, si, wo, visible) * weight
                contribution = dr.select(visible, contribution, 0.0)
                if dr.hint(not primal, mode="scalar"):
                    if dr.hint(mode == dr.ADMode.Backward, mode="scalar"):
                        dr.backward_from(δL * contribution)
                    else:
                        δL += dr.forward_to(contribution)
            L = L + dr.detach(contribution) if primal else L - dr.detach(contribution)
            k += 1

        return (L if primal else δL, valid, [], L)

    def to_string(self):
        return f"GraOneBounce[far_field={self.far_field}]"


def register() -> None:
    mi.register_integrator("gra_onebounce", lambda props: GraOneBounce(props))
