"""How many cameras `--align-cameras` needs placed, and how closely: a calibration in a frame of its own (a COLMAP
reconstruction's, at a scale of its own) moved into the LEDs' frame by a few of its cameras' measured places.

The paper's rig (40 cameras on four rings at 1.8 m, 1024×540) is taken out of the LEDs' frame by a random similarity
(scale 0.1–10, any rotation, a few metres away); n of its cameras, drawn at random, are placed at their true
positions plus a measuring error (Gaussian, σ per axis); :func:`gra_mi.capture.alignment.align_cameras` moves the
whole rig back. Scored on every camera: how far its centre lands from the truth and how far it images points of the
subject's volume (a 0.6 × 1.8 × 0.4 m box on the stage) from where the true camera does; beside them the RMS the
import report states (how closely the placed cameras land), which a user sees. *Swaps found*: two placed cameras'
names exchanged (a mix-up when measuring), the share of draws the import refuses. The draws are the same for every
row (one seed).

    .venv/bin/python benchmarks/align_cameras.py [--draws 200] [--write docs/results/align-cameras.md]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark

PLACED = (3, 4, 6, 10, 40)
SIGMA_MM = (0.0, 1.0, 3.0, 10.0)
SUBJECT_BOX = (np.array([-0.3, 0.1, -0.2]), np.array([0.3, 1.9, 0.2]))  # metres, the stage's frame


def own_frame(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    return float(np.exp(rng.uniform(np.log(0.1), np.log(10.0)))), Rotation.random(random_state=rng).as_matrix(), rng.uniform(-3, 3, 3)


def calibration_in(stage, frame) -> list:
    """The rig's cameras as CalibCameras moved into ``frame`` (scale, rotation, translation) out of the stage's."""
    from gra_mi.capture.source_files import CalibCamera

    scale, turn, shift = frame
    return [CalibCamera(np.eye(3), np.column_stack([turn @ c.rotation, scale * turn @ c.position + shift]), []) for c in stage.cameras]


def imaged(stage, cameras: list, points: np.ndarray) -> np.ndarray:
    """(C, P, 2) pixels of ``points`` through each of the stage's cameras posed as ``cameras`` (camera-to-world 3 × 4)."""
    from dataclasses import replace

    posed = [
        replace(cam, camera_to_world=np.vstack([moved.extrinsic, [0.0, 0.0, 0.0, 1.0]]))
        for cam, moved in zip(stage.cameras, cameras, strict=True)
    ]
    return np.array([cam.project(points)[:, :2] for cam in posed])


def one_draw(stage, rng, placed: int, sigma: float, points: np.ndarray, truth_px: np.ndarray, work: Path, swap: bool) -> dict | None:
    """One alignment from ``placed`` random cameras' noisy places: its errors, or None where the import refuses it."""
    from gra_mi.capture.alignment import align_cameras
    from gra_mi.core.errors import GraMiInputError

    names = [c.name for c in stage.cameras]
    chosen = rng.choice(len(names), placed, replace=False)
    places = {names[k]: stage.cameras[k].position + rng.normal(0.0, sigma, 3) for k in chosen}
    if swap:
        a, b = names[chosen[0]], names[chosen[1]]
        places[a], places[b] = places[b], places[a]
    (work / "places.txt").write_text("".join(f"{n} {' '.join(f'{x:.17g}' for x in p)}\n" for n, p in places.items()))
    try:
        moved, _, said = align_cameras(work / "places.txt", names, calibration_in(stage, own_frame(rng)))
    except GraMiInputError:
        return None
    centres = np.linalg.norm(np.array([c.extrinsic[:, 3] for c in moved]) - np.array([c.position for c in stage.cameras]), axis=1)
    pixels = np.linalg.norm(imaged(stage, moved, points) - truth_px, axis=-1)
    return {"centre_mm": 1000 * centres.max(), "px": pixels.ravel(), "rms_mm": 1000 * said["rms"]}


def measure(run: BenchmarkRun) -> str:
    from gra_mi.stage.lightstage import default_lightstage

    stage, draws = default_lightstage(), run.args.draws
    rng = np.random.default_rng(0)
    points = rng.uniform(*SUBJECT_BOX, (200, 3))
    truth_px = imaged(stage, calibration_in(stage, (1.0, np.eye(3), np.zeros(3))), points)
    rows = []
    for placed in PLACED:
        for sigma in SIGMA_MM:
            found = [
                one_draw(stage, np.random.default_rng([placed, k]), placed, sigma / 1000, points, truth_px, run.work, False)
                for k in range(draws)
            ]
            kept = [f for f in found if f is not None]
            swaps = [one_draw(stage, np.random.default_rng([placed, k]), placed, sigma / 1000, points, truth_px, run.work, True) is None
                     for k in range(draws)]  # fmt: skip
            px = np.concatenate([f["px"] for f in kept]) if kept else np.array([np.nan])
            rows.append(
                f"| {placed} | {sigma:g} | {100 * (1 - len(kept) / draws):.0f} % | {np.median([f['rms_mm'] for f in kept]):.2f} | "
                f"{np.median([f['centre_mm'] for f in kept]):.2f} / {np.percentile([f['centre_mm'] for f in kept], 95):.2f} | "
                f"{np.median(px):.3f} / {np.percentile(px, 95):.3f} / {px.max():.3f} | {100 * np.mean(swaps):.0f} % |"
            )
    return "\n".join(
        [
            "# Aligning a calibration by its cameras' places (`--align-cameras`)",
            "",
            f"Generated by `benchmarks/align_cameras.py` ({run.stamp('the paper rig: 40 cameras, 1024×540')}).",
            "",
            "The paper's rig (40 cameras on four rings at 1.8 m) taken out of the LEDs' frame by a random similarity (scale "
            "0.1–10, any rotation, a few metres away); n of its cameras, drawn at random, placed at their true positions "
            "plus a measuring error (Gaussian, σ per axis); `align_cameras` (what `gra-mi import --align-cameras` runs) "
            "moves the whole rig back. Scored on every camera of the rig, placed or not, against the truth.",
            "",
            f"{draws} draws per row. *refused*: draws the import refused (a camera landing over 2 % of the placed cameras' "
            "extent from its place). *stated RMS*: the report's `alignment.rms` (median). *worst centre*: the rig's worst "
            "camera centre per draw, median / 95th percentile. *pixels*: every camera's image of the subject's points, "
            "median / 95th percentile / worst. *swaps found*: two placed cameras' names exchanged (a mix-up when measuring), "
            "the share of draws refused.",
            "",
            "| placed cameras | σ (mm) | refused | stated RMS (mm) | worst centre (mm) | pixels (1024 wide) | swaps found |",
            "|---|---|---|---|---|---|---|",
            *rows,
        ]
    )


def arguments(parser) -> None:
    parser.add_argument("--draws", type=int, default=200, help="Random draws per row (default 200).")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, mitsuba=False)
