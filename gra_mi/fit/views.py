"""Where a fit keeps what it knows about each training view (camera × frame): its observed texels, its pixel
footprints, its shading parts.

A small capture's views are held in memory. A large one's (``FitConfig.batch_views`` > 0) are written to scratch
files, one per view, and read back when a pass or a minibatch needs that view, so that the fit's memory is set by
how many views it works on at once, not by how many the capture has (the paper's data: 40 cameras × 28,420 frames).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from gra_mi.core.guard import check_output_path, scratch_folder


class ViewStore:
    """Named groups of arrays, one per view: in memory (``folder`` None), or one uncompressed .npz per group under
    ``folder`` (scratch: :meth:`close` removes it)."""

    def __init__(self, folder: str | Path | None = None):
        self.folder = None if folder is None else Path(folder)
        self._memory: dict[str, dict[str, np.ndarray]] = {}
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)  # a previous run's scratch: rebuilt, never trusted
            self.folder.mkdir(parents=True)

    @classmethod
    def for_fit(cls, streamed: bool, out: Path | None, rank: int = 0) -> ViewStore:
        """In memory, or (``streamed``) in ``out``/views.tmp (process ``rank`` > 0 of a fit: views-RANK.tmp), or a
        temporary folder when the fit has no output folder."""
        if not streamed:
            return cls()
        return cls(scratch_folder("gra-mi-views-") if out is None else Path(out) / ("views.tmp" if rank == 0 else f"views-{rank}.tmp"))

    @property
    def on_disk(self) -> bool:
        return self.folder is not None

    def _path(self, name: str) -> Path:
        return self.folder / (name.replace("/", "__") + ".npz")

    def put(self, name: str, **arrays: np.ndarray) -> None:
        if self.folder is None:
            self._memory[name] = arrays
            return
        check_output_path(self._path(name))
        with open(self._path(name), "wb") as fh:
            np.savez(fh, **arrays)

    def get(self, name: str) -> dict[str, np.ndarray]:
        if self.folder is None:
            return self._memory[name]
        with np.load(self._path(name), allow_pickle=False) as data:
            return {key: data[key] for key in data.files}

    def close(self) -> None:
        self._memory.clear()
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)


def batch_at(iteration: int, num_views: int, batch_views: int, seed: int) -> np.ndarray:
    """The views Adam's step ``iteration`` uses: all of them (``batch_views`` 0 or ≥ the count), or the next
    ``batch_views`` of a per-epoch random permutation, so that every view is used once per epoch and the batch of a
    step depends only on its number (a resumed fit sees the batches an uninterrupted one does)."""
    if batch_views <= 0 or batch_views >= num_views:
        return np.arange(num_views)
    per_epoch = -(-num_views // batch_views)
    epoch, position = divmod(iteration, per_epoch)
    order = np.random.default_rng([seed, epoch]).permutation(num_views)
    return np.sort(order[position * batch_views : (position + 1) * batch_views])


def curve_sample(num_views: int, at_most: int) -> np.ndarray:
    """Evenly spaced views on which a streamed fit measures its convergence curve (all if there are few)."""
    if num_views <= at_most:
        return np.arange(num_views)
    return np.unique(np.linspace(0, num_views - 1, at_most).round().astype(np.int64))
