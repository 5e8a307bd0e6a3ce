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

import time
from dataclasses import replace
from pathlib import Path

from gra_mi.fit.maps import LevelStart


def fit_levels(capture, config, out: Path, make_fitter):
    """Fit ``config.levels`` in turn into ``out`` (each coarse level checkpointed in ``out``/level_RRRR, a finished one
    reused on a rerun) with fitters ``make_fitter(capture, level_config, cache_dir)`` makes; returns the last level's
    fitter and result, whose curve spans every level."""

    start, earlier, clock = None, [], time.perf_counter()
    for k, resolution in enumerate(config.levels):
        last = k == len(config.levels) - 1
        level = replace(config, resolution=resolution, levels=None, calibrate_brightness=config.calibrate_brightness if last else False)
        folder = out if last else out / f"level_{resolution:04d}"
        fitter = make_fitter(capture, level, out / "cache")
        done = folder / "level.npz"
        fitter.ranks.agree(done.is_file(), f"{done}: whether this level is done")
        if not last and done.is_file():
            start = LevelStart.load(done, fitter.atlas)
            earlier = start.curve
            continue
        result = fitter.fit(folder, start)
        if last:
            curve = earlier + [(t, loss, f"{resolution}²: {label}") for t, loss, label in result.loss_curve]
            return fitter, replace(result, loss_curve=curve)
        start = LevelStart.of(fitter, result, earlier, (start.seconds if start else 0.0) + time.perf_counter() - clock)
        clock = time.perf_counter()
        if fitter.ranks.main:
            start.save(done)
        earlier = start.curve
    raise AssertionError("levels is never empty (FitConfig.validate)")
