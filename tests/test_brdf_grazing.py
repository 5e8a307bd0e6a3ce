"""gra_microfacet where path tracers and optimisers actually go: grazing angles down to cos θ = 1e-8, the mirror
direction of sharp lobes, automatic derivatives there, and texels holding NaN, Inf or out-of-range values.

Every check is against something gra_mi.brdf did not compute: Mitsuba's own χ² harness, the float64 reference of
tests/test_brdf.py (textbook GGX/Smith/Schlick), quadrature in float64, or central finite differences of it.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest

from .test_brdf import ref_eval_cos

ROUGHNESSES = (0.01, 0.05, 0.2, 0.5, 1.0)


def incident(cos_theta: float, azimuth: float) -> np.ndarray:
    """A unit ωi at the given cosine and azimuth (random azimuths: the x–z plane hides float32 cancellations)."""
    sin_theta = np.sqrt(max(1.0 - cos_theta**2, 0.0))
    return np.array([sin_theta * np.cos(azimuth), sin_theta * np.sin(azimuth), cos_theta])


def load_bsdf(albedo, roughness: float):
    import mitsuba as mi

    return mi.load_dict(
        {"type": "gra_microfacet", "albedo": {"type": "rgb", "value": list(map(float, albedo))}, "roughness": float(roughness)}
    )


def interaction(wi: np.ndarray, n: int):
    import drjit as dr
    import mitsuba as mi

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    wi = np.broadcast_to(np.asarray(wi, np.float32), (n, 3))
    si.wi = mi.Vector3f(*wi.T)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    return si


# ---------------------------------------------------------------------------------------------------------------
# A log-polar chart around the mirror direction (for χ² and quadrature)
# ---------------------------------------------------------------------------------------------------------------


class MirrorChart:
    """Directions as points of the unit disk: angle ψ from the mirror direction r of ωi, mapped to ρ = ln(1 + ψ/s) / L
    (L = ln(1 + π/s)), azimuth φ about r. Cells near r are s-sized: a lobe of width s spans many cells.
    The solid-angle Jacobian is dω/dA = sin ψ · s L e^(ρL) / ρ."""

    def __init__(self, wi: np.ndarray, scale: float):
        self.r = np.array([-wi[0], -wi[1], wi[2]], np.float64)
        helper = np.array([1.0, 0.0, 0.0]) if abs(self.r[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        self.t1 = np.cross(self.r, helper)
        self.t1 /= np.linalg.norm(self.t1)
        self.t2 = np.cross(self.r, self.t1)
        self.s, self.L = scale, np.log1p(np.pi / scale)

    def to_direction(self, rho, phi):
        """float64 directions and dω/dA for points (ρ, φ) of the disk."""
        psi = np.minimum(self.s * np.expm1(rho * self.L), np.pi)
        radial = np.cos(phi)[:, None] * self.t1 + np.sin(phi)[:, None] * self.t2
        d = np.cos(psi)[:, None] * self.r + np.sin(psi)[:, None] * radial
        jacobian = np.sin(psi) * self.s * self.L * np.exp(rho * self.L) / np.maximum(rho, 1e-30)
        return d, jacobian

    def to_disk(self, d):
        """float64 points of the disk for directions d (N, 3)."""
        along = d @ self.r
        x, y = d @ self.t1, d @ self.t2
        psi = np.arctan2(np.hypot(x, y), along)
        rho = np.log1p(psi / self.s) / self.L
        phi = np.arctan2(y, x)
        return rho * np.cos(phi), rho * np.sin(phi)


def chi2_around_mirror(albedo, roughness, cos_theta, azimuth, pdf_roughness=None, sample_count=1_000_000):
    """Mitsuba's χ² test of gra_microfacet's ``sample`` against its ``pdf`` (``pdf_roughness`` to mistune the pdf), on
    the mirror chart with s = α/2: the stock spherical grid cannot resolve lobes below roughness 0.2."""
    import drjit as dr
    import mitsuba as mi
    import mitsuba.chi2 as chi2

    alpha = max(roughness**2, 1e-3)
    wi = incident(cos_theta, azimuth)
    chart = MirrorChart(wi, alpha * cos_theta / 2)
    bsdf = load_bsdf(albedo, roughness)
    pdf_bsdf = bsdf if pdf_roughness is None else load_bsdf(albedo, pdf_roughness)

    def sample_func(u):
        n = dr.width(u)
        bs, weight = bsdf.sample(mi.BSDFContext(), interaction(wi, n), u[0], mi.Point2f(u[1], u[2]))
        keep = (np.array(dr.max(weight)) > 0).astype(np.float32)
        x, y = chart.to_disk(np.array(bs.wo, np.float64).T)
        return mi.Vector2f(x.astype(np.float32), y.astype(np.float32)), mi.Float(keep)

    def pdf_func(p):
        p = np.array(p, np.float64)
        rho, phi = np.hypot(p[0], p[1]), np.arctan2(p[1], p[0])
        d, jacobian = chart.to_direction(rho, phi)
        n = len(rho)
        density = np.array(pdf_bsdf.pdf(mi.BSDFContext(), interaction(wi, n), mi.Vector3f(*d.astype(np.float32).T)), np.float64)
        return mi.Float(np.where(rho < 1.0, density * jacobian, 0.0).astype(np.float32))

    test = chi2.ChiSquareTest(
        domain=chi2.PlanarDomain(), sample_func=sample_func, pdf_func=pdf_func, sample_dim=3, sample_count=sample_count, res=61, ires=12
    )
    return test


@pytest.mark.parametrize("roughness", ROUGHNESSES)
def test_chi2_around_the_mirror_direction(plugins, roughness):
    # Mitsuba's own χ² harness: sample() draws what pdf() says, for every albedo and incidence down to cos 0.01,
    # ωi at a random azimuth.
    rng = np.random.default_rng(int(roughness * 100))
    failures = []
    for albedo in (0.0, 0.5, 1.0):
        for cos_theta in (1.0, 0.5, 0.1, 0.01):
            test = chi2_around_mirror([albedo] * 3, roughness, cos_theta, rng.uniform(0, 2 * np.pi))
            if not test.run(quiet=True):
                failures.append((albedo, cos_theta, test.messages[-300:]))
    assert not failures, failures


@pytest.mark.parametrize("roughness", [0.05, 0.5])
def test_chi2_rejects_a_pdf_with_alpha_ten_percent_too_wide(plugins, roughness):
    # The negative control: the chart and the sample count resolve a 10 % error in α.
    test = chi2_around_mirror([0.0] * 3, roughness, 0.5, 1.1, pdf_roughness=roughness * np.sqrt(1.1))
    assert not test.run(quiet=True)


# ---------------------------------------------------------------------------------------------------------------
# Sample weights: the directional albedo, never above 1
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("roughness", [0.0, 0.01, 0.05, 0.1, 0.2, 0.5, 1.0])
def test_sample_weights_stay_bounded_at_grazing_incidence(plugins, roughness):
    # Weights estimate the directional albedo (≤ 1 for albedo 1); a path tracer's fireflies are their maximum.
    # Mixture sampling bounds each weight by 1 / min(p_spec, 1 − p_spec) = 20.
    import mitsuba as mi

    rng = np.random.default_rng(11)
    n = 200_000
    bsdf = load_bsdf([1.0, 1.0, 1.0], roughness)
    for cos_theta in (1e-1, 1e-2, 1e-3, 2e-4, 1e-4, 1e-5, 1e-6):
        azimuths = rng.uniform(0, 2 * np.pi, n)
        wi = np.stack([incident(cos_theta, a) for a in azimuths[:64]])[rng.integers(0, 64, n)]
        u = rng.random((n, 3)).astype(np.float32)
        bs, weight = bsdf.sample(mi.BSDFContext(), interaction(wi, n), mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
        w = np.array(weight, np.float64)[0]
        assert np.isfinite(w).all() and w.min() >= 0, (cos_theta, w.min())
        assert w.max() <= 20.0 * (1 + 1e-5), (cos_theta, w.max())
        assert w.mean() <= 1.0 + 3 * w.std() / np.sqrt(n), (cos_theta, w.mean())


# ---------------------------------------------------------------------------------------------------------------
# White furnace and reciprocity down to cos θ = 1e-8
# ---------------------------------------------------------------------------------------------------------------


def directional_albedo(roughness: float, cos_theta: float, azimuth: float, nodes: int = 500):
    """(ours in float32, the float64 reference) ∫ f cosθo dωo for albedo 1, by Gauss–Legendre quadrature on the mirror
    chart (s = α cosθi: the lobe's width in ωo at grazing incidence)."""
    import drjit as dr
    import mitsuba as mi

    wi = incident(cos_theta, azimuth)
    alpha = max(roughness**2, 1e-3)
    chart = MirrorChart(wi, alpha * max(cos_theta, 1e-12))
    x, w_rho = np.polynomial.legendre.leggauss(nodes)
    rho, w_rho = 0.5 * (x + 1), 0.5 * w_rho
    phi = (np.arange(2 * nodes) + 0.5) * np.pi / nodes
    rr, pp = np.meshgrid(rho, phi, indexing="ij")
    d, jacobian = chart.to_direction(rr.ravel(), pp.ravel())
    weight = (w_rho[:, None] * rr * (np.pi / nodes)).ravel() * jacobian  # dA = ρ dρ dφ
    up = d[:, 2] > 0
    d, weight = d[up], weight[up]
    wi_rep = np.broadcast_to(wi, d.shape)
    ref = ref_eval_cos(np.ones((len(d), 3)), np.full(len(d), roughness), wi_rep, d)[:, 0]
    bsdf = load_bsdf([1.0, 1.0, 1.0], roughness)
    ours = np.array(bsdf.eval(mi.BSDFContext(), interaction(wi, len(d)), mi.Vector3f(*d.astype(np.float32).T)), np.float64)[0]
    dr.eval()
    return float(np.sum(ours * weight)), float(np.sum(ref * weight))


@pytest.mark.parametrize("roughness", [0.0, 0.05, 0.2, 0.5, 1.0])
def test_white_furnace_down_to_cos_1e_8(plugins, roughness):
    # Albedo 1 reflects at most the light it receives, at every incidence; where float32 can still resolve the lobe
    # (cos ≥ 1e-3) ours and the float64 reference integrate to the same albedo.
    for cos_theta in (1.0, 0.3, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 5e-7, 1e-7, 1e-8):
        ours, ref = directional_albedo(roughness, cos_theta, 0.7)
        assert ref <= 1.0 + 1e-3, ("reference", cos_theta, ref)
        assert 0 <= ours <= 1.0 + 1e-3, (cos_theta, ours, ref)
        if cos_theta >= 1e-3:
            assert abs(ours - ref) <= 2e-3, (cos_theta, ours, ref)


def grazing_pairs(rng, n: int):
    """(ωi, ωo) float32-exact pairs with cosines log-uniform in [1e-8, 1] at random azimuths, a third of them mirror
    pairs (ωo = the mirror of ωi, exact in float32) and a third within a few degrees of it."""
    cos_i, cos_o = 10 ** rng.uniform(-8, 0, n), 10 ** rng.uniform(-8, 0, n)
    wi = np.stack([incident(c, a) for c, a in zip(cos_i, rng.uniform(0, 2 * np.pi, n), strict=True)])
    wo = np.stack([incident(c, a) for c, a in zip(cos_o, rng.uniform(0, 2 * np.pi, n), strict=True)])
    third = n // 3
    wo[:third] = wi[:third] * [-1, -1, 1]
    near = wi[third : 2 * third] * [-1, -1, 1] + rng.normal(0, 0.03, (third, 3))
    near[:, 2] = np.abs(near[:, 2])
    wo[third : 2 * third] = near / np.linalg.norm(near, axis=1, keepdims=True)
    wi, wo = wi.astype(np.float32), wo.astype(np.float32)
    wo[:third] = wi[:third] * np.float32([-1, -1, 1])
    return wi.astype(np.float64), wo.astype(np.float64)


def plugin_f(roughness: float, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """f(ωi, ωo) (not times the cosine) through the plugin, albedo 1."""
    import mitsuba as mi

    value = load_bsdf([1.0, 1.0, 1.0], roughness).eval(mi.BSDFContext(), interaction(wi, len(wi)), mi.Vector3f(*wo.astype(np.float32).T))
    return np.array(value, np.float64)[0] / wo[:, 2]


@pytest.mark.parametrize("roughness", [0.0, 0.01, 0.1, 0.5, 1.0])
def test_values_and_reciprocity_at_grazing_angles(plugins, roughness):
    rng = np.random.default_rng(int(roughness * 1000) + 3)
    wi, wo = grazing_pairs(rng, 3000)
    ours, ours_swapped = plugin_f(roughness, wi, wo), plugin_f(roughness, wo, wi)
    ones = np.ones((len(wi), 3))
    ref = ref_eval_cos(ones, np.full(len(wi), roughness), wi, wo)[:, 0] / wo[:, 2]
    # Reciprocity to 1e-5 on every pair. (The float64 reference itself, whose Fresnel takes ωi·ĥ from the float32
    # directions' dot product, is reciprocal only to ~2e-4 near grazing mirror pairs: the unit lengths' rounding.)
    assert np.max(np.abs(ours - ours_swapped) / np.maximum(np.abs(ours), 1e-30)) <= 1e-5
    # The values themselves: float32 resolves a half vector to ~1e-7 of |ωi + ωo|; where that is well inside the
    # lobe (|ωi + ωo| α ≫ 1e-7) ours matches float64 — the exact mirror pairs among them.
    resolved = np.linalg.norm(wi + wo, axis=1) * max(roughness**2, 1e-3) > 1e-4
    rel = np.abs(ours - ref)[resolved] / np.abs(ref[resolved])
    assert rel.max() <= 1e-3, (rel.max(), np.sum(resolved))
    mirror = np.zeros(len(wi), bool)
    mirror[: len(wi) // 3] = True
    assert np.all(np.abs(ours - ref)[mirror] <= 1e-3 * np.abs(ref[mirror])), "exact mirror pairs"


# ---------------------------------------------------------------------------------------------------------------
# Derivatives through Dr.Jit's AD: finite at the mirror at grazing, equal to finite differences elsewhere
# ---------------------------------------------------------------------------------------------------------------


def ad_roughness_gradient(roughness: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """d (f cosθo) / d roughness per lane, by dr.backward through gra_mi.brdf.eval_cos in float32."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render import brdf

    r = mi.Float(roughness.astype(np.float32))
    dr.enable_grad(r)
    value = brdf.eval_cos(mi.Color3f(0.5), r, mi.Vector3f(*wi.astype(np.float32).T), mi.Vector3f(*wo.astype(np.float32).T))
    dr.backward(dr.sum(value.x))
    return np.array(dr.grad(r), np.float64)


def test_autodiff_is_finite_at_the_grazing_mirror_direction(plugins):
    rng = np.random.default_rng(5)
    for roughness in (0.04, 0.05, 0.1, 0.2, 0.5):
        for cos_theta in (3e-3, 1e-4, 1e-5, 1e-6, 1e-8):
            wi = np.stack([incident(cos_theta, a) for a in rng.uniform(0, 2 * np.pi, 512)]).astype(np.float32)
            mirror = wi * np.float32([-1, -1, 1])
            near = mirror + rng.normal(0, roughness**2, mirror.shape).astype(np.float32)
            near[:, 2] = np.abs(near[:, 2])
            near /= np.linalg.norm(near, axis=1, keepdims=True)
            for wo in (mirror, near):
                grad = ad_roughness_gradient(np.full(len(wi), roughness), wi.astype(np.float64), wo.astype(np.float64))
                assert np.isfinite(grad).all(), (roughness, cos_theta, np.mean(~np.isfinite(grad)))


def test_autodiff_matches_central_differences_of_the_float64_reference(plugins):
    rng = np.random.default_rng(6)
    n = 3000
    wi = np.stack([incident(c, a) for c, a in zip(rng.uniform(0.05, 1, n), rng.uniform(0, 2 * np.pi, n), strict=True)])
    wo = np.stack([incident(c, a) for c, a in zip(rng.uniform(0.05, 1, n), rng.uniform(0, 2 * np.pi, n), strict=True)])
    wi, wo = wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)
    roughness = rng.uniform(0.1, 1.0, n)
    grad = ad_roughness_gradient(roughness, wi, wo)
    eps = 1e-6
    ones = np.full((n, 3), 0.5)
    fd = (ref_eval_cos(ones, roughness + eps, wi, wo)[:, 0] - ref_eval_cos(ones, roughness - eps, wi, wo)[:, 0]) / (2 * eps)
    value = ref_eval_cos(ones, roughness, wi, wo)[:, 0]
    assert np.max(np.abs(grad - fd) / np.maximum(np.abs(fd), 1e-3 * value)) <= 2e-3


def mirror_plane_scene(roughness: float, elevation_deg: float):
    """A gra_microfacet floor seen by an orthographic camera at the given elevation and lit by a directional light
    from its mirror direction: every pixel is an exact mirror pair."""
    import mitsuba as mi

    e = np.radians(elevation_deg)
    return mi.load_dict(
        {
            "type": "scene",
            "floor": {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(100),
                "bsdf": {"type": "gra_microfacet", "albedo": {"type": "rgb", "value": [0.5, 0.5, 0.5]}, "roughness": roughness},
            },
            "camera": {
                "type": "orthographic",
                "to_world": mi.ScalarTransform4f()
                .look_at(origin=[float(-4 * np.cos(e)), float(4 * np.sin(e)), 0.0], target=[0, 0, 0], up=[0, 1, 0])
                .scale([0.5, 0.5, 1]),
                "film": {"type": "hdrfilm", "width": 16, "height": 16},
            },
            "light": {
                "type": "directional",
                "direction": [float(-np.cos(e)), float(-np.sin(e)), 0.0],
                "irradiance": {"type": "rgb", "value": 1.0},
            },
        }
    )


@pytest.mark.parametrize("elevation", [0.0005, 0.005, 0.2, 30.0])
def test_render_backward_through_gra_onebounce_is_finite_and_matches_finite_differences(plugins, elevation):
    # Mitsuba's own optimisation loop (mi.render + dr.backward), which the README shows: a glossy plane seen at
    # grazing with the light at the mirror side returned −inf for the roughness gradient.
    import drjit as dr
    import mitsuba as mi

    integrator = mi.load_dict({"type": "gra_onebounce"})
    key = "floor.bsdf.roughness.value"
    for roughness in (0.05, 0.1, 0.3):
        scene = mirror_plane_scene(roughness, elevation)
        params = mi.traverse(scene)
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, integrator=integrator, spp=4, seed=3)
        dr.backward(dr.sum(image))
        grad = float(dr.grad(params[key])[0])
        assert np.isfinite(grad), (elevation, roughness, grad)
        if elevation < 0.2:
            continue  # a lobe thinner than float32 resolves: finite is the claim, not a match with differences

        # The comparison replays the primal's samples in the adjoint pass (mi.render draws others, for unbiasedness),
        # as tests/test_onebounce.py does: pixels on the plane's far edge are partly covered.
        dr.set_grad(params[key], 0.0)
        integrator.render_backward(scene, params, mi.TensorXf(np.ones((16, 16, 3), np.float32)), sensor=0, seed=3, spp=4)
        grad = float(dr.grad(params[key])[0])

        def image_sum(value, scene=scene, params=params):
            params[key] = mi.Float(value)
            params.update()
            return float(np.sum(np.array(mi.render(scene, params, integrator=integrator, spp=4, seed=3), np.float64)))

        eps = 5e-3 * roughness  # the sum is sharply curved in r at a tight lobe: small steps
        fd = (image_sum(roughness + eps) - image_sum(roughness - eps)) / (2 * eps)
        assert grad == pytest.approx(fd, rel=1e-2), (elevation, roughness, grad, fd)


# ---------------------------------------------------------------------------------------------------------------
# Texels outside the model: defined per lane, never spread
# ---------------------------------------------------------------------------------------------------------------

BAD_ALBEDO = {"nan": np.nan, "+inf": np.inf, "-inf": -np.inf, "negative": -0.5, "above one": 3.0}
BAD_ROUGHNESS = {"nan": np.nan, "+inf": np.inf, "-inf": -np.inf, "negative": -0.5, "above one": 3.0}


def bitmap_bsdf(albedo_texels: np.ndarray, roughness_texels: np.ndarray):
    import mitsuba as mi

    def bitmap(data):
        return {"type": "bitmap", "bitmap": mi.Bitmap(data.astype(np.float32)), "filter_type": "nearest", "raw": True}

    return mi.load_dict({"type": "gra_microfacet", "id": "skin", "albedo": bitmap(albedo_texels), "roughness": bitmap(roughness_texels)})


def evaluate_at_texels(bsdf, width: int, wi: np.ndarray, wo: np.ndarray):
    """(eval, pdf, sampled weight, sampled ωo) with lane k at the centre of texel k of a width × 1 bitmap."""
    import mitsuba as mi

    n = len(wi)
    si = interaction(wi, n)
    texel = np.arange(n) % width
    si.uv = mi.Point2f(((texel + 0.5) / width).astype(np.float32), np.full(n, 0.5, np.float32))
    ctx = mi.BSDFContext()
    wo_ = mi.Vector3f(*wo.astype(np.float32).T)
    value, density = np.array(bsdf.eval(ctx, si, wo_)).T, np.array(bsdf.pdf(ctx, si, wo_))
    u = np.random.default_rng(9).random((n, 3)).astype(np.float32)
    bs, weight = bsdf.sample(ctx, si, mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
    return value, density, np.array(weight).T, np.array(bs.wo).T, texel


@pytest.mark.parametrize("channel", ["albedo", "roughness"])
@pytest.mark.parametrize("bad", list(BAD_ALBEDO))
def test_bad_texels_are_defined_and_stay_in_their_lane(plugins, caplog, channel, bad):
    # Texel 3 of 8 holds the bad value. Its lanes: finite, ≥ 0, exactly 0 below either horizon, and equal to the
    # documented reading (albedo: non-finite → 0, clamp to [0, 1]; roughness: non-finite → 1, clamp). Every other
    # lane: bit-identical to the clean material's.
    rng = np.random.default_rng(7)
    width = 8
    albedo = rng.uniform(0.2, 0.8, (1, width, 3))
    roughness = rng.uniform(0.2, 0.8, (1, width, 1))
    dirty_albedo, dirty_roughness, read_as_albedo, read_as_roughness = albedo.copy(), roughness.copy(), albedo.copy(), roughness.copy()
    value = (BAD_ALBEDO if channel == "albedo" else BAD_ROUGHNESS)[bad]
    if channel == "albedo":
        dirty_albedo[0, 3] = value
        read_as_albedo[0, 3] = np.clip(value, 0, 1) if np.isfinite(value) else 0.0
    else:
        dirty_roughness[0, 3] = value
        read_as_roughness[0, 3] = np.clip(value, 0, 1) if np.isfinite(value) else 1.0
    n = 4000
    wi = np.stack([incident(c, a) for c, a in zip(rng.uniform(-0.3, 1, n), rng.uniform(0, 2 * np.pi, n), strict=True)])
    wo = np.stack([incident(c, a) for c, a in zip(rng.uniform(-0.3, 1, n), rng.uniform(0, 2 * np.pi, n), strict=True)])
    with caplog.at_level(logging.WARNING, logger="gra_mi.render.plugins.microfacet"):
        dirty = evaluate_at_texels(bitmap_bsdf(dirty_albedo, dirty_roughness), width, wi, wo)
    assert "skin" in caplog.text and channel in caplog.text, caplog.text
    clean = evaluate_at_texels(bitmap_bsdf(albedo, roughness), width, wi, wo)
    documented = evaluate_at_texels(bitmap_bsdf(read_as_albedo, read_as_roughness), width, wi, wo)
    texel = dirty[-1]
    for got, want, reading in zip(dirty[:4], clean[:4], documented[:4], strict=True):
        assert np.isfinite(got).all()
        np.testing.assert_array_equal(got[texel != 3], want[texel != 3])
        np.testing.assert_array_equal(got[texel == 3], reading[texel == 3])
    value_, density, weight = dirty[0], dirty[1], dirty[2]
    assert value_.min() >= 0 and density.min() >= 0 and weight.min() >= 0
    below = (wi[:, 2] <= 0) | (wo[:, 2] <= 0)
    assert np.all(value_[below] == 0) and np.all(density[below] == 0)


def test_an_8_bit_albedo_is_not_warned_about(plugins, caplog, tmp_path):
    """An sRGB PNG's texels are stored as levels (0–255) and decoded when looked up: not values outside [0, 1]."""
    import mitsuba as mi
    from PIL import Image

    Image.fromarray(np.full((4, 4, 3), 200, np.uint8)).save(tmp_path / "albedo.png")
    with caplog.at_level(logging.WARNING, logger="gra_mi.render.plugins.microfacet"):
        mi.load_dict({"type": "gra_microfacet", "albedo": {"type": "bitmap", "filename": str(tmp_path / "albedo.png")}})
    assert "outside [0, 1]" not in caplog.text, caplog.text


def test_a_nan_texel_does_not_reach_other_pixels_of_a_path_traced_render(plugins):
    # Mitsuba's own `path` integrator over a floor whose albedo map holds NaN and Inf texels: the image is finite
    # and, away from those texels' own footprint, equal to the clean map's render.
    import mitsuba as mi

    rng = np.random.default_rng(8)
    albedo = rng.uniform(0.2, 0.8, (16, 16, 3))
    dirty = albedo.copy()
    dirty[4, 5] = np.nan
    dirty[10, 11] = np.inf
    images = []
    for data in (albedo, dirty):
        scene = mi.load_dict(
            {
                "type": "scene",
                "floor": {
                    "type": "rectangle",
                    "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90),
                    "bsdf": {
                        "type": "gra_microfacet",
                        "albedo": {"type": "bitmap", "bitmap": mi.Bitmap(data.astype(np.float32)), "filter_type": "nearest", "raw": True},
                        "roughness": 0.3,
                    },
                },
                "camera": {
                    "type": "perspective",
                    "fov": 60,
                    "to_world": mi.ScalarTransform4f().look_at(origin=[0, 3, 0.01], target=[0, 0, 0], up=[0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}},
                },
                "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            }
        )
        images.append(np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": 3}), spp=16, seed=1)))
    clean, dirty_image = images
    assert np.isfinite(dirty_image).all()
    differs = np.any(dirty_image != clean, axis=2)
    assert differs.mean() < 0.05, differs.mean()  # only the two texels' own pixels
