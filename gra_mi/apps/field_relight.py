"""`gra-mi relight-field`: a capture's cameras under any LED lighting, as the weighted sum of its OLAT photographs.

No model is involved: this is the capture's own answer to "what would the subject look like under this lighting in
this stage" (near field: the LEDs where they are), and the truth the learned stages are measured against.
"""

from __future__ import annotations

import json
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
    (name → LED intensities (L, 3)) and camera; ``out/summary.json`` with what was held and what it cost.
    ``skip_incomplete``: leave out (and name in the summary) a camera a real capture's gap left without an OLAT image;
    else such a camera is refused (the sum needs every OLAT)."""
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    static_pose(capture)
    index = OlatIndex.of(capture, stage)
    weights = {name: index.weights(intensities, name) for name, intensities in lights.items()}  # every drive checked first
    names = list(weights)
    summary = {"capture": str(capture.folder), "olats": len(index.frames), "lightings": names, "cameras": {}, "skipped": {}}
    if skip_incomplete:
        summary["skipped"] = index.incomplete(capture, cameras)
        cameras = [c for c in cameras if c not in summary["skipped"]]
        if not cameras:
            raise GraMiInputError(
                capture.folder / "capture.json", "no camera has an image of every OLAT: nothing to relight", field="frames"
            )
    for camera in cameras:
        start = time.perf_counter()
        rf = ReflectanceField.load(capture, camera, index, config.memory_gb)
        loaded, summed = time.perf_counter() - start, 0.0
        for first in progress(range(0, len(names), config.batch), description=f"relight {camera}"):
            batch = names[first : first + config.batch]
            start = time.perf_counter()
            images = rf.relight(np.stack([weights[n] for n in batch]))
            summed += time.perf_counter() - start
            for name, image in zip(batch, images, strict=True):
                write_exr(out / name / f"{camera}.exr", image)
                write_png(out / name / f"{camera}.png", image[..., :3], exposure=None)
        summary["cameras"][camera] = rf.stats | {
            "size": list(rf.shape[::-1]),
            "subject_pixels": int(rf.pixels.size),
            "load_s": round(loaded, 3),
            "ms_per_lighting": round(1000 * summed / len(names), 3),
        }
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=1) + "\n")
    return summary
