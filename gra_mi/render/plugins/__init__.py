"""gra-mi's Mitsuba plugins, registered per variant by :func:`register_plugins` (never at import time).

- ``gra_microfacet`` (BSDF): the paper's Lambert + Cook–Torrance/GGX material with UV textures.
- ``gra_onebounce`` (integrator): deterministic one-bounce lighting from every point-light LED.
"""

from __future__ import annotations

_registered: set[str] = set()


def register_plugins() -> None:
    """Register the plugins for the current Mitsuba variant (idempotent)."""
    import mitsuba as mi

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("choose a Mitsuba variant first (gra_mi.render.runtime.start_runtime)")
    if variant in _registered:
        return
    from gra_mi.render.plugins.microfacet import register as register_bsdf
    from gra_mi.render.plugins.onebounce import register as register_integrator

    register_bsdf()
    register_integrator()
    _registered.add(variant)
