"""What a perfect material fit scores: gra-mi's render with a capture's *true* maps (its gt/ folder) against the
capture's own held-out images. The gap to a perfect score is what the coarse model leaves out (the effects its
physics does not have, its UV-space resampling), and so what RelightNet has to make up."""

from __future__ import annotations

import numpy as np

HELD_OUT_GROUPS = {"pattern": "held-out OLATs", "envmap": "held-out envmaps"}
"""Held-out frames by their lighting kind, as the scores group them."""


def true_maps_relighter(capture, transport=None):
    """gra-mi's relighter of ``capture``'s scene with its true maps (its gt/ folder) and ``transport``'s bounces."""
    from gra_mi.render.relighter import Relighter, load_texture

    gt = capture.folder / "gt"
    return Relighter(
        capture.load_scene(), albedo=load_texture(gt / "albedo.exr", 3, "albedo"),
        roughness=load_texture(gt / "roughness.exr", 1, "roughness"), transport=transport,
    )  # fmt: skip


def true_maps_relit(capture, transport=None) -> dict[str, tuple[float, float]]:
    """Display PSNR and SSIM of gra-mi's render (``transport``'s bounces of light; default one) with the true maps
    against the capture's images, per held-out lighting group, from the held-out cameras."""
    from gra_mi.capture.dataset import load_observation
    from gra_mi.core.metrics import compare, subject_mask

    relighter = true_maps_relighter(capture, transport)
    scores: dict[str, list] = {group: [] for group in HELD_OUT_GROUPS.values()}
    for entry in (f for f in capture.frames if f.split == "test" and f.kind in HELD_OUT_GROUPS):
        for camera in capture.eval_cameras:
            truth = load_observation(capture, camera, entry.frame)
            mask = subject_mask(truth)
            if not truth[mask, :3].sum() > 0:
                continue  # an OLAT behind the subject: nothing to score
            image = relighter.render(entry.mesh_frame, camera, capture.lighting(relighter.ls.stage, entry)).image
            score = compare(image, truth, mask)
            scores[HELD_OUT_GROUPS[entry.kind]].append((score["psnr"], score["ssim"]))
    return {group: tuple(np.mean(values, axis=0)) for group, values in scores.items() if values}


def ceiling_cells(capture, transports) -> list[str]:
    """Table cells "PSNR / SSIM" per held-out group, for each transport in turn ("–" where a group has no frames)."""
    cells = []
    for transport in transports:
        relit = true_maps_relit(capture, transport)
        cells += [f"{relit[g][0]:.2f} / {relit[g][1]:.3f}" if g in relit else "–" for g in HELD_OUT_GROUPS.values()]
    return cells
