"""gra_microfacet: against a float64 NumPy reference, Mitsuba's own GGX, reciprocity, chi², and hard cases."""

from __future__ import annotations

import numpy as np
import pytest

F0 = 0.04


# ---------------------------------------------------------------------------------------------------------------
# Independent float64 reference (written from the formulas in the docs, not from gra_mi.brdf)
# ---------------------------------------------------------------------------------------------------------------


def ref_eval_cos(albedo, roughness, wi, wo):
    alpha = np.maximum(roughness**2, 1e-3)
    ci, co = wi[:, 2], wo[:, 2]
    h = wi + wo
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    ch = h[:, 2]
    a2 = alpha**2
    d = np.where(ch > 0, a2 / (np.pi * (ch**2 * (a2 - 1) + 1) ** 2), 0.0)

    def g1(c):
        tan2 = (1 - c**2) / c**2
        return np.where(c > 0, 2 / (1 + np.sqrt(1 + a2 * tan2)), 0.0)

    def fresnel(c):
        return F0 + (1 - F0) * (1 - c) ** 5

    spec = d * g1(ci) * g1(co) * fresnel(np.sum(wi * h, axis=1)) / (4 * ci * co)
    transmission = (1 - fresnel(np.clip(ci, 0, 1))) * (1 - fresnel(np.clip(co, 0, 1))) / (1 - F0) ** 2
    value = albedo / np.pi * transmission[:, None] + spec[:, None]
    return np.where(((ci > 0) & (co > 0))[:, None], value * co[:, None], 0.0)


def random_dirs(rng, n, upper=True):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    if upper:
        d[:, 2] = np.abs(d[:, 2]) + 1e-3
        d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d


def plugin_eval(albedo, roughness, wi, wo):
    """Evaluate the registered plugin through Mitsuba (float32) with constant textures per call."""
    import drjit as dr
    import mitsuba as mi

    out = np.zeros((len(wi), 3))
    for r in np.unique(roughness):
        sel = roughness == r
        bsdf = mi.load_dict({"type": "gra_microfacet", "albedo": {"type": "rgb", "value": albedo.tolist()}, "roughness": float(r)})
        si = dr.zeros(mi.SurfaceInteraction3f, int(sel.sum()))
        si.wi = mi.Vector3f(*wi[sel].T.astype(np.float32))
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo[sel].T.astype(np.float32)))
        out[sel] = np.array(value).T
    return out


def test_shared_formula_matches_float64_reference(plugins):
    # The same Dr.Jit code the plugin and the texel shader run, evaluated in double precision.
    import drjit as dr

    from gra_mi.render import brdf

    Array3f64 = dr.llvm.ad.Array3f64  # noqa: N806
    rng = np.random.default_rng(0)
    n = 5000
    wi, wo = random_dirs(rng, n), random_dirs(rng, n)
    albedo = rng.uniform(0, 1, size=(n, 3))
    rough = rng.uniform(0, 1, size=n)
    ours = np.array(brdf.eval_cos(Array3f64(*albedo.T), dr.llvm.ad.Float64(rough), Array3f64(*wi.T), Array3f64(*wo.T))).T
    ref = ref_eval_cos(albedo, rough, wi, wo)
    finite = np.isfinite(ref)
    rel = np.abs(ours - ref)[finite] / np.maximum(np.abs(ref[finite]), 1e-30)
    assert rel.max() <= 1e-5


@pytest.mark.parametrize("roughness", [0.05, 0.3, 0.7, 1.0])
def test_plugin_eval_matches_reference(plugins, roughness):
    rng = np.random.default_rng(1)
    n = 2000
    wi, wo = random_dirs(rng, n), random_dirs(rng, n)
    albedo = np.array([0.6, 0.4, 0.2])
    rough = np.full(n, roughness)
    ours = plugin_eval(albedo, rough, wi, wo)
    ref = ref_eval_cos(np.tile(albedo, (n, 1)), rough, wi, wo)
    # float32 evaluation: relative error ≤ 1e-5 where the lobe is well conditioned, 1e-3 for sharp lobes.
    tol = 1e-5 if roughness >= 0.3 else 1e-3
    well = (wi[:, 2] > 0.05) & (wo[:, 2] > 0.05)
    rel = np.abs(ours - ref)[well] / np.maximum(np.abs(ref[well]), 1e-12)
    assert np.median(rel) < 1e-6 and rel.max() < max(tol, 5e-5)


def near_peak_directions(rng, alpha, n):
    """float32 (wi, wo) pairs whose half vector lies within 3α of the normal (the lobe's peak), both above 0.05."""
    wi = random_dirs(rng, 4 * n)
    wi = wi[wi[:, 2] > 0.1]
    theta = rng.uniform(0, 3 * alpha, len(wi))
    phi = rng.uniform(0, 2 * np.pi, len(wi))
    h = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], axis=1)
    wo = 2 * np.sum(wi * h, axis=1, keepdims=True) * h - wi
    keep = wo[:, 2] > 0.05
    wi, wo = wi[keep][:n].astype(np.float32), wo[keep][:n].astype(np.float32)
    return wi.astype(np.float64), wo.astype(np.float64)  # the reference sees exactly the float32 directions


@pytest.mark.parametrize("roughness", [0.0, 0.01, 0.03, 0.05, 0.1, 0.2, 0.4, 0.7, 1.0])
def test_near_peak_float32_matches_float64(plugins, roughness):
    # Near the GGX peak the textbook denominator cos²θh (α² − 1) + 1 cancels in float32 (it erred by up to 75 % at
    # roughness 0). The plugin and the texel shader's per-LED term must stay within 1e-4 of float64 there.
    import mitsuba as mi

    from gra_mi.render import brdf

    rng = np.random.default_rng(int(roughness * 1000) + 7)
    alpha = max(roughness**2, 1e-3)
    wi, wo = near_peak_directions(rng, alpha, 2000)
    albedo = np.array([0.6, 0.4, 0.2])
    ref = ref_eval_cos(np.tile(albedo, (len(wi), 1)), np.full(len(wi), roughness), wi, wo)
    ours = plugin_eval(albedo, np.full(len(wi), roughness), wi, wo)
    assert np.max(np.abs(ours - ref) / np.abs(ref)) <= 1e-4
    # The UV-space shader's loop body: diffuse and specular parts, float32.
    diffuse, spec = brdf.PreparedBRDF(
        mi.Color3f(1.0), mi.Float(np.full(len(wi), roughness, np.float32)), mi.Vector3f(*wi.T.astype(np.float32))
    ).eval_parts(mi.Vector3f(*wo.T.astype(np.float32)))
    ref_spec = ref_eval_cos(np.zeros((len(wi), 3)), np.full(len(wi), roughness), wi, wo)[:, 0]
    ref_diffuse = ref_eval_cos(np.ones((len(wi), 3)), np.full(len(wi), roughness), wi, wo)[:, 0] - ref_spec
    assert np.max(np.abs(np.array(spec).ravel() - ref_spec) / ref_spec) <= 1e-4
    assert np.max(np.abs(np.array(diffuse).ravel() - ref_diffuse) / ref_diffuse) <= 1e-4


def test_roughness_derivative_matches_finite_differences(plugins):
    # The material fit differentiates the LED sums with this analytic ∂ specular / ∂ roughness (float64 here).
    import drjit as dr

    from gra_mi.render import brdf

    Array3f64, Float64 = dr.llvm.ad.Array3f64, dr.llvm.ad.Float64  # noqa: N806
    rng = np.random.default_rng(4)
    n = 4000
    wi, wo = random_dirs(rng, n), random_dirs(rng, n)
    rough = rng.uniform(0.04, 1.0, n)
    h = 1e-6

    def spec(r):
        return np.array(brdf.PreparedBRDF(Array3f64(0, 0, 0), Float64(r), Array3f64(*wi.T)).eval_parts(Array3f64(*wo.T))[1])

    _, value, derivative = brdf.PreparedBRDF(Array3f64(0, 0, 0), Float64(rough), Array3f64(*wi.T)).eval_parts(
        Array3f64(*wo.T), roughness_derivative=True
    )
    fd = (spec(rough + h) - spec(rough - h)) / (2 * h)
    derivative = np.array(derivative)
    scale = np.maximum(np.abs(fd), 1e-6 * np.abs(np.array(value)) + 1e-12)
    assert np.max(np.abs(derivative - fd) / scale) < 1e-4
    # Below the α clamp (r² < ALPHA_MIN) roughness does not change the lobe: the derivative is 0.
    _, _, clamped = brdf.PreparedBRDF(Array3f64(0, 0, 0), Float64(np.full(n, 0.02)), Array3f64(*wi.T)).eval_parts(
        Array3f64(*wo.T), roughness_derivative=True
    )
    assert np.all(np.array(clamped) == 0)


def test_ggx_terms_match_mitsuba_microfacet(plugins):
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render import brdf

    rng = np.random.default_rng(2)
    m = random_dirs(rng, 1000)
    v = random_dirs(rng, 1000)
    for alpha in (0.05, 0.3, 0.9):
        theirs = mi.MicrofacetDistribution(mi.MicrofacetType.GGX, alpha, alpha, True)
        mm, vv = mi.Vector3f(*m.T.astype(np.float32)), mi.Vector3f(*v.T.astype(np.float32))
        np.testing.assert_allclose(np.array(brdf.ggx_d(mm, mi.Float(alpha))), np.array(theirs.eval(mm)), rtol=2e-4)
        # Mitsuba's G1 also zeroes back-facing microfacets (v·m ≤ 0), which never occur for our half vectors.
        front = np.sum(v * m, axis=1) > 0
        np.testing.assert_allclose(
            np.array(brdf.smith_g1(vv.z, mi.Float(alpha)))[front], np.array(theirs.smith_g1(vv, mm))[front], rtol=2e-4, atol=1e-6
        )
        dr.eval()


def test_reciprocity(plugins):
    rng = np.random.default_rng(3)
    n = 1000
    wi, wo = random_dirs(rng, n), random_dirs(rng, n)
    albedo = np.array([0.5, 0.5, 0.5])
    for r in (0.1, 0.5, 1.0):
        a = plugin_eval(albedo, np.full(n, r), wi, wo) / wo[:, 2:3]
        b = plugin_eval(albedo, np.full(n, r), wo, wi) / wi[:, 2:3]
        np.testing.assert_allclose(a, b, rtol=2e-4)


@pytest.mark.parametrize("roughness", [0.35, 0.6, 1.0])  # α ≥ 0.12: sharper lobes defeat the χ² grid integration
@pytest.mark.parametrize("cos_wi", [0.95, 0.3])
def test_sample_pdf_chi2(plugins, roughness, cos_wi):
    import mitsuba.chi2 as chi2

    wi = [float(np.sqrt(1 - cos_wi**2)), 0.0, cos_wi]
    sample_func, pdf_func = chi2.BSDFAdapter(
        "gra_microfacet", f'<float name="roughness" value="{roughness}"/><rgb name="albedo" value="0.4, 0.5, 0.6"/>', wi=wi
    )
    test = chi2.ChiSquareTest(domain=chi2.SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func, sample_dim=3, sample_count=400_000)
    assert test.run(), test.messages


def test_no_nan_or_inf_on_hard_cases(plugins):
    rng = np.random.default_rng(4)
    n = 500
    grazing = random_dirs(rng, n)
    grazing[:, 2] = 1e-7
    grazing /= np.linalg.norm(grazing, axis=1, keepdims=True)
    below = random_dirs(rng, n)
    below[:, 2] *= -1
    normal = np.tile([0.0, 0.0, 1.0], (n, 1))
    cases = [
        (grazing, random_dirs(rng, n)),
        (random_dirs(rng, n), grazing),
        (below, random_dirs(rng, n)),
        (random_dirs(rng, n), below),
        (normal, normal),
        (grazing, grazing),
    ]
    for r in (0.0, 1e-6, 0.5, 1.0):
        for wi, wo in cases:
            value = plugin_eval(np.array([1.0, 1.0, 1.0]), np.full(n, r), wi, wo)
            assert np.isfinite(value).all() and value.min() >= 0
        # Back-facing: exactly zero.
        assert plugin_eval(np.array([1.0, 1.0, 1.0]), np.full(n, r), below, random_dirs(rng, n)).max() == 0


def test_white_furnace_bound(plugins):
    # Directional albedo ∫ f cos dωo ≤ 1 for albedo 1 at every roughness and angle (energy is not created).
    import drjit as dr
    import mitsuba as mi

    n = 200_000
    sampler_u = np.random.default_rng(5).random((n, 2))
    wo = mi.warp.square_to_uniform_hemisphere(mi.Point2f(*sampler_u.T.astype(np.float32)))
    for r in (0.0, 0.05, 0.2, 0.4, 0.7, 1.0):
        bsdf = mi.load_dict({"type": "gra_microfacet", "albedo": {"type": "rgb", "value": [1, 1, 1]}, "roughness": r})
        for theta in (0.0, 30.0, 60.0, 80.0, 89.0, 89.9):
            si = dr.zeros(mi.SurfaceInteraction3f, n)
            si.wi = mi.Vector3f(float(np.sin(np.radians(theta))), 0.0, float(np.cos(np.radians(theta))))
            si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
            value = np.array(bsdf.eval(mi.BSDFContext(), si, wo))[0]
            albedo = value.mean() * 2 * np.pi
            # Monte Carlo estimate: 3 standard errors of slack.
            slack = 3 * value.std() * 2 * np.pi / np.sqrt(n)
            assert albedo <= 1.0 + slack, (r, theta, albedo)
