"""The paper's simplified Cook–Torrance BRDF (Sec. 3.1), written once for every renderer in gra-mi.

    f(ωi, ωo) = a / π · T(ωi) T(ωo)  +  D(h) G(ωi, ωo) F(ωi·h) / (4 cosθi cosθo),
    T(ω) = (1 − F(cosθ)) / (1 − F0)

- D: GGX / Trowbridge–Reitz with α = r² (r the per-texel "roughness" in [0, 1], perceptual as in Disney/UE4);
- G: Smith masking-shadowing in its *separable* (uncorrelated) form G = G1(ωi) G1(ωo) with the exact GGX
  G1(ω) = 2 / (1 + sqrt(1 + α² tan²θ)), as Mitsuba's own microfacet BSDFs use;
- F: Schlick with F0 = 0.04 (dielectric skin and cloth), F = F0 + (1 − F0)(1 − cos)^5;
- T: the light the specular interface lets through to the diffuse layer, on the way in and out (Shirley et al.
  1997 style coupling). T = 1 at normal incidence, so ``a`` is the diffuse albedo seen head-on; toward grazing
  angles the diffuse part yields to the specular one, which keeps the BRDF energy conserving (white furnace ≤ 1
  at every roughness and angle, tests/test_brdf.py) where a plain sum would reflect up to ~1.4× the light.

Float32 at grazing angles (docs/accuracy.md, "The BRDF"): every term is written so that no cosine is divided by and
no clamp is needed. With s(c) = sqrt(α² + (1 − α²) c²), G1(c) = 2c / (c + s(c)), so the specular term is

    f_spec cosθo = D F cosθo / ((cosθi + s_i)(cosθo + s_o)),     pdf_spec = D / (2 (cosθi + s_i)),

both finite as either cosine → 0 (c + s ≥ α), symmetric in (ωi, ωo), and sharing one D(h). The Fresnel cosine
ωi·h = ωo·h = |ωi + ωo| / 2 is taken from the same sum: never negative, the same in eval, pdf and sample.

Texel values outside the model (NaN, ±Inf, < 0, > 1) are defined per lane, never spread: albedo non-finite → 0,
roughness non-finite → 1, both clamped to [0, 1] (:func:`sanitize_albedo`, :func:`sanitize_roughness`). gra-mi's
own map loaders refuse such files; the plugin warns when a scene's texture holds them.

Directions are in the local shading frame (z = normal). α is clamped below at :data:`ALPHA_MIN` so that
roughness exactly 0 stays finite. Functions take Dr.Jit arrays (Mitsuba types) and are pure, so the BSDF plugin,
the image-space integrator and the UV-space texel shader share them and their derivatives.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

F0 = 0.04
ALPHA_MIN = 1e-3  # roughness 0 → α = 1e-3: a very sharp but finite GGX lobe (a delta would be invisible to point lights)


def sanitize_albedo(albedo):
    """Albedo as the model reads it: non-finite → 0, then clamped to [0, 1] (per channel, per lane)."""
    return dr.select(dr.isfinite(albedo), dr.clip(albedo, 0.0, 1.0), 0.0)


def sanitize_roughness(roughness):
    """Roughness as the model reads it: non-finite → 1 (the lobe that cannot make fireflies), clamped to [0, 1]."""
    return dr.select(dr.isfinite(roughness), dr.clip(roughness, 0.0, 1.0), 1.0)


def alpha_from_roughness(roughness):
    return dr.maximum(dr.square(roughness), ALPHA_MIN)


def ggx_d(h, alpha):
    """GGX normal distribution D(h) for a half vector h in the local frame (any length; 0 for h = 0 or h_z ≤ 0).

    Written as α² / (π q²) with q = (α² h_z² + h_x² + h_y²) / |h|², from the tangential components as Mitsuba's
    microfacet code does: the textbook denominator cos²θh (α² − 1) + 1 cancels in float32 near the peak. q ≥ α² for
    every direction, so the clamp below is exact in real arithmetic; it keeps q² far from float32's underflow (and
    h = 0 finite), where 1/q² and its derivative would otherwise become inf at grazing mirror pairs.
    """
    a2 = dr.square(alpha)
    q = _ggx_q(h, a2)
    return dr.select(h.z > 0, a2 / (dr.pi * dr.square(q)), 0.0)


def _ggx_q(h, a2):
    """(α² h_z² + h_x² + h_y²) / |h|², at least α² (its exact minimum, at h = +z)."""
    len2 = dr.maximum(dr.squared_norm(h), 1e-37)
    return dr.maximum((a2 * dr.square(h.z) + (dr.square(h.x) + dr.square(h.y))) / len2, a2)


def _g1_denominator(cos_theta, a2):
    """c + sqrt(α² + (1 − α²) c²): G1 = 2c / this. At least α, so its reciprocal never overflows."""
    return cos_theta + dr.sqrt(a2 + (1.0 - a2) * dr.square(cos_theta))


def smith_g1(cos_theta, alpha):
    """Smith masking for GGX, 2 / (1 + sqrt(1 + α² tan²θ)) = 2c / (c + sqrt(α² + (1 − α²) c²)): no tan, no clamp."""
    c = dr.maximum(cos_theta, 0.0)
    return dr.select(cos_theta > 0, 2.0 * c * dr.rcp(_g1_denominator(c, dr.square(alpha))), 0.0)


def fresnel_schlick(cos_d):
    x = dr.clip(1.0 - cos_d, 0.0, 1.0)
    x2 = dr.square(x)
    return F0 + (1.0 - F0) * (dr.square(x2) * x)  # x⁵ by multiplication: dr.power would go through exp/log


def diffuse_transmission(cos_theta):
    """T(ω) = (1 − F(cosθ)) / (1 − F0) = 1 − (1 − c)⁵: 1 head-on, 0 at grazing.

    Written as c (1 + x + x² + x³ + x⁴) with x = 1 − c: the subtraction 1 − F cancels in float32 near grazing angles
    (F → 1), where it erred by up to 60 % at c = 1e-7; the factored form is exact to a few ulps at every angle."""
    c = dr.clip(cos_theta, 0.0, 1.0)
    x = 1.0 - c
    return c * (1.0 + x * (1.0 + x * (1.0 + x * (1.0 + x))))


def half_vector_terms(wi, wo):
    """(h = ωi + ωo unnormalised, the Fresnel cosine ωi·ĥ = ωo·ĥ = |h| / 2): one h for eval, pdf and sample.

    |h| / 2 equals ωi·ĥ for unit vectors but is never negative: the float32 dot product of two nearly opposite
    unit vectors is dominated by their rounding and can come out ≤ 0, which dropped the lobe from the pdf only."""
    h = wi + wo
    return h, dr.minimum(0.5 * dr.norm(h), 1.0)


class PreparedBRDF:
    """The BRDF at fixed (albedo, roughness, ωi), with everything that does not depend on ωo computed once.

    Loops over many light directions (the LED sums) call :meth:`eval_parts` or :meth:`eval_cos` per direction.
    """

    def __init__(self, albedo, roughness, wi):
        roughness = sanitize_roughness(roughness)
        self.wi = wi
        self.alpha = alpha_from_roughness(roughness)
        self.alpha2 = dr.square(self.alpha)
        cos_i = dr.maximum(wi.z, 0.0)
        # G1(ωi) / (4 cosθi) = 1 / (2 (cosθi + s_i)): the cosine cancels exactly, finite at grazing incidence.
        self.spec_scale = 0.5 * dr.rcp(_g1_denominator(cos_i, self.alpha2))
        self.diffuse_unit = dr.inv_pi * diffuse_transmission(wi.z)
        self.albedo = sanitize_albedo(albedo)
        self.front = wi.z > 0
        # dα/dr (0 where the clamp at ALPHA_MIN holds) and ∂ ln G1(ωi) / ∂α, for roughness derivatives.
        self.dalpha_dr = dr.select(dr.square(roughness) > ALPHA_MIN, 2.0 * roughness, 0.0)
        self.dlog_g1_i = self._dlog_g1(cos_i)

    def _dlog_g1(self, cos_theta):
        """∂ ln G1 / ∂α for G1 = 2c / (c + s), s = sqrt(α² + (1 − α²) c²): −α (1 − c²) / (s (c + s))."""
        s = dr.sqrt(self.alpha2 + (1.0 - self.alpha2) * dr.square(cos_theta))
        return -self.alpha * (1.0 - dr.square(cos_theta)) * dr.rcp(s * (cos_theta + s))

    def eval_parts(self, wo, roughness_derivative: bool = False):
        """(diffuse per unit albedo, specular), both times cosθo: f cos = albedo ⊙ first + second.

        The model is linear in albedo; fitting uses the two parts separately. With ``roughness_derivative``, a
        third value: ∂ specular / ∂ roughness, analytic (material fitting differentiates the LED sums with it;
        Dr.Jit's AD cannot go through their per-lane loops).
        """
        cos_o = dr.maximum(wo.z, 0.0)
        h, cos_d = half_vector_terms(self.wi, wo)
        q = _ggx_q(h, self.alpha2)  # shared with the roughness derivative below (the fit's per-LED loop)
        d = dr.select(h.z > 0, self.alpha2 / (dr.pi * dr.square(q)), 0.0)
        # f_spec cosθo = D F G1(ωi) G1(ωo) / (4 cosθi) = D F · spec_scale · 2 cosθo / (cosθo + s_o): no cosine divides.
        spec = d * fresnel_schlick(cos_d) * cos_o * (2.0 * self.spec_scale) * dr.rcp(_g1_denominator(cos_o, self.alpha2))
        valid = self.front & (wo.z > 0)
        diffuse = self.diffuse_unit * (diffuse_transmission(cos_o) * cos_o)
        diffuse, spec = dr.select(valid, diffuse, 0.0), dr.select(valid, spec, 0.0)
        if not roughness_derivative:
            return diffuse, spec
        # ∂ ln D / ∂α for D = α² / (π q²), q = α² ĥ_z² + ĥ_x² + ĥ_y²: 2/α − 4 α ĥ_z² / q.
        hz2 = dr.square(h.z) * dr.rcp(dr.maximum(dr.squared_norm(h), 1e-37))
        dlog_d = 2.0 * dr.rcp(self.alpha) - 4.0 * self.alpha * hz2 * dr.rcp(q)
        dlog_spec = dlog_d + self._dlog_g1(cos_o) + self.dlog_g1_i
        return diffuse, spec, spec * dlog_spec * self.dalpha_dr

    def eval_cos(self, wo):
        """f(ωi, ωo) · cosθo."""
        diffuse, spec = self.eval_parts(wo)
        return self.albedo * diffuse + spec


class PreparedLambert:
    """A Lambertian surface with :class:`PreparedBRDF`'s interface, seen along its normal: the set's floor or wall as
    the light after the first bounce leaves it (:mod:`gra_mi.render.bounce`). ``eval_parts`` gives (cosθo / π, 0)."""

    def __init__(self, wi):
        self.front = wi.z > 0

    def eval_parts(self, wo):
        diffuse = dr.select(self.front & (wo.z > 0), wo.z * dr.inv_pi, 0.0)
        return mi.Color3f(diffuse), mi.Color3f(0.0)


def eval_cos(albedo, roughness, wi, wo):
    """f(ωi, ωo) · cosθo: what Mitsuba's ``BSDF.eval`` returns. ``albedo`` is RGB, ``roughness`` scalar."""
    return PreparedBRDF(albedo, roughness, wi).eval_cos(wo)


# --------------------------------------------------------------------------------------------------------------
# Sampling: a mixture of cosine-weighted diffuse and GGX visible normals (Heitz 2018)
# --------------------------------------------------------------------------------------------------------------


def specular_probability(albedo):
    """Probability of sampling the specular lobe: its share of the normal-incidence reflectance."""
    diffuse = dr.mean(sanitize_albedo(albedo)) * (1.0 - F0)
    return F0 / (F0 + diffuse + 1e-6) * 0.9 + 0.05  # never 0 or 1: both lobes stay sampled


def sample_visible_normal(wi, alpha, sample: mi.Point2f):
    """A GGX microfacet normal sampled proportionally to its visible projected area from wi (Heitz 2018)."""
    v = dr.normalize(mi.Vector3f(alpha * wi.x, alpha * wi.y, wi.z))
    length2 = dr.square(v.x) + dr.square(v.y)
    t1 = dr.select(length2 > 0, mi.Vector3f(-v.y, v.x, 0.0) * dr.rsqrt(dr.maximum(length2, 1e-20)), mi.Vector3f(1.0, 0.0, 0.0))
    t2 = dr.cross(v, t1)
    r = dr.sqrt(sample.x)
    phi = 2.0 * dr.pi * sample.y
    p1 = r * dr.cos(phi)
    p2 = r * dr.sin(phi)
    s = 0.5 * (1.0 + v.z)
    p2 = (1.0 - s) * dr.sqrt(dr.maximum(1.0 - dr.square(p1), 0.0)) + s * p2
    nh = t1 * p1 + t2 * p2 + v * dr.sqrt(dr.maximum(1.0 - dr.square(p1) - dr.square(p2), 0.0))
    return dr.normalize(mi.Vector3f(alpha * nh.x, alpha * nh.y, dr.maximum(nh.z, 1e-7)))


def pdf(albedo, roughness, wi, wo):
    """Density (solid angle) of :func:`sample` producing wo.

    Visible normals: G1(ωi) (ωi·h) D(h) / cosθi, times the reflection Jacobian 1 / (4 ωo·h); with ωi·h = ωo·h that
    is G1(ωi) D(h) / (4 cosθi) = D(h) / (2 (cosθi + s_i)), the same D(h) as :meth:`PreparedBRDF.eval_parts`.
    """
    alpha = alpha_from_roughness(sanitize_roughness(roughness))
    p_spec = specular_probability(albedo)
    h, _ = half_vector_terms(wi, wo)
    cos_i = dr.maximum(wi.z, 0.0)
    spec = ggx_d(h, alpha) * 0.5 * dr.rcp(_g1_denominator(cos_i, dr.square(alpha)))
    diff = dr.maximum(wo.z, 0.0) * dr.inv_pi
    valid = (wi.z > 0) & (wo.z > 0)
    return dr.select(valid, p_spec * spec + (1.0 - p_spec) * diff, 0.0)


def sample(albedo, roughness, wi, sample1, sample2: mi.Point2f):
    """Sample wo; returns (wo, pdf)."""
    alpha = alpha_from_roughness(sanitize_roughness(roughness))
    p_spec = specular_probability(albedo)
    choose_spec = sample1 < p_spec
    h = sample_visible_normal(wi, alpha, sample2)
    wo_spec = mi.reflect(wi, h)
    wo_diff = mi.warp.square_to_cosine_hemisphere(sample2)
    wo = dr.select(choose_spec, wo_spec, wo_diff)
    return wo, pdf(albedo, roughness, wi, wo)
