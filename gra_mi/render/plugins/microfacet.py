"""``gra_microfacet``: Lambert diffuse + Cook–Torrance specular (GGX, separable Smith, Schlick F0 = 0.04).

.. list-table::
   :header-rows: 1

   * - Parameter
     - Type
     - Description
   * - ``albedo``
     - texture or rgb
     - Diffuse albedo in [0, 1], usually a bitmap in the mesh's UV space. Default: 0.5.
   * - ``roughness``
     - texture or float
     - Perceptual roughness r in [0, 1] (α = r², clamped at 1e-3), single channel. Default: 0.5.

The maths lives in :mod:`gra_mi.brdf`. One-sided (back faces are black), reflection only. ``sample`` mixes cosine
sampling of the diffuse lobe with GGX visible-normal sampling, so any Mitsuba integrator renders it.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from gra_mi.render import brdf


def _as_texture(props, name: str, default: float, single_channel: bool):
    """A property as a Mitsuba texture: nested textures pass through; numbers and colours become constants."""
    if not props.has_property(name):
        return mi.load_dict({"type": "uniform", "value": default})
    value = props[name]
    if isinstance(value, mi.Texture):
        return value
    if isinstance(value, (int, float)):
        return mi.load_dict({"type": "uniform", "value": float(value)})
    if single_channel:
        raise ValueError(f"gra_microfacet: '{name}' must be a float or a single-channel texture, got {value!r}")
    return mi.load_dict({"type": "rgb", "value": value})


class GraMicrofacet(mi.BSDF):
    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        self.albedo = _as_texture(props, "albedo", 0.5, single_channel=False)
        self.roughness = _as_texture(props, "roughness", 0.5, single_channel=True)
        flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.SpatiallyVarying
        self.m_components = [flags]
        self.m_flags = flags

    def _params(self, si, active):
        albedo = self.albedo.eval(si, active)
        roughness = self.roughness.eval_1(si, active)
        return albedo, roughness

    def eval(self, ctx, si, wo, active=True):
        albedo, roughness = self._params(si, active)
        return dr.select(active, brdf.eval_cos(albedo, roughness, si.wi, wo), 0.0)

    def pdf(self, ctx, si, wo, active=True):
        albedo, roughness = self._params(si, active)
        return dr.select(active, brdf.pdf(albedo, roughness, si.wi, wo), 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        albedo, roughness = self._params(si, active)
        return dr.select(active, brdf.eval_cos(albedo, roughness, si.wi, wo), 0.0), dr.select(
            active, brdf.pdf(albedo, roughness, si.wi, wo), 0.0
        )

    def sample(self, ctx, si, sample1, sample2, active=True):
        albedo, roughness = self._params(si, active)
        wo, pdf = brdf.sample(albedo, roughness, si.wi, sample1, sample2)
        value = brdf.eval_cos(albedo, roughness, si.wi, wo)
        valid = active & (pdf > 0) & (si.wi.z > 0) & (wo.z > 0)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = wo
        bs.pdf = dr.select(valid, pdf, 0.0)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
        bs.sampled_component = mi.UInt32(0)
        return bs, dr.select(valid, value / dr.maximum(pdf, 1e-20), 0.0)

    def traverse(self, callback):
        callback.put("albedo", self.albedo, mi.ParamFlags.Differentiable)
        callback.put("roughness", self.roughness, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        pass

    def to_string(self):
        return f"GraMicrofacet[albedo={self.albedo}, roughness={self.roughness}]"


def register() -> None:
    mi.register_bsdf("gra_microfacet", lambda props: GraMicrofacet(props))
