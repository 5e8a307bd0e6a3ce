"""Training lightings for RelightNet synthesized from a capture's reflectance field (its OLATs).

A static OLAT capture photographs the subject under one LED at a time, so its image under any LED drive is known
without a model: Σ wᵢ · OLATᵢ (:mod:`gra_mi.capture.reflectance`). Each procedural environment map (skies with a
sun, rooms; :mod:`gra_mi.stage.envmap_library`) mapped onto the LEDs is then a training pair at the cost of a sum:
the network's input is the microfacet render under that drive, its target the OLAT sum. The capture's held-out OLATs
are left out of every sum (their LEDs are off in the synthesized drives), so they stay unseen lightings.

Training draws (lighting, camera) pairs; their views are made when drawn (a shading pass and a sum, tens of ms), so
memory does not grow with the number of lightings. Validation lightings are another seed range of the library.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.reflectance import MISSING_SHARE_LIMIT, OlatIndex, ReflectanceField, static_pose
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path
from gra_mi.core.progress import progress
from gra_mi.relightnet.data import SYNTHESIZED_SPLIT, Sample
from gra_mi.render.bridge import camera_uv_grid, to_torch
from gra_mi.stage.envmap import envmap_to_leds
from gra_mi.stage.envmap_library import SPLIT_SEED_BASE, envmap_from_seed

logger = logging.getLogger(__name__)

LIBRARY_HEIGHT = 32  # rows of each procedural map before the LED mapping (331 LEDs resolve no finer)


SEED_OFFSET = 500_000  # library seeds past the ones captures draw their own maps from (train / test)


def synthesized_drives(stage, split: str, count: int, index: OlatIndex, cache: Path | None = None, offset: int = SEED_OFFSET) -> np.ndarray:
    """(count, L, 3) LED radiant intensities of ``count`` library maps of ``split``, LEDs without a training OLAT off.
    Cached in ``cache`` (an .npz) when given: mapping a thousand maps takes about a minute."""
    if cache is not None and cache.is_file():
        with np.load(cache) as data:
            if data["drives"].shape == (count, stage.num_leds, 3) and np.array_equal(data["leds"], index.leds):
                return data["drives"]
    off = np.setdiff1d(np.arange(stage.num_leds), index.leds)
    drives = np.empty((count, stage.num_leds, 3))
    seeds = [SPLIT_SEED_BASE[split] + offset + k for k in range(count)]
    for k, seed in enumerate(progress(seeds, description=f"lightings ({split})")):
        drives[k] = envmap_to_leds(envmap_from_seed(seed, LIBRARY_HEIGHT)[0], stage).radiant_intensity(stage)
        drives[k, off] = 0.0
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(cache) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, drives=drives, leds=index.leds)
    return drives


@dataclass
class SynthesizedViews:
    """Views of a static capture under synthesized lightings: ``view(k, camera)`` is a RelightNet :class:`Sample`
    whose target is the reflectance field's sum for drive ``k``."""

    capture: object
    relighter: object
    drives: np.ndarray  # (N, L, 3)
    index: OlatIndex
    fields: dict  # camera → ReflectanceField
    grids: dict  # camera → (grid, hit)
    env_height: int
    device: str
    split: str
    cameras: list[str] | None = None  # the cameras training draws (None: every camera with a field)

    @classmethod
    def build(cls, capture, relighter, drives: np.ndarray, index: OlatIndex, cameras: list[str], env_height: int, device: str, split: str):
        pose = static_pose(capture)
        relighter.ls.set_frame(pose)
        fields = {c: ReflectanceField.load(capture, c, index) for c in cameras}
        grids = {c: camera_uv_grid(relighter.ls, relighter.ls.stage.camera(c), device) for c in cameras}
        return cls(capture, relighter, drives, index, fields, grids, env_height, device, split)

    def keys(self, cameras: list[str] | None = None) -> list[tuple[int, str]]:
        """(lighting, camera) pairs, but those whose sum would take more than a little light from neighbouring OLATs
        (:meth:`summable`)."""
        cameras = cameras or list(self.fields)
        summable = {c: self.summable(c) for c in cameras}
        return [(k, c) for k in range(len(self.drives)) for c in cameras if summable[c][k]]

    def summable(self, camera: str) -> np.ndarray:
        """(N,) whether each drive's light on the LEDs whose OLAT ``camera`` has no image of is within
        :data:`~gra_mi.capture.reflectance.MISSING_SHARE_LIMIT` (their light then comes from neighbouring OLATs)."""
        lacking = self.fields[camera].lacking
        if not lacking.size:
            return np.ones(len(self.drives), bool)
        share = self.drives[:, self.index.leds[lacking]].sum(axis=(1, 2)) / np.maximum(self.drives.sum(axis=(1, 2)), 1e-30)
        return share <= MISSING_SHARE_LIMIT

    def view(self, k: int, camera: str):
        from gra_mi.relightnet.infer import view_inputs

        pose = static_pose(self.capture)
        intensities = self.drives[k]
        features, mask, env, _ = view_inputs(self.relighter, pose, camera, intensities, self.env_height, self.device)
        field = self.fields[camera]
        image = field.relight(field.weights(intensities, f"synthesized lighting {k}", quiet=True))[0]
        grid, hit = self.grids[camera]
        target = to_torch(image[..., :3], self.device).permute(2, 0, 1)[None].contiguous()
        pixels = hit * to_torch((image[..., 3] > 0.99).astype(np.float32), self.device)[None, None]
        return Sample(f"{camera}/lighting_{k:04d}", self.split, features, mask, env, grid, pixels, target)


def synthesized_views(capture, relighter, config, device: str, cache: Path | None) -> tuple[SynthesizedViews, list]:
    """The training lightings (``config.synthesized_lightings``, training cameras) and the validation views
    (``config.synthesized_validation`` other maps, from every held-out camera), targets from the training OLATs."""
    stage = relighter.ls.stage
    static_pose(capture)
    index = OlatIndex.of(capture, stage, splits=("train",))
    train = synthesized_drives(stage, "train", config.synthesized_lightings, index, cache and cache / "synthesized_train.npz", SEED_OFFSET)
    val = synthesized_drives(stage, "test", config.synthesized_validation, index, cache and cache / "synthesized_val.npz", SEED_OFFSET)
    cameras = [c for c in capture.train_cameras + capture.eval_cameras if index.lacking(capture, c).size < len(index.frames)]
    views = SynthesizedViews.build(capture, relighter, train, index, cameras, config.env_height, device, "train")
    views.cameras = [c for c in capture.train_cameras if c in cameras]
    if not views.keys(views.cameras):
        raise GraMiInputError(capture.folder / "capture.json", "no training camera has the OLAT images its synthesized lightings need", field="frames")  # fmt: skip
    held = SynthesizedViews(capture, relighter, val, index, views.fields, views.grids, config.env_height, device, SYNTHESIZED_SPLIT)
    shown = [c for c in capture.eval_cameras if c in cameras]
    validation = [held.view(k, c) for k, c in progress(held.keys(shown), description="synthesized validation")] if shown else []
    _say_gaps(views, held)
    logger.info("synthesized lightings: %d training, %d validation maps, from %d OLATs", len(train), len(val), len(index.frames))
    return views, validation


def _say_gaps(*views: SynthesizedViews) -> None:
    """Once per camera that lacks an OLAT image: whose light comes from its neighbours, and in how many lightings
    that would have been too much of the light (those pairs are left out)."""
    for camera, field in views[0].fields.items():
        if field.lacking.size:
            left = sum(int((~v.summable(camera)).sum()) for v in views)
            logger.warning("synthesized lightings: camera %s has no image of the OLAT of LEDs %s: their light comes from their neighbours' "
                           "OLATs; %d of %d lightings, where it is more than %.0f %% of the light, are left out for it", camera,
                           ", ".join(str(led) for led in field.index.leds[field.lacking]), left, sum(len(v.drives) for v in views),
                           100 * MISSING_SHARE_LIMIT)  # fmt: skip


class TrainingViews:
    """The views training draws from, indexable like a list (so the sample order stays a function of the step):
    the capture's own (held :class:`Sample` objects, or view jobs made when drawn by ``make``), then synthesized
    (lighting, camera) pairs."""

    def __init__(self, items: list, make, synthesized: SynthesizedViews | None = None, order: list[int] | None = None):
        self.items, self.make, self.synthesized = items, make, synthesized
        self.synth_keys = synthesized.keys(synthesized.cameras) if synthesized is not None else []
        self.order = list(range(len(self.items) + len(self.synth_keys))) if order is None else order

    def __len__(self) -> int:
        return len(self.order)

    def __getitem__(self, i: int):
        j = self.order[i]
        if j >= len(self.items):
            return self.synthesized.view(*self.synth_keys[j - len(self.items)])
        item = self.items[j]
        return item if not isinstance(item, tuple) else self.make(item)

    def share(self, rank: int, world: int) -> TrainingViews:
        """This process's views of a ``world``-process run."""
        return TrainingViews(self.items, self.make, self.synthesized, self.order[rank::world])

    def spread(self, count: int) -> list:
        """Up to ``count`` views evenly spaced over the captured and the synthesized ones (the report's training row)."""
        picks = np.unique(np.linspace(0, len(self) - 1, min(count, len(self))).round().astype(int))
        return [self[int(k)] for k in picks]
