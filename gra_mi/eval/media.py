"""What an evaluation shows people: each split's frames side by side with the truth as an MP4 (and, under
environment lighting, composited over the environment on a platform), and a contact sheet of a scored frame with its
ꟻLIP error maps. :mod:`gra_mi.eval.protocol` computes the frames; this only lays them out."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from gra_mi.core.color import to_display
from gra_mi.core.io import pyplot, save_figure, write_mp4
from gra_mi.core.metrics import flip_map
from gra_mi.core.progress import progress
from gra_mi.eval.report import STAGE_TITLES, STAGES
from gra_mi.render.composite import PlatformCompositor
from gra_mi.stage.envmap import envmap_to_leds, load_envmap

logger = logging.getLogger(__name__)


def contact_sheet(path: Path, frames: dict, truths, masks, exposure: float, scored: list[int], split: str) -> None:
    """Truth and each stage at the middle scored frame, their ꟻLIP maps below."""

    i = scored[len(scored) // 2]
    stages = [s for s in STAGES if s in frames]
    ys, xs = np.nonzero(masks[i])
    pad = 4
    box = (
        (slice(max(ys.min() - pad, 0), ys.max() + pad + 1), slice(max(xs.min() - pad, 0), xs.max() + pad + 1))
        if ys.size
        else (slice(None), slice(None))
    )
    plt = pyplot()
    fig, axes = plt.subplots(2, 1 + len(stages), figsize=(1.9 * (1 + len(stages)), 5.2), squeeze=False)
    axes[0, 0].imshow(to_display(truths[i], exposure)[box])
    axes[0, 0].set_title("truth", fontsize=8)
    axes[1, 0].imshow(masks[i][box], cmap="gray")
    axes[1, 0].set_title("mask (truth α ≥ 0.5)", fontsize=8)
    for k, stage in enumerate(stages, start=1):
        axes[0, k].imshow(to_display(frames[stage][i], exposure)[box])
        axes[0, k].set_title(STAGE_TITLES[stage], fontsize=8)
        error = np.where(masks[i], flip_map(frames[stage][i], truths[i], exposure), 0.0)
        axes[1, k].imshow(error[box], cmap="magma", vmin=0, vmax=1)
        axes[1, k].set_title(f"ꟻLIP (mean {error[masks[i]].mean():.3f})", fontsize=8)
    for ax in axes.ravel():
        ax.axis("off")
    fig.suptitle(f"{split}, frame {i}", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)


def write_videos(folder: Path, videos: dict, splits: list, capture, relighter, scale: float, platform) -> list[str]:
    """Truth | each stage side by side per split; with ``platform`` (a :class:`~gra_mi.render.composite.PlatformConfig`)
    also over the environment on that platform.
    Returns the splits that were composited (environment lighting only)."""
    composited = []

    fps = 12.0
    for split in splits:
        video = videos[split.name]
        frames, exposure = video["frames"], video["exposure"]
        order = ["truth"] + [s for s in STAGES if s in frames]
        panels = [np.concatenate([frames[s][i][..., :3] for s in order], axis=1) for i in range(len(frames["truth"]))]
        write_mp4(folder / f"{split.name}.mp4", panels, fps=fps, exposure=exposure)
        if not platform or relighter is None:
            continue

        stage = relighter.ls.stage
        entries = {f.frame: f for f in capture.frames}
        if split.lights:
            logger.warning("%s: no composites of reflectance-field splits (their maps are not capture frames), skipped", split.name)
            continue
        if any(entries[f].kind != "envmap" for f in split.capture_frames):
            logger.warning("%s: composites need environment lighting; this sequence has LED patterns, skipped", split.name)
            continue
        cam = stage.camera(split.camera).resized(scale)
        compositor = PlatformCompositor(relighter.ls.sequence, platform)
        envmaps = {e: load_envmap(capture.folder / e) for e in {entries[f].envmap for f in split.capture_frames}}
        composites = []
        for i, f in progress(list(enumerate(split.capture_frames)), description=f"composites {split.name}"):
            env = envmaps[entries[f].envmap]
            scale_env = envmap_to_leds(env, stage).scale
            # stages without an alpha of their own (the refiner's frames) are shown where the geometry covers
            covered = (video["coverage"][i][..., 3:4] if video["coverage"] is not None else frames["truth"][i][..., 3:4]) > 0
            row = [
                compositor(frames[s][i][..., :3] * covered, entries[f].mesh_frame, cam, env, scale_env, entries[f].envmap) for s in order
            ]
            composites.append(np.concatenate(row, axis=1))
        write_mp4(folder / f"{split.name}_composite.mp4", composites, fps=fps, exposure=exposure)
        composited.append(split.name)
    return composited
