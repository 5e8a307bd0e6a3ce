"""Per-view one-bounce shading of the texels (paper Eq. 1): Σ over LEDs that are on of visibility · I/d² · f(ωi, ωk)
cosθk, in one Dr.Jit loop over each texel's visible LEDs. Changing the envmap only changes the intensities: nothing
is re-traced.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.runtime import concat, opaque
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
    p, n = geom.position, geom.normal
    frame = mi.Frame3f(n)
    view = dr.normalize(opaque(mi.Point3f, camera_position) - p)
    wi = frame.to_local(view)
    if np.max(led_intensities, initial=0.0) > 0:
        on, pos, inten = led_loop_inputs(leds, led_intensities)
        words, vis = lane_visibility(visibility, m, None, on, leds.num_leds)
        diffuse, spec = _led_sum(m, words, vis, pos, inten, p, frame, wi, mi.Float(np.asarray(roughness, np.float32)), leds.far_field)
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
    visibility: mi.UInt32  # per lane, one bit per LED that is on (:func:`lane_visibility`)
    led_pos: mi.Point3f
    led_int: mi.Color3f
    position: mi.Point3f
    frame: mi.Frame3f
    wi: mi.Vector3f
    far_field: bool = False
    indirect: tuple | None = None  # per lane: (diffuse per unit albedo, specular) of the light after the first bounce
    led_base: mi.UInt32 | None = None  # per lane, where its LEDs start in led_pos / led_int (loops joined by concat)

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
        distinct: tuple[np.ndarray, np.ndarray] | None = None,
        hold: bool = True,
    ) -> TexelLedLoop:
        """The loop of ``texels`` (repeats allowed) seen from ``camera_position`` (any viewer :func:`local_view`
        takes). ``indirect``: the light after the first bounce, held fixed, as ((M, 3) what each texel's diffuse layer
        takes in, as :func:`shade_texels` takes it; (M, 3) the specular light it sends toward this viewer).
        ``distinct``: ``np.unique(texels, return_inverse=True)`` as two ``mi.UInt32`` when texels repeat (the rays of a
        bounce share their sources): the visibility is then packed once per texel, not per lane. ``hold``: the gathered
        inputs are evaluated once, for a loop run many times (a fit); False for one run, which gathers them itself."""
        m = dr.width(geom.position)
        on, led_pos, led_int = led_loop_inputs(leds, led_intensities)
        t = mi.UInt32(np.asarray(texels, np.uint32))
        position = dr.gather(mi.Point3f, geom.position, t)
        frame = mi.Frame3f(dr.gather(mi.Vector3f, geom.normal, t))
        wi = local_view(frame, position, camera_position)
        extra = None
        if indirect is not None:
            diffuse_in, specular = (mi.Color3f(*np.asarray(x, np.float32).T) for x in indirect)
            extra = (indirect_toward(wi, dr.gather(mi.Color3f, diffuse_in, t)), dr.gather(mi.Color3f, specular, t))
        words, vis = lane_visibility(visibility, m, t, on, leds.num_leds, distinct)
        if hold:
            dr.eval(position, frame, wi, vis, extra)
        return cls(int(len(texels)), words, vis, led_pos, led_int, position, frame, wi, leds.far_field, extra)

    @classmethod
    def concat(cls, loops: list[TexelLedLoop]) -> TexelLedLoop:
        """One loop over the lanes of ``loops`` (a fit step's views: their own texels, cameras and lightings), each
        lane walking its own loop's LEDs: one kernel where there were ``len(loops)``, whose launches and host work
        dominated a step on small views. Lane i of loop k is lane (Σ counts before k) + i; each lane's values are
        those its own loop computes."""
        if len(loops) == 1:
            return loops[0]
        if len({loop.far_field for loop in loops}) > 1:
            raise ValueError("loops of far-field and near-field LEDs cannot be joined")
        counts = np.array([loop.count for loop in loops], np.int64)
        total, words = int(counts.sum()), max(loop.words for loop in loops)
        visibility = dr.zeros(mi.UInt32, words * total)
        start = 0
        for loop, count in zip(loops, counts, strict=True):  # word-major: word w of lane i at w * total + i
            if loop.words:
                j = dr.arange(mi.UInt32, loop.words * int(count))
                w = j // dr.opaque(mi.UInt32, int(count))
                lane = j - w * dr.opaque(mi.UInt32, int(count))
                dr.scatter(visibility, loop.visibility, w * dr.opaque(mi.UInt32, total) + lane + dr.opaque(mi.UInt32, start))
            start += int(count)
        led_counts = [dr.width(loop.led_int) if loop.words else 0 for loop in loops]
        led_starts = np.cumsum([0] + led_counts[:-1]).astype(np.uint32)
        base = mi.UInt32(np.repeat(led_starts, counts))
        if any(loop.led_base is not None for loop in loops):
            base += concat(mi.UInt32, [dr.zeros(mi.UInt32, loop.count) if loop.led_base is None else loop.led_base for loop in loops])
        dr.eval(visibility, base)
        with_leds = [loop for loop in loops if loop.words] or loops[:1]
        indirect = None
        if any(loop.indirect is not None for loop in loops):
            zero = [(dr.zeros(mi.Color3f, loop.count),) * 2 if loop.indirect is None else loop.indirect for loop in loops]
            indirect = tuple(concat(mi.Color3f, [z[k] for z in zero]) for k in range(2))

        def joined(name: str, among=loops):
            return concat(type(getattr(loops[0], name)), [getattr(loop, name) for loop in among])

        return cls(
            total, words, visibility, joined("led_pos", with_leds), joined("led_int", with_leds), joined("position"),
            joined("frame"), joined("wi"), loops[0].far_field, indirect, base,
        )  # fmt: skip

    def run(self, roughness: mi.Float | tuple, roughness_derivative: bool = False, material=None):
        """(diffuse per unit albedo, specular) per texel of the subset, and ∂ specular / ∂ roughness if asked.
        ``roughness`` as a tuple (a fit's candidate values): the specular part as a tuple, one per value, from one walk
        over the LEDs (no derivative then); None: a Lambertian surface (:func:`_led_sum`). ``material``: another
        material per lane instead (``front`` and ``eval_parts(wo)`` as :class:`~gra_mi.render.brdf.PreparedBRDF` has
        them: a set's glossy lobe, :class:`~gra_mi.render.bounce.SetGlossyLobe`)."""
        grid = isinstance(roughness, tuple)
        if grid and roughness_derivative:
            raise ValueError("the roughness derivative is for one roughness per texel, not a tuple of candidates")
        if self.words == 0:  # every LED off
            zero = dr.zeros(mi.Color3f, self.count)
            parts = (zero, (zero,) * len(roughness) if grid else zero) + ((zero,) if roughness_derivative else ())
        else:
            parts = _led_sum(
                self.count, self.words, self.visibility, self.led_pos, self.led_int, self.position, self.frame, self.wi,
                roughness, self.far_field, roughness_derivative, self.led_base, material,
            )  # fmt: skip
            # Together: each output of a loop evaluated on its own (a NumPy read, an AD pass) runs the whole loop again.
            dr.eval(*parts)
        if self.indirect is None:
            return parts
        spec = tuple(x + self.indirect[1] for x in parts[1]) if grid else parts[1] + self.indirect[1]
        return (parts[0] + self.indirect[0], spec, *parts[2:])


def led_cell_roughness(roughness: np.ndarray, num_leds: int) -> np.ndarray:
    """Roughness whose GGX lobe is widened to the angular spacing of ``num_leds`` LEDs that sample an environment.

    Each LED stands for a cell of about 4π/L sr, 2/√L rad across; a lobe narrower than that sees the samples (one
    sparkle per LED, a sun split into three highlights) instead of the environment. α² + α_cell², α_cell = 1/√L
    (half-vectors spread half as far as the light), widens roughness 0.31 by 7 % and leaves rough texels alone.
    """
    alpha = np.square(np.asarray(roughness, np.float64))
    return np.minimum(np.sqrt(np.sqrt(alpha**2 + 1.0 / num_leds)), np.maximum(roughness, 1.0)).astype(np.float32)


def led_loop_inputs(leds: LedLayout, led_intensities: np.ndarray) -> tuple[np.ndarray, mi.Point3f, mi.Color3f]:
    """What :func:`_led_sum` needs of the LEDs: (the indices of the LEDs that are on, their targets and intensities as
    :meth:`LedLayout.as_lights` gives them). LEDs that are off never enter the loop."""
    on = np.flatnonzero(np.max(led_intensities, axis=1) > 0)
    pos, inten = leds.as_lights(led_intensities)
    # Opaque: one LED's arrays (an OLAT) would otherwise be literals, and every OLAT its own kernel (an LLVM compile).
    return on, _opaque_columns(mi.Point3f, pos[on]), _opaque_columns(mi.Color3f, inten[on])


def _opaque_columns(kind, rows: np.ndarray):
    value = kind(*np.asarray(rows, np.float32).T)
    dr.make_opaque(value)
    return value


def lane_visibility(
    visibility: mi.UInt32, m: int, lanes: mi.UInt32 | None, on: np.ndarray, num_leds: int,
    distinct: tuple[mi.UInt32, mi.UInt32] | None = None,
) -> tuple[int, mi.UInt32]:  # fmt: skip
    """The visibility the LED loop walks: per lane (texel ``lanes[i]``, or texel i when ``lanes`` is None), one bit per
    LED that is on, in the order of ``on``, word-major over the lanes. ``visibility`` is the frame's cache (one bit
    per LED, word-major over its ``m`` texels). With every LED on that is its own layout; with fewer (an OLAT, a
    pattern, the LEDs a bounce starts from) their bits are packed into fewer words, so a lane walks only those.
    ``distinct`` (the distinct lane texels, each lane's index among them): packed once per texel, then spread."""
    if distinct is not None and len(on) not in (0, num_leds):
        texels, index = distinct
        words, packed = lane_visibility(visibility, m, texels, on, num_leds)
        return words, _spread_words(packed, dr.width(texels), index, words)
    if len(on) == num_leds:
        words = (num_leds + 31) // 32
        if lanes is None:
            return words, visibility
        n = dr.width(lanes)
        lane = dr.arange(mi.UInt32, words * n)
        w = lane // dr.opaque(mi.UInt32, n)  # sizes as kernel inputs: one kernel for every view's lane count
        i = lane - w * dr.opaque(mi.UInt32, n)
        return words, dr.gather(mi.UInt32, visibility, w * dr.opaque(mi.UInt32, m) + dr.gather(mi.UInt32, lanes, i))
    n = m if lanes is None else dr.width(lanes)
    if len(on) == 0:  # every LED off: no word to walk
        return 0, dr.zeros(mi.UInt32, n)
    words = (len(on) + 31) // 32
    leds_on = mi.UInt32(np.asarray(on, np.uint32))
    dr.make_opaque(leds_on)  # an OLAT's one index would be a literal: a kernel per LED
    return words, _packed_bits(visibility, m, lanes, leds_on, len(on), words * n, n)


def _spread_words(packed: mi.UInt32, count: int, index: mi.UInt32, words: int) -> mi.UInt32:
    """Word c of lane i = word c of distinct texel index[i] (both layouts word-major)."""
    n = dr.width(index)
    lane = dr.arange(mi.UInt32, words * n)
    c = lane // dr.opaque(mi.UInt32, n)
    i = lane - c * dr.opaque(mi.UInt32, n)
    return dr.gather(mi.UInt32, packed, c * dr.opaque(mi.UInt32, count) + dr.gather(mi.UInt32, index, i))


@dr.syntax
def _packed_bits(visibility, m, lanes, on, count, size, n):
    """Word c of lane i: bit b is LED on[32c + b]'s bit of texel lanes[i] (:func:`lane_visibility`). The sizes are
    kernel inputs, not literals: one kernel for every pattern and subset."""
    lane = dr.arange(mi.UInt32, size)
    c = lane // dr.opaque(mi.UInt32, n)
    i = lane - c * dr.opaque(mi.UInt32, n)
    t = i if lanes is None else dr.gather(mi.UInt32, lanes, i)
    stride, total = dr.opaque(mi.UInt32, m), dr.opaque(mi.UInt32, count)
    word, b = mi.UInt32(0), mi.UInt32(0)
    while (b < 32) & (c * 32 + b < total):
        led = dr.gather(mi.UInt32, on, c * 32 + b)
        word |= ((dr.gather(mi.UInt32, visibility, (led >> 5) * stride + t) >> (led & 31)) & 1) << b
        b += 1
    return word


@dr.syntax
def _led_sum(m, words, visibility, led_pos, led_int, p, frame, wi, roughness, far_field, roughness_derivative=False, led_base=None, material=None):  # fmt: skip
    """Σ over the LEDs that are on *and* visible from each texel, walking the set bits of its visibility words
    (:func:`lane_visibility`: only the LEDs that are on have bits; ``led_pos`` and ``led_int`` are theirs).

    Each lane loops over its own visible LEDs only (about a fifth of them on a body), instead of all LEDs masked.
    Returns (diffuse per unit albedo, specular), and ∂ specular / ∂ roughness with ``roughness_derivative``.
    ``roughness`` as a tuple (of scalars or per-lane values): the specular part for each, as a tuple, from one walk
    over the LEDs (the diffuse part does not depend on it); None: Lambert's cosθ / π (the specular part 0). ``led_base``: per lane, where its LEDs start in ``led_pos``
    and ``led_int`` (:meth:`TexelLedLoop.concat`).
    """
    t = dr.arange(mi.UInt32, m)  # texel index
    # The texel count as a kernel input, not a literal: a fit's views and a culled frame each have their own count,
    # and a literal would compile (and keep in memory) one LED-loop kernel per count.
    stride = dr.opaque(mi.UInt32, m)
    grid = isinstance(roughness, tuple)
    # per-texel terms hoisted out of the loop, one material per roughness
    # roughness None: a Lambertian surface (the set, as the light after the first bounce leaves it)
    prepared = [brdf.PreparedBRDF(mi.Color3f(1.0), r, wi) for r in (roughness if grid else (roughness,))] if roughness is not None else []
    materials = [material] if material is not None else (prepared or [brdf.PreparedLambert(wi)])
    material = materials[0]
    diffuse = mi.Color3f(0.0)  # Σ diffuse part per unit albedo (the model is linear in albedo)
    specs = [mi.Color3f(0.0) for _ in materials]  # Σ specular part, per roughness
    dspec = mi.Color3f(0.0)  # Σ ∂ specular / ∂ roughness (stays 0 unless asked for)
    n_words = mi.UInt32(words)
    # Texels the camera sees from below their horizon reflect nothing toward it (the BRDF is zero there): they skip the
    # loop, exactly (about half of them on a body).
    w = dr.select(material.front, mi.UInt32(0), n_words)  # current visibility word
    bits = dr.select(material.front, dr.gather(mi.UInt32, visibility, t), 0)
    while w < n_words:
        if bits == 0:
            w += 1
            bits = dr.gather(mi.UInt32, visibility, w * stride + t, w < n_words)
        else:
            led = w * 32 + dr.tzcnt(bits)
            if dr.hint(led_base is not None, mode="scalar"):
                led += led_base
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
            specs = [specs[0] + s_part * weight] + [specs[k] + materials[k].eval_parts(wo)[1] * weight for k in range(1, len(specs))]
    spec = tuple(specs) if grid else specs[0]
    return (diffuse, spec, dspec) if roughness_derivative else (diffuse, spec)
