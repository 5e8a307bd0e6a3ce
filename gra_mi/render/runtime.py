"""Starting Mitsuba for gra-mi: the variant (:func:`gra_mi.core.runtime.choose_variant`) with gra-mi's plugins
registered for it, and the torch device, once per command. Here rather than in ``core`` because registering the
plugins is the render layer's business (docs/architecture.md: no import runs back up the layers)."""

from __future__ import annotations

from gra_mi.core import runtime
from gra_mi.render.plugins import register_plugins


def start_runtime(variant: str | None = None, device: str | None = None, *, mitsuba: bool = True, torch: bool = False) -> runtime.Runtime:
    """Start what a command needs, once: the Mitsuba variant with the plugins registered (``mitsuba``) and the torch
    device (``torch``). ``None`` means automatic: the GPU where one works."""
    if mitsuba:
        runtime.RUNTIME.variant = runtime.choose_variant(variant)
        register_plugins()
    if torch:
        runtime.RUNTIME.torch_device = runtime.pick_torch_device(device)
    return runtime.RUNTIME


def ensure_mitsuba() -> str:
    """The Mitsuba variant for library code: the one already set (by :func:`start_runtime` or a test), else the
    automatic choice; gra-mi's plugins are registered for it either way."""
    import mitsuba as mi

    if mi.variant() is None:
        return start_runtime().variant

    register_plugins()
    return mi.variant()
