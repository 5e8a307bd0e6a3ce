"""Coarse-to-fine material fits (``gra-mi fit --levels 256,512,1024``).

A texel at 1024² sees 1/16 of the pixels one at 256² sees, so a flat fit at high resolution starts from a noisy
closed form and needs many expensive steps to settle. Fitting coarse first and upsampling (as Mitsuba's texture
tutorials do with ``dr.upsample``) gives each finer level a start that already holds the coarse solution; its Adam
steps only add the detail the images carry. What is carried across levels:

- the maps, resampled bilinearly in UV (the coarse map first extended past its charts by its nearest texel, so that
  texels at chart borders do not blend in the background);
- the highlight confidence: a fine texel without highlight evidence of its own whose coarse texel had some keeps the
  coarse roughness and anchors the fill of its neighbours, instead of being interpolated from far away;
- the prior: the same smoothness weights at every level (their graph is built per level, in 3D).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gra_mi.core.io import atomic_path, read_checkpoint_npz
from gra_mi.render.atlas import UVAtlas, texel_uvs


def resample(atlas_from: UVAtlas, texture: np.ndarray, atlas_to: UVAtlas) -> np.ndarray:
    """A texture of ``atlas_from`` (R, R, C) sampled bilinearly at the texel centres of ``atlas_to``: (M_to, C)."""
    from scipy.ndimage import distance_transform_edt

    r = atlas_from.resolution
    nearest = distance_transform_edt(~atlas_from.mask, return_distances=False, return_indices=True)
    extended = texture[nearest[0], nearest[1]]  # every texel outside the atlas takes its nearest valid texel's value
    uv = texel_uvs(atlas_to.resolution)[atlas_to.texel_index]
    x, y = np.clip(uv[:, 0] * r - 0.5, 0, r - 1), np.clip(uv[:, 1] * r - 0.5, 0, r - 1)
    x0, y0 = np.minimum(x.astype(np.int64), r - 2), np.minimum(y.astype(np.int64), r - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = extended[y0, x0] * (1 - fx) + extended[y0, x0 + 1] * fx
    bottom = extended[y0 + 1, x0] * (1 - fx) + extended[y0 + 1, x0 + 1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


@dataclass
class LevelStart:
    """What a finished level hands to the next: its maps, where it saw highlights, and its convergence curve."""

    atlas: UVAtlas
    albedo: np.ndarray  # (R, R, 3)
    roughness: np.ndarray  # (R, R, 1)
    highlights: np.ndarray  # (R, R, 1): 1 where the level had highlight evidence
    curve: list  # (seconds, data L1, label), labels prefixed with the level
    seconds: float  # wall time of the levels so far: where the next level's curve starts

    @property
    def resolution(self) -> int:
        return self.atlas.resolution

    @classmethod
    def of(cls, fitter, result, earlier: list, seconds: float) -> LevelStart:
        r = fitter.atlas.resolution
        highlights = np.zeros(fitter.atlas.num_texels, np.float32)
        if result.evidence is not None:
            highlights = (result.evidence.highlights > 0).astype(np.float32)
        curve = earlier + [(t, loss, f"{r}²: {label}") for t, loss, label in result.loss_curve]
        return cls(fitter.atlas, result.albedo, result.roughness, fitter.atlas.scatter(highlights[:, None]), curve, seconds)

    def resampled(self, atlas: UVAtlas) -> tuple[np.ndarray, np.ndarray]:
        """The albedo (R', R', 3) and roughness (R', R', 1) maps on ``atlas``."""
        from gra_mi.fit.materials import DEFAULT_ALBEDO, DEFAULT_ROUGHNESS

        albedo = np.clip(resample(self.atlas, self.albedo, atlas), 0.0, 1.0)
        roughness = np.clip(resample(self.atlas, self.roughness, atlas), 0.0, 1.0)
        return atlas.scatter(albedo, fill=DEFAULT_ALBEDO), atlas.scatter(roughness, fill=DEFAULT_ROUGHNESS)

    def carried_highlights(self, atlas: UVAtlas) -> np.ndarray:
        """(M',) texels of ``atlas`` whose coarse texel had highlight evidence."""
        return resample(self.atlas, self.highlights, atlas)[:, 0] > 0.5

    def save(self, path: Path) -> None:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            arrays = {"albedo": self.albedo, "roughness": self.roughness, "highlights": self.highlights}
            np.savez(fh, **arrays, curve=json.dumps(self.curve), seconds=np.array(self.seconds))

    @classmethod
    def load(cls, path: Path, atlas: UVAtlas) -> LevelStart:
        state = read_checkpoint_npz(path)
        curve = [tuple(c) for c in json.loads(str(state["curve"]))]
        return cls(atlas, state["albedo"], state["roughness"], state["highlights"], curve, float(state["seconds"]))


def fit_levels(capture, config, out: Path):
    """Fit ``config.levels`` in turn into ``out`` (each coarse level checkpointed in ``out``/level_RRRR, a finished one
    reused on a rerun); returns the last level's fitter and result, whose curve spans every level."""
    from gra_mi.fit.materials import MaterialFitter

    start, earlier, clock = None, [], time.perf_counter()
    for k, resolution in enumerate(config.levels):
        last = k == len(config.levels) - 1
        level = replace(config, resolution=resolution, levels=None, calibrate_brightness=config.calibrate_brightness and last)
        folder = out if last else out / f"level_{resolution:04d}"
        fitter = MaterialFitter(capture, level, cache_dir=out / "cache")
        done = folder / "level.npz"
        if not last and done.is_file():
            start = LevelStart.load(done, fitter.atlas)
            earlier = start.curve
            continue
        result = fitter.fit(folder, start)
        if last:
            curve = earlier + [(t, loss, f"{resolution}²: {label}") for t, loss, label in result.loss_curve]
            fitter.config = config  # the report records the fit as asked for, levels included
            return fitter, replace(result, loss_curve=curve)
        start = LevelStart.of(fitter, result, earlier, (start.seconds if start else 0.0) + time.perf_counter() - clock)
        clock = time.perf_counter()
        start.save(done)
        earlier = start.curve
    raise AssertionError("levels is never empty (FitConfig.validate)")
