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

Directions are in the local shading frame (z = normal). α is clamped below at :data:`ALPHA_MIN` so that
roughness exactly 0 stays finite (docs/accuracy.md). Functions take Dr.Jit arrays (Mitsuba types) and are pure, so
the BSDF plugin, the image-space integrator and the UV-space texel shader share them and their derivatives.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

F0 = 0.04
ALPHA_MIN = 1e-3  # roughness 0 → α = 1e-3: a very sharp but finite GGX lobe (a delta would be invisible to point lights)


def alpha_from_roughness(roughness):
    return dr.maximum(dr.square(roughness), ALPHA_MIN)


def ggx_d(h, alpha):
    """GGX normal distribution D(h) for a half vector h in the local frame (any length > 0).

    Written as α² |h|⁴ / (π (α² h_z² + h_x² + h_y²)²), i.e. from the tangential components, as Mitsuba's microfacet
    code does: the textbook denominator cos²θh (α² − 1) + 1 cancels in float32 near the peak (at α = 1e-3 it erred
    by up to 75 % within 3α of the normal); here every term is positive, so float32 stays exact to a few ulps.
    """
    a2 = dr.square(alpha)
    len2 = dr.squared_norm(h)
    denom = a2 * dr.square(h.z) + (dr.square(h.x) + dr.square(h.y))
    return dr.select(h.z > 0, a2 * dr.square(len2) * dr.inv_pi * dr.rcp(dr.square(dr.maximum(denom, 1e-18))), 0.0)


def smith_g1(cos_theta, alpha):
    """Smith masking for GGX: 2 / (1 + sqrt(1 + α² tan²θ)), written without tan to stay finite at grazing angles."""
    c2 = dr.square(cos_theta)
    tan2 = dr.maximum(1.0 - c2, 0.0) / dr.maximum(c2, 1e-12)
    return dr.select(cos_theta > 0, 2.0 / (1.0 + dr.sqrt(1.0 + dr.square(alpha) * tan2)), 0.0)


def fresnel_schlick(cos_d):
    x = dr.maximum(1.0 - cos_d, 0.0)
    x2 = dr.square(x)
    return F0 + (1.0 - F0) * (dr.square(x2) * x)  # x⁵ by multiplication: dr.power would go through exp/log


def diffuse_transmission(cos_theta):
    """T(ω) = (1 − F(cosθ)) / (1 − F0): 1 head-on, 0 at grazing."""
    return (1.0 - fresnel_schlick(dr.maximum(cos_theta, 0.0))) / (1.0 - F0)


class PreparedBRDF:
    """The BRDF at fixed (albedo, roughness, ωi), with everything that does not depend on ωo computed once.

    Loops over many light directions (the LED sums) call :meth:`eval_parts` or :meth:`eval_cos` per direction.
    """

    def __init__(self, albedo, roughness, wi):
        self.wi = wi
        self.alpha = alpha_from_roughness(roughness)
        self.alpha2 = dr.square(self.alpha)
        # G1(ωi) / (4 cosθi): with f_spec cosθo = D F G1(ωo) · G1(ωi) / (4 cosθi), the cosθo cancels.
        self.spec_scale = smith_g1(wi.z, self.alpha) / (4.0 * dr.maximum(wi.z, 1e-12))
        self.diffuse_unit = dr.inv_pi * diffuse_transmission(wi.z)
        self.albedo = albedo
        self.front = wi.z > 0
        # dα/dr (0 where the clamp at ALPHA_MIN holds) and ∂ ln G1(ωi) / ∂α, for roughness derivatives.
        self.dalpha_dr = dr.select(dr.square(roughness) > ALPHA_MIN, 2.0 * roughness, 0.0)
        self.dlog_g1_i = self._dlog_g1(wi.z)

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
        cos_o = wo.z
        h_raw = self.wi + wo  # unnormalised: ggx_d needs only its direction, exactly
        d = ggx_d(h_raw, self.alpha)
        h = h_raw * dr.rsqrt(dr.squared_norm(h_raw))
        # Smith G1 written as 2 cos / (cos + sqrt(α² + (1 − α²) cos²)): no tan, finite at grazing angles.
        g1_o = 2.0 * cos_o * dr.rcp(cos_o + dr.sqrt(self.alpha2 + (1.0 - self.alpha2) * dr.square(cos_o)))
        spec = dr.select(h.z > 0, d * fresnel_schlick(dr.dot(self.wi, h)) * g1_o * self.spec_scale, 0.0)
        valid = self.front & (cos_o > 0)
        diffuse = self.diffuse_unit * (diffuse_transmission(cos_o) * cos_o)
        diffuse, spec = dr.select(valid, diffuse, 0.0), dr.select(valid, spec, 0.0)
        if not roughness_derivative:
            return diffuse, spec
        # ∂ ln D / ∂α for D = α² |h|⁴ / (π q²), q = α² h_z² + h_x² + h_y²: 2/α − 4 α h_z² / q (h unnormalised).
        hz2 = dr.square(h_raw.z)
        q = self.alpha2 * hz2 + dr.square(h_raw.x) + dr.square(h_raw.y)
        dlog_d = 2.0 * dr.rcp(self.alpha) - 4.0 * self.alpha * hz2 * dr.rcp(dr.maximum(q, 1e-18))
        dlog_spec = dlog_d + self._dlog_g1(cos_o) + self.dlog_g1_i
        return diffuse, spec, spec * dlog_spec * self.dalpha_dr

    def eval_cos(self, wo):
        """f(ωi, ωo) · cosθo."""
        diffuse, spec = self.eval_parts(wo)
        return self.albedo * diffuse + spec


def eval_cos(albedo, roughness, wi, wo):
    """f(ωi, ωo) · cosθo: what Mitsuba's ``BSDF.eval`` returns. ``albedo`` is RGB, ``roughness`` scalar."""
    return PreparedBRDF(albedo, roughness, wi).eval_cos(wo)


# --------------------------------------------------------------------------------------------------------------
# Sampling: a mixture of cosine-weighted diffuse and GGX visible normals (Heitz 2018)
# --------------------------------------------------------------------------------------------------------------


def specular_probability(albedo):
    """Probability of sampling the specular lobe: its share of the normal-incidence reflectance."""
    diffuse = dr.mean(albedo) * (1.0 - F0)
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
    """Density (solid angle) of :func:`sample` producing wo."""
    alpha = alpha_from_roughness(roughness)
    p_spec = specular_probability(albedo)
    h = dr.normalize(wi + wo)
    # Visible-normal density: G1(wi) max(0, wi·h) D(h) / cosθi, then the reflection Jacobian 1 / (4 wo·h).
    d_visible = smith_g1(wi.z, alpha) * dr.maximum(dr.dot(wi, h), 0.0) * ggx_d(h, alpha) / dr.maximum(wi.z, 1e-12)
    spec = d_visible / (4.0 * dr.maximum(dr.dot(wo, h), 1e-12))
    diff = dr.maximum(wo.z, 0.0) * dr.inv_pi
    valid = (wi.z > 0) & (wo.z > 0)
    return dr.select(valid, p_spec * spec + (1.0 - p_spec) * diff, 0.0)


def sample(albedo, roughness, wi, sample1, sample2: mi.Point2f):
    """Sample wo; returns (wo, pdf)."""
    alpha = alpha_from_roughness(roughness)
    p_spec = specular_probability(albedo)
    choose_spec = sample1 < p_spec
    h = sample_visible_normal(wi, alpha, sample2)
    wo_spec = mi.reflect(wi, h)
    wo_diff = mi.warp.square_to_cosine_hemisphere(sample2)
    wo = dr.select(choose_spec, wo_spec, wo_diff)
    return wo, pdf(albedo, roughness, wi, wo)
