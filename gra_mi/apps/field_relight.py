"""`gra-mi relight-field`: a capture's cameras under any LED lighting, as the weighted sum of its OLAT photographs.

No model is involved: this is the capture's own answer to "what would the subject look like under this lighting in
this stage" (near field: the LEDs where they are), and the truth the learned stages are measured against.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture
from gra_mi.capture.reflectance import OlatIndex, ReflectanceField, static_pose
from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import atomic_write_text, write_exr, write_png
from gra_mi.core.progress import progress
from gra_mi.stage.lightstage import load_calibration

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class FieldRelightConfig:
    """How the OLATs are held (:func:`relight_from_field`)."""

    memory_gb: float = 4.0
    """Hold one camera's OLATs in memory up to this size (float32, else float16); above it they are read from disk for
    every batch of lightings (the same result, slower)."""
    batch: int = field(default=32, metadata=option(flag="--lighting-batch"))
    """Lightings summed together (one read of each OLAT per batch when streaming)."""

    def validate(self) -> None:
        if not (np.isfinite(self.memory_gb) and self.memory_gb >= 0):
            raise GraMiParameterError("memory_gb", f"must be a finite number >= 0, got {self.memory_gb}")
        if self.batch < 1:
            raise GraMiParameterError("batch", f"must be >= 1, got {self.batch}")


def relight_from_field(
    capture: Capture, out: Path, lights: dict, cameras: list[str], config: FieldRelightConfig, skip_incomplete: bool = False
) -> dict:
    """``out/<light>/<camera>.exr`` (linear RGBA, alpha = the subject's mask) and a PNG preview for every light
    (name → LED intensities (L, 3)) and camera; ``out/summary.json`` with what was held and what it cost. A camera a
    real capture's gap left without an OLAT image takes that LED's light from its neighbours' OLATs while it is a small
    share of every lighting (:meth:`~gra_mi.capture.reflectance.OlatIndex.weights`); where it is not, the camera is
    refused, or with ``skip_incomplete`` left out and named in the summary."""
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    static_pose(capture)
    index = OlatIndex.of(capture, stage)
    for name, intensities in lights.items():  # every drive checked first
        index.weights(intensities, name)
    names = list(lights)
    summary = {"capture": str(capture.folder), "olats": len(index.frames), "lightings": names, "cameras": {}, "skipped": {}}
    weights = {}
    for camera in cameras:
        try:
            weights[camera] = camera_weights(capture, index, camera, lights)
        except GraMiInputError as exc:
            if not skip_incomplete:
                raise
            summary["skipped"][camera] = str(exc)
    if not weights:
        raise GraMiInputError(capture.folder / "capture.json", "no camera has the OLAT images these lightings need", field="frames")
    for camera, (lacking, camera_weight) in weights.items():
        start = time.perf_counter()
        rf = ReflectanceField.load(capture, camera, index, config.memory_gb)
        loaded, summed = time.perf_counter() - start, 0.0
        for first in progress(range(0, len(names), config.batch), description=f"relight {camera}"):
            batch = names[first : first + config.batch]
            start = time.perf_counter()
            images = rf.relight(np.stack([camera_weight[n] for n in batch]))
            summed += time.perf_counter() - start
            for name, image in zip(batch, images, strict=True):
                write_exr(out / name / f"{camera}.exr", image)
                write_png(out / name / f"{camera}.png", image[..., :3], exposure=None)
        summary["cameras"][camera] = (
            rf.stats
            | {
                "size": list(rf.shape[::-1]),
                "subject_pixels": int(rf.pixels.size),
                "load_s": round(loaded, 3),
                "ms_per_lighting": round(1000 * summed / len(names), 3),
            }
            | lacking
        )
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    return summary


def camera_weights(capture: Capture, index: OlatIndex, camera: str, lights: dict) -> tuple[dict, dict]:
    """({} or what the camera lacks, for the summary; lighting name → its OLAT weights on ``camera``), said once per
    camera where some of a lighting's light comes from neighbouring OLATs; refused (naming the camera, the LEDs and
    the share) where too much would (:meth:`~gra_mi.capture.reflectance.OlatIndex.light_from_neighbours`)."""
    shares = index.light_from_neighbours(capture, camera, lights)
    lacking = index.lacking(capture, camera)
    weights = {name: index.weights(intensities, name, lacking, quiet=True) for name, intensities in lights.items()}
    if not shares:
        return {}, weights
    logger.warning("camera %s has no image of the OLAT of LEDs %s: their light (at most %.2f %% of a lighting's) comes from their "
                   "neighbours' OLATs", camera, ", ".join(str(led) for led in index.leds[lacking]), 100 * max(shares.values()))  # fmt: skip
    return {"lacking_olat_frames": [int(f) for f in index.frames[lacking]], "light_from_neighbours": shares}, weights
