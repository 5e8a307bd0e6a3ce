"""A capture and its fitted maps (``gra-mi fit``), loaded together: what RelightNet, the refiner's data and the
evaluation start from."""

from __future__ import annotations

from pathlib import Path

from gra_mi.capture.dataset import Capture
from gra_mi.core.errors import GraMiInputError
from gra_mi.render.relighter import Relighter, load_texture
from gra_mi.render.transport import LightTransport


def fitted_relighter(
    capture_dir: str | Path, fit_dir: str | Path, cache_dir: str | Path | None = None, transport: LightTransport | None = None
):
    """(capture, relighter) for a capture and its fitted maps (``gra-mi fit``): what RelightNet and the refiner train
    on; ``transport``: the bounces of light it renders (default: one)."""
    capture = Capture.load(capture_dir)
    capture.check_images()
    fit_dir = Path(fit_dir)
    albedo = load_texture(fit_dir / "albedo.exr", 3, "albedo")
    roughness = load_texture(fit_dir / "roughness.exr", 1, "roughness")
    if roughness.shape[:2] != albedo.shape[:2]:
        raise GraMiInputError(
            fit_dir / "roughness.exr",
            f"{roughness.shape[0]}² but albedo.exr is {albedo.shape[0]}²: the maps of one fit share a resolution (refit, or resample both)",
            field="resolution",
        )
    ls = capture.load_scene()
    return capture, Relighter(ls, albedo=albedo, roughness=roughness, cache_dir=cache_dir, transport=transport)
