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

The maths lives in :mod:`gra_mi.render.brdf`. One-sided (back faces are black), reflection only. ``sample`` mixes
cosine sampling of the diffuse lobe with GGX visible-normal sampling, so any Mitsuba integrator renders it.

Texel values outside the model are read per lane as :func:`~gra_mi.render.brdf.sanitize_albedo` and
:func:`~gra_mi.render.brdf.sanitize_roughness` define (non-finite albedo → 0, non-finite roughness → 1, both clamped to
[0, 1]); a bitmap that holds any is named in a warning when the scene loads.
"""

from __future__ import annotations

import logging

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.render import brdf

log = logging.getLogger(__name__)


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


def _warn_out_of_model(bsdf_id: str, name: str, texture) -> None:
    """Warn, naming the texture, when a bitmap holds values the model reads differently (non-finite, outside [0, 1])."""
    params = mi.traverse(texture)
    if "data" not in params:  # constants are checked by the sanitizers' clamps alone
        return
    values = np.asarray(params["data"])
    if not np.issubdtype(values.dtype, np.floating):  # an 8- or 16-bit image's levels: decoded to [0, 1] when looked up
        return
    values = values.astype(np.float64)
    non_finite = int(np.count_nonzero(~np.isfinite(values)))
    finite = values[np.isfinite(values)]
    outside = int(np.count_nonzero((finite < 0) | (finite > 1)))
    if non_finite or outside:
        read_as = "0" if name == "albedo" else "1"
        log.warning(
            "gra_microfacet '%s': %s texture %s holds %d non-finite values (read as %s) and %d outside [0, 1] (clamped)",
            bsdf_id,
            name,
            texture,
            non_finite,
            read_as,
            outside,
        )


class GraMicrofacet(mi.BSDF):
    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)
        self.albedo = _as_texture(props, "albedo", 0.5, single_channel=False)
        self.roughness = _as_texture(props, "roughness", 0.5, single_channel=True)
        _warn_out_of_model(props.id(), "albedo", self.albedo)
        _warn_out_of_model(props.id(), "roughness", self.roughness)
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
