"""The LED drive of a frame that many LEDs lit at once and whose drive the source does not state (HumanOLAT's
environment-map frames: which map lit which frame is not in its files), solved from the same pose's OLATs.

A static pose's image under any drive is the drive-weighted sum of its OLAT images (light adds). So a frame's drive
is the non-negative least-squares fit of the OLATs to it, per colour channel (:func:`solve_drives`), on a few
training cameras spread over the rig, on block means of the subject's pixels (blocks wholly inside the mask; blocks
any saturated pixel touches left out). The normal equations are formed once per channel and shared by every frame,
so each frame costs one small NNLS (one unknown per LED). What the fit leaves unexplained (``residual``: motion
between the frames, light that is not the stage's, a camera's non-linearity, LEDs whose colour mix is not their
OLAT's) is measured, not assumed away: the importer leaves out a frame the OLATs do not explain.

Neighbouring LEDs light the body almost alike, so the drive of a single LED is poorly determined; the light the drive
gives is not (tests/test_import_envmap_frames.py measures the relit image on held-out cameras, not LED by LED).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.placement import CameraPlan, mask_at_source
from gra_mi.capture.reprojection import frame_mask
from gra_mi.capture.source import Source
from gra_mi.capture.source_files import read_image
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_write_text, read_json
from gra_mi.core.progress import threaded

logger = logging.getLogger(__name__)
MAX_CAMERAS = 8  # training cameras the solve reads every OLAT of (spread over the rig)
BLOCK_COLUMNS = 96  # an image is reduced to about this many columns of block means (averages the 8-bit steps)
ROWS_PER_CAMERA = 4000  # block means kept per camera (a fixed random subset of the subject's)
MAX_RESIDUAL = 0.25  # a frame whose OLATs leave more of its light unexplained is not a mix of them (left out)
UNSEEN = 1e-4  # an LED whose OLATs carry less than this share of the median LED's energy is not seen by the solve


@dataclass
class SolvedDrive:
    """A frame's drive in the OLATs' units: the frame = Σ ``drive[k]`` × the OLAT image of LED ``leds[k]``."""

    key: int  # the frame's key in the source (its image number)
    leds: list[int]  # the source's LED numbers, in the order of ``drive``'s rows
    drive: np.ndarray  # (len(leds), 3), non-negative
    residual: float  # RMS of what the OLATs leave unexplained over the RMS of the frame (its subject pixels)
    unseen: list[int]  # LEDs whose OLATs no chosen camera sees lit (their drive is 0: unknown)
    cameras: list[str]  # the cameras it was solved on
    weights: np.ndarray  # (len(leds), 3): each LED's OLAT summed over the solve's pixels (what a share weighs)

    def share(self, leds: set[int]) -> float:
        """The share of the frame's light (summed over channels) that the given LEDs give."""
        picked = np.array([n in leds for n in self.leds])
        return float((self.drive[picked] * self.weights[picked]).sum() / max((self.drive * self.weights).sum(), 1e-30))

    def record(self) -> dict:
        return {
            "key": self.key, "leds": self.leds, "drive": self.drive.tolist(), "residual": self.residual, "unseen": self.unseen,
            "cameras": self.cameras, "weights": self.weights.tolist(),
        }  # fmt: skip

    @classmethod
    def from_record(cls, r: dict) -> SolvedDrive:
        return cls(r["key"], r["leds"], np.array(r["drive"]), r["residual"], r["unseen"], r["cameras"], np.array(r["weights"]))


def spread_cameras(plans: list[CameraPlan], count: int) -> list[CameraPlan]:
    """Up to ``count`` of ``plans``, each next the farthest from those already taken (their positions)."""
    if len(plans) <= count:
        return list(plans)
    positions = np.array([p.camera.position for p in plans])
    taken = [0]
    while len(taken) < count:
        distance = np.min(np.linalg.norm(positions[:, None] - positions[taken][None], axis=-1), axis=1)
        taken.append(int(np.argmax(distance)))
    return [plans[i] for i in sorted(taken)]


def solve_drives(source: Source, plans: list[CameraPlan], keys: list[int]) -> dict[int, SolvedDrive]:
    """The drive of each frame ``keys`` names, from the OLATs of every LED the source fired (``source.order``,
    ``source.olat_keys``), on up to :data:`MAX_CAMERAS` of ``plans`` (pass the training cameras) that have every one
    of those images."""
    olat_of = {int(led): key for led, key in zip(source.order, source.olat_keys, strict=True)}
    leds = sorted(olat_of)
    needed = [olat_of[n] for n in leds] + list(keys)
    complete = [p for p in plans if all(k in source.images[p.index] for k in needed)]
    if not complete:
        raise GraMiInputError(source.folder, "no training camera has every OLAT and every frame to solve the drive on")
    chosen = spread_cameras(complete, MAX_CAMERAS)
    parts = [_camera_rows(source, plan, [olat_of[n] for n in leds], keys) for plan in chosen]
    olats = np.concatenate([p[0] for p in parts])  # (rows, LEDs, 3)
    frames = np.concatenate([p[1] for p in parts])  # (rows, frames, 3)
    spoiled = np.concatenate([p[2] for p in parts])  # (rows, frames): a saturated pixel in the block
    energy = (olats**2).sum(axis=(0, 2))
    unseen = [n for n, e in zip(leds, energy, strict=True) if e < UNSEEN * np.median(energy)]
    drives = {k: np.zeros((len(leds), 3)) for k in keys}
    squared = {k: [0.0, 0.0] for k in keys}  # (unexplained, the frame's own) over the channels
    for c in range(3):
        a = olats[..., c].astype(np.float64)
        gram = a.T @ a
        for j, key in enumerate(keys):
            b, out = frames[:, j, c].astype(np.float64), spoiled[:, j]
            used, b = (a[~out], b[~out]) if out.any() else (a, b)  # a copy only where saturated blocks drop out
            g = gram - a[out].T @ a[out] if out.any() else gram
            drives[key][:, c] = _nnls_normal(g, used.T @ b)
            squared[key][0] += float(((used @ drives[key][:, c] - b) ** 2).sum())
            squared[key][1] += float((b**2).sum())
    weights = olats.sum(axis=0).astype(np.float64)
    names = [p.camera.name for p in chosen]
    return {
        k: SolvedDrive(k, leds, drives[k], float(np.sqrt(squared[k][0] / max(squared[k][1], 1e-30))), unseen, names, weights) for k in keys
    }


def _nnls_normal(gram: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """argmin_{x ≥ 0} ||A x − b||² from its normal equations (AᵀA, Aᵀb): NNLS on the Cholesky factor R (AᵀA = RᵀR,
    ||A x − b||² = ||R x − R⁻ᵀ Aᵀb||² + const). A tiny ridge keeps an LED no row sees from making AᵀA singular."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import nnls

    ridge = 1e-9 * max(float(np.trace(gram)) / len(gram), 1e-30)
    r = cholesky(gram + ridge * np.eye(len(gram)), lower=False)
    x, _ = nnls(r, solve_triangular(r, rhs, trans="T"), maxiter=50 * len(gram))
    return x


def _camera_rows(source: Source, plan: CameraPlan, olat_keys: list[int], keys: list[int]):
    """(OLAT block means (rows, LEDs, 3), the frames' (rows, frames, 3), the frames' saturated blocks (rows, frames))
    of one camera: blocks wholly inside the subject's mask, none that a saturated OLAT pixel touches."""
    images = source.images[plan.index]
    mask = mask_at_source(frame_mask(source, plan, keys[0]), plan) > 0.5
    block = max(1, mask.shape[1] // BLOCK_COLUMNS)
    inside = np.flatnonzero(_blocks(mask[..., None].astype(np.float32), block)[..., 0] > 0.999)
    if inside.size > ROWS_PER_CAMERA:  # a fixed subset: a rerun, or another shard, solves on the same rows
        inside = np.sort(np.random.default_rng(plan.index).choice(inside, ROWS_PER_CAMERA, replace=False))

    def reduced(key: int) -> tuple[np.ndarray, np.ndarray]:
        rgb, clipped, _ = read_image(images[key])
        return _blocks(rgb, block)[inside], _blocks(clipped[..., None].astype(np.float32), block)[inside, 0] > 0

    read = list(threaded(reduced, olat_keys + keys, f"solve drives: read {plan.camera.name}"))
    olats, frames = read[: len(olat_keys)], read[len(olat_keys) :]
    keep = ~np.any([clipped for _, clipped in olats], axis=0)  # a clipped OLAT pixel only bounds its light
    return (
        np.stack([m for m, _ in olats], axis=1)[keep].astype(np.float32),
        np.stack([m for m, _ in frames], axis=1)[keep].astype(np.float32),
        np.stack([clipped for _, clipped in frames], axis=1)[keep],
    )


def _blocks(image: np.ndarray, block: int) -> np.ndarray:
    """Means over ``block`` × ``block`` tiles (the image cropped to whole tiles), flattened to (tiles, channels)."""
    h, w = (image.shape[0] // block) * block, (image.shape[1] // block) * block
    tiles = image[:h, :w].reshape(h // block, block, w // block, block, image.shape[2])
    return tiles.mean(axis=(1, 3)).reshape(-1, image.shape[2])


def apply_solved_drives(source: Source, plans: list[CameraPlan], cache: Path) -> list[dict]:
    """Every frame of ``source.frames`` whose drive is to be solved (drive ``("solve", key, …)``) given its drive on the
    rig's LEDs (``("solved", drive in the OLATs' units)``), or left out where its OLATs do not explain it
    (:data:`MAX_RESIDUAL`). The light of the source's LEDs that the rig leaves out (HumanOLAT's door) is subtracted from
    the frame's images (``source.subtracted``), so that the frame shows what the rig's LEDs gave. ``plans``: the
    training cameras. The solve is kept in ``cache`` (a resumed import, or another shard, reads it back). Returns
    what the import report says of each frame."""
    keys = [d[1] for _, _, d in source.frames if isinstance(d, tuple) and d[0] == "solve"]
    if not keys:
        return []
    if cache.is_file():
        solved = {r["key"]: SolvedDrive.from_record(r) for r in read_json(cache)}
    else:
        solved = solve_drives(source, plans, keys)
        atomic_write_text(cache, json.dumps([s.record() for s in solved.values()]) + "\n")
    rig = source.led_numbers or list(range(len(source.leds)))
    outside = set(solved[keys[0]].leds) - set(rig)
    olat_of = {int(led): key for led, key in zip(source.order, source.olat_keys, strict=True)}
    kept, rows = [], []
    for key, entry, drive in source.frames:
        if not (isinstance(drive, tuple) and drive[0] == "solve"):
            kept.append((key, entry, drive))
            continue
        s, index = solved[key], {n: i for i, n in enumerate(solved[key].leds)}
        row = {"image": key, "frame": entry.frame, "what": drive[2], "sequence": entry.sequence, "residual": s.residual}
        row |= {"outside_share": s.share(outside), "unseen": s.unseen}
        rows.append(row | {"cameras": s.cameras, "drive_mean": s.drive.mean(axis=0).tolist()})
        if s.residual > MAX_RESIDUAL or not s.drive.any():
            why = "no light" if not s.drive.any() else f"{100 * s.residual:.0f} % of its light unexplained"
            rows[-1]["left_out"] = why
            logger.warning("%s: frame %06d left out: its OLATs do not give it (%s)", source.folder, key, why)
            continue
        kept.append((key, entry, ("solved", s.drive[[index[n] for n in rig]])))
        if outside:
            source.subtracted[key] = [(olat_of[n], s.drive[index[n]]) for n in sorted(outside) if s.drive[index[n]].any()]
    source.frames = kept
    return rows


def plot_solved_drives(stage, frames: list, path: Path) -> None:
    """Each solved frame's drive on the rig's LEDs, seen from the stage centre (azimuth against elevation), each LED a
    dot in its drive's colour (scaled per frame to its brightest LED): what lit the frame, at a glance."""
    from gra_mi.core.io import pyplot, save_figure

    solved = [(Path(entry.pattern).stem, drive[1]) for _, entry, drive in frames if isinstance(drive, tuple) and drive[0] == "solved"]
    if not solved:
        return
    d = stage.led_directions()
    azimuth, elevation = np.degrees(np.arctan2(d[:, 0], d[:, 2])), np.degrees(np.arcsin(np.clip(d[:, 1], -1, 1)))
    plt = pyplot()
    columns = min(5, len(solved))
    rows = -(-len(solved) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(3.2 * columns, 1.9 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.set_facecolor("0.15")
        ax.set_xticks([])
        ax.set_yticks([])
    for ax, (name, drive) in zip(axes.ravel(), solved, strict=False):
        colour = np.clip(drive / max(float(drive.max()), 1e-12), 0, 1) ** (1 / 2.2)
        ax.scatter(azimuth, elevation, c=colour, s=9)
        ax.set_xlim(-180, 180)
        ax.set_ylim(-90, 90)
        ax.set_title(name, fontsize=8)
    fig.suptitle("LED drives solved from the OLATs (azimuth → , elevation ↑; each frame scaled to its brightest LED)", fontsize=9)
    fig.tight_layout()
    save_figure(fig, path)
