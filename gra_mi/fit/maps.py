"""A fit's maps as records, below the fit that makes them: the defaults of texels no view sees, the resampling of a
map from one UV atlas to another (coarse-to-fine levels, a truth fitted at another resolution), and a coarse level's
maps as the next level starts from them (:class:`LevelStart`)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.io import atomic_path, read_checkpoint_npz
from gra_mi.render.atlas import UVAtlas, texel_uvs

DEFAULT_ALBEDO = 0.5
DEFAULT_ROUGHNESS = 0.5


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
