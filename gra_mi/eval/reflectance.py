"""Evaluation lightings whose truth is a capture's reflectance field: environment maps the capture never photographed
(the user's HDRIs, held-out procedural maps), each the sum of the capture's OLATs under that map's LED drive.

This is the truth a real lightstage capture can give for any lighting the stage can make: photographs, summed, with
no model in between (:mod:`gra_mi.capture.reflectance`). It is near field (the LEDs where they are), the same
lighting the microfacet render and RelightNet are asked for.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.reflectance import OlatIndex, ReflectanceField
from gra_mi.relightnet.lightings import SEED_OFFSET, synthesized_drives
from gra_mi.stage.lightstage import load_calibration

logger = logging.getLogger(__name__)

EVAL_SEED_OFFSET = SEED_OFFSET + 100_000  # library maps no training or validation run draws
TRUTH = "Σ OLAT (the capture's reflectance field)"


@dataclass
class FieldLighting:
    name: str
    intensities: np.ndarray  # (L, 3) LED radiant intensities


def field_lightings(capture, stage, envmaps: dict[str, np.ndarray], library: int) -> list[FieldLighting]:
    """The user's maps (name → lat-long radiance) and ``library`` held-out procedural maps, mapped onto the LEDs."""
    from gra_mi.stage.envmap import envmap_to_leds

    if not (envmaps or library):
        return []
    index = OlatIndex.of(capture, stage)  # every OLAT, either split: the truth is as complete as the capture is
    off = np.setdiff1d(np.arange(stage.num_leds), index.leds)
    lights = []
    for name, env in envmaps.items():
        drive = envmap_to_leds(env, stage).radiant_intensity(stage)
        if off.size and drive[off].any():  # LEDs the capture has no OLAT of are off for every stage and the truth
            logger.info("%s: %.1f %% of its light falls on LEDs without an OLAT; they are off", name, 100 * drive[off].sum() / drive.sum())
            drive[off] = 0.0
        lights.append(FieldLighting(name, drive))
    drives = synthesized_drives(stage, "test", library, index, offset=EVAL_SEED_OFFSET) if library else []
    return lights + [FieldLighting(f"library_{k:03d}", d) for k, d in enumerate(drives)]


@dataclass
class FieldTruth:
    """The reflectance-field image of a held-out camera under a lighting; each camera's OLATs loaded once."""

    capture: object
    fields: dict = field(default_factory=dict)
    index: OlatIndex | None = None

    def __call__(self, camera: str, light: FieldLighting) -> np.ndarray:
        if self.index is None:
            self.index = OlatIndex.of(self.capture, load_calibration(Path(self.capture.folder) / "rig" / "calibration.json"))
        if camera not in self.fields:
            self.fields[camera] = ReflectanceField.load(self.capture, camera, self.index)
        rf = self.fields[camera]
        return rf.relight(rf.weights(light.intensities, light.name, quiet=True))[0]
