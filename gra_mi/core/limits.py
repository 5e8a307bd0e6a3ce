"""Sizes checked before work: an option or a declared size that would need more memory than the machine has is
refused with the estimate in the message, before any output folder is claimed (an allocation error found later
would leave a claimed folder and a traceback)."""

from __future__ import annotations

import os
from pathlib import Path

from gra_mi.core.errors import GraMiInputError, GraMiParameterError

MEMORY_SHARE = 0.9  # of the machine's physical memory a single allocation may plan on
DRIVE_BYTES = 2048 * 3 * 8  # one lighting's LED drive (float64 RGB) on a rig of up to 2,048 LEDs
MAX_INTENSITY = 1e20  # W/sr: above it, intensity × BRDF × 1/d² leaves float32 (NaN renders), far past any real lamp


def machine_memory() -> int:
    """Physical memory in bytes (a generous fallback where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 1 << 40


def _said(needed: float) -> str:
    return f"about {needed / 2**30:,.1f} GiB, more than this machine's {machine_memory() / 2**30:,.0f} GiB"


def require_memory(parameter: str, needed_bytes: float, what: str) -> None:
    """Refuse an option value whose work would need more than :data:`MEMORY_SHARE` of the machine's memory."""
    if needed_bytes > MEMORY_SHARE * machine_memory():
        raise GraMiParameterError(parameter, f"{what} would need {_said(needed_bytes)}; choose a smaller value")


def require_memory_for(source: str | Path, field: str, needed_bytes: float, what: str) -> None:
    """The same for a size declared in a file (a film, an image size)."""
    if needed_bytes > MEMORY_SHARE * machine_memory():
        raise GraMiInputError(source, f"{what} would need {_said(needed_bytes)}", field=field)
