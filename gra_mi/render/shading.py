"""Per-view one-bounce shading of the texels (paper Eq. 1): Σ over LEDs that are on of visibility · I/d² · f(ωi, ωk)
cosθk, in one Dr.Jit loop over each texel's visible LEDs. Changing the envmap only changes the intensities: nothing
is re-traced.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.runtime import opaque
from gra_mi.render import brdf
from gra_mi.render.atlas import TexelGeometry
from gra_mi.render.leds import LedLayout


@dataclass
class TexelShading:
    radiance: np.ndarray  # (M, 3) outgoing radiance toward the camera
    view_dir: np.ndarray  # (M, 3) unit direction from texel to camera (world)
    facing_camera: np.ndarray  # (M,) the camera is above the texel's horizon
    diffuse_unit: np.ndarray  # (M, 3) the diffuse part for albedo 1: radiance = albedo ⊙ diffuse_unit + specular
    specular: np.ndarray  # (M, 3)


def shade_texels(
    geom: TexelGeometry,
    visibility: mi.UInt32 | None,
    leds: LedLayout,
    led_intensities: np.ndarray,
    albedo: np.ndarray,
    roughness: np.ndarray,
    camera_position: np.ndarray,
    indirect: np.ndarray | None = None,
) -> TexelShading:
    """Outgoing radiance of every valid texel toward ``camera_position`` (paper Eq. 1, one bounce).

    ``albedo`` (M, 3) and ``roughness`` (M,) are per valid texel. LEDs that are off are dropped before the loop;
    ``visibility`` may be None when every LED is off. ``indirect`` (M, 3): the light after the first bounce each
    texel's diffuse layer receives (:func:`gra_mi.render.bounce.indirect_unit`), added to the diffuse part.
    """
    m = dr.width(geom.position)
    words, on_words, pos, inten = led_loop_inputs(leds, led_intensities)

    p, n = geom.position, geom.normal
    frame = mi.Frame3f(n)
    view = dr.normalize(opaque(mi.Point3f, camera_position) - p)
    wi = frame.to_local(view)
    if np.max(led_intensities, initial=0.0) > 0:
        diffuse, spec = _led_sum(
            m, words, visibility, on_words, pos, inten, p, frame, wi, mi.Float(np.asarray(roughness, np.float32)), leds.far_field
        )
    else:  # every LED off: nothing to do
        diffuse, spec = dr.zeros(mi.Color3f, m), dr.zeros(mi.Color3f, m)
    if indirect is not None:
        diffuse += indirect_toward(wi, mi.Color3f(*np.asarray(indirect, np.float32).T))
    dr.eval(diffuse, spec, view, wi)
    diffuse, spec = np.array(diffuse).T.reshape(m, 3), np.array(spec).T.reshape(m, 3)
    radiance = np.asarray(albedo, np.float32) * diffuse + spec
    return TexelShading(radiance, np.array(view).T.reshape(m, 3), np.array(wi.z > 0), diffuse, spec)


def indirect_toward(wi: mi.Vector3f, indirect: mi.Color3f) -> mi.Color3f:
    """The diffuse radiance per unit albedo that light after the first bounce (``indirect``, per unit T of the
    receiving texel) sends toward ``wi``: the diffuse layer's transmission toward the viewer, 0 below the horizon."""
    return dr.select(wi.z > 0, brdf.diffuse_transmission(wi.z), 0.0) * indirect


ALONG_NORMAL = None
"""``camera_position`` that shades each texel as seen along its own normal: T(ω_view) = 1, so the diffuse part is the
view-independent light each texel's diffuse layer sends out per unit albedo (what a later bounce starts from)."""


def local_view(frame: mi.Frame3f, position: mi.Point3f, viewer) -> mi.Vector3f:
    """ωi in each lane's shading frame for ``viewer``: a camera position (3,), :data:`ALONG_NORMAL`, or per-lane world
    directions toward the viewer (``mi.Vector3f``: light leaving one texel toward another)."""
    if viewer is ALONG_NORMAL:
        wi = dr.zeros(mi.Vector3f, dr.width(position))
        wi.z = 1.0
        return wi
    if isinstance(viewer, mi.Vector3f):
        return frame.to_local(viewer)
    return frame.to_local(dr.normalize(opaque(mi.Point3f, viewer) - position))


@dataclass
class TexelLedLoop:
    """The LED sum of a subset of a frame's texels seen from one camera under one lighting, with its inputs gathered
    once: material fitting runs it many times (roughness candidates, optimiser steps) on the same texels."""

    count: int
    words: int
    visibility: mi.UInt32
    on_words: mi.UInt32
    led_pos: mi.Point3f
    led_int: mi.Color3f
    position: mi.Point3f
    frame: mi.Frame3f
    wi: mi.Vector3f
    far_field: bool = False
    indirect: tuple | None = None  # per lane: (diffuse per unit albedo, specular) of the light after the first bounce

    @classmethod
    def build(
        cls,
        geom: TexelGeometry,
        visibility: mi.UInt32,
        texels: np.ndarray,
        leds: LedLayout,
        led_intensities: np.ndarray,
        camera_position,
        indirect: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> TexelLedLoop:
        """The loop of ``texels`` (repeats allowed) seen from ``camera_position`` (any viewer :func:`local_view`
        takes). ``indirect``: the light after the first bounce, held fixed, as ((M, 3) what each texel's diffuse layer
        takes in, as :func:`shade_texels` takes it; (M, 3) the specular light it sends toward this viewer)."""
        m = dr.width(geom.position)
        words, on_words, led_pos, led_int = led_loop_inputs(leds, led_intensities)
        t = mi.UInt32(np.asarray(texels, np.uint32))
        position = dr.gather(mi.Point3f, geom.position, t)
        frame = mi.Frame3f(dr.gather(mi.Vector3f, geom.normal, t))
        wi = local_view(frame, position, camera_position)
        extra = None
        if indirect is not None:
            diffuse_in, specular = (mi.Color3f(*np.asarray(x, np.float32).T) for x in indirect)
            extra = (indirect_toward(wi, dr.gather(mi.Color3f, diffuse_in, t)), dr.gather(mi.Color3f, specular, t))
        # Visibility words are word-major over all texels (w * M + t): gather this subset's, in the same layout.
        index = (np.arange(words, dtype=np.uint64)[:, None] * m + np.asarray(texels, np.uint64)[None, :]).ravel()
        vis = dr.gather(mi.UInt32, visibility, mi.UInt32(index.astype(np.uint32)))
        dr.eval(position, frame, wi, vis, extra)
        return cls(int(len(texels)), words, vis, on_words, led_pos, led_int, position, frame, wi, leds.far_field, extra)

    def run(self, roughness: mi.Float, roughness_derivative: bool = False):
        """(diffuse per unit albedo, specular) per texel of the subset, and ∂ specular / ∂ roughness if asked."""
        parts = _led_sum(
            self.count, self.words, self.visibility, self.on_words, self.led_pos, self.led_int, self.position, self.frame, self.wi,
            roughness, self.far_field, roughness_derivative,
        )  # fmt: skip
        if self.indirect is None:
            return parts
        return (parts[0] + self.indirect[0], parts[1] + self.indirect[1], *parts[2:])


def led_cell_roughness(roughness: np.ndarray, num_leds: int) -> np.ndarray:
    """Roughness whose GGX lobe is widened to the angular spacing of ``num_leds`` LEDs that sample an environment.

    Each LED stands for a cell of about 4π/L sr, 2/√L rad across; a lobe narrower than that sees the samples (one
    sparkle per LED, a sun split into three highlights) instead of the environment. α² + α_cell², α_cell = 1/√L
    (half-vectors spread half as far as the light), widens roughness 0.31 by 7 % and leaves rough texels alone.
    """
    alpha = np.square(np.asarray(roughness, np.float64))
    return np.minimum(np.sqrt(np.sqrt(alpha**2 + 1.0 / num_leds)), np.maximum(roughness, 1.0)).astype(np.float32)


def led_loop_inputs(leds: LedLayout, led_intensities: np.ndarray) -> tuple[int, mi.UInt32, mi.Point3f, mi.Color3f]:
    """What :func:`_led_sum` needs of the LEDs: (visibility words per texel, the mask of LEDs that are on in the same
    word layout, LED targets and intensities as :meth:`LedLayout.as_lights` gives them)."""
    num_leds = leds.num_leds
    on = np.max(led_intensities, axis=1) > 0
    pos, inten = leds.as_lights(led_intensities)
    # One bit per LED that is on, in the same word layout as the visibility: off LEDs are masked out of every
    # texel's word before the loop, so they cost nothing.
    words = (num_leds + 31) // 32
    on_bits = np.zeros(words * 32, bool)
    on_bits[:num_leds] = on
    on_words = (on_bits.reshape(words, 32) * (1 << np.arange(32, dtype=np.uint64))).sum(axis=1).astype(np.uint32)
    return words, mi.UInt32(on_words), mi.Point3f(*pos.T.astype(np.float32)), mi.Color3f(*inten.T.astype(np.float32))


@dr.syntax
def _led_sum(m, words, visibility, on_words, led_pos, led_int, p, frame, wi, roughness, far_field, roughness_derivative=False):
    """Σ over the LEDs that are on *and* visible from each texel, walking the set bits of its visibility words.

    Each lane loops over its own visible LEDs only (about a fifth of them on a body), instead of all LEDs masked.
    Returns (diffuse per unit albedo, specular), and ∂ specular / ∂ roughness with ``roughness_derivative``.
    """
    t = dr.arange(mi.UInt32, m)  # texel index
    # The texel count as a kernel input, not a literal: a fit's views and a culled frame each have their own count,
    # and a literal would compile (and keep in memory) one LED-loop kernel per count.
    stride = dr.opaque(mi.UInt32, m)
    material = brdf.PreparedBRDF(mi.Color3f(1.0), roughness, wi)  # per-texel terms hoisted out of the loop
    diffuse = mi.Color3f(0.0)  # Σ diffuse part per unit albedo (the model is linear in albedo)
    spec = mi.Color3f(0.0)  # Σ specular part
    dspec = mi.Color3f(0.0)  # Σ ∂ specular / ∂ roughness (stays 0 unless asked for)
    n_words = mi.UInt32(words)
    # Texels the camera sees from below their horizon reflect nothing toward it (the BRDF is zero there): they skip the
    # loop, exactly (about half of them on a body).
    w = dr.select(material.front, mi.UInt32(0), n_words)  # current visibility word
    bits = dr.select(material.front, dr.gather(mi.UInt32, visibility, t) & dr.gather(mi.UInt32, on_words, mi.UInt32(0)), 0)
    while w < n_words:
        if bits == 0:
            w += 1
            bits = dr.gather(mi.UInt32, visibility, w * stride + t, w < n_words) & dr.gather(mi.UInt32, on_words, w, w < n_words)
        else:
            led = w * 32 + dr.tzcnt(bits)
            bits = bits & (bits - 1)  # clear the lowest set bit
            lp = dr.gather(mi.Point3f, led_pos, led)
            intensity = dr.gather(mi.Color3f, led_int, led)
            if dr.hint(far_field, mode="scalar"):
                wo_world = mi.Vector3f(lp)
                inv_d2 = mi.Float(1.0)
            else:
                offset = lp - p
                inv_d = dr.rsqrt(dr.squared_norm(offset))
                inv_d2 = dr.square(inv_d)
                wo_world = offset * inv_d
            wo = frame.to_local(wo_world)
            weight = intensity * inv_d2
            if dr.hint(roughness_derivative, mode="scalar"):
                d_part, s_part, ds_part = material.eval_parts(wo, roughness_derivative=True)
                dspec += ds_part * weight
            else:
                d_part, s_part = material.eval_parts(wo)
            diffuse += d_part * weight
            spec += s_part * weight
    return (diffuse, spec, dspec) if roughness_derivative else (diffuse, spec)
