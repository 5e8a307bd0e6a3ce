"""A camera that lost one OLAT image: that LED's light from its neighbours' OLATs, against the whole capture's sum and
against leaving the light out.

On a synthetic `olat_quick` pose (331 LEDs, 8 cameras, path-traced), each camera is made to lack the OLAT of every
8th LED in turn (42 LEDs). Its image under each lighting is then summed three ways: from every OLAT (the reference: the
photo that was lost is the one thing missing), with the lost LED's light taken from its k nearest LEDs' OLATs (k = 1,
3, 6; gra-mi's default is 3), and with that light left out. Lightings: the capture's own white, gradient and
environment-map drives and 16 held-out library maps (skies with a sun, rooms), each kept only where the lost LED
carries at most the 2 % of its light gra-mi stands in for (above it gra-mi refuses the camera for that lighting).
Error: relative RMSE over the subject's pixels against the whole sum; beside it, the whole sum against the capture's
own direct render of the same drive (the noise any comparison with a photo of it would see).

    .venv/bin/python benchmarks/missing_olats.py [--capture DIR] [--write docs/results/missing-olats.md]
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark

PRESET = "olat_quick"
LED_STEP = 8  # every 8th LED lost in turn
LIBRARY_MAPS = 16
NEIGHBOUR_COUNTS = (1, 3, 6)


def capture_at(run: BenchmarkRun) -> Path:
    from gra_mi.cli.main import main

    folder = run.args.capture or run.work / "capture"
    if not (folder / "capture.json").is_file():
        assert main(["capture", "--preset", PRESET, "--out", str(folder)]) == 0
    return folder


def lightings(capture, stage, index) -> dict:
    """Name → (L, 3) drive: the capture's non-OLAT frames and the library's held-out maps."""
    from gra_mi.eval.reflectance import EVAL_SEED_OFFSET
    from gra_mi.relightnet.lightings import synthesized_drives

    drives = {}
    for entry in capture.frames:
        if int(entry.frame) not in set(index.frames.tolist()):
            drives[Path(entry.pattern or entry.envmap).stem] = (capture.lighting(stage, entry), entry.frame)
    library = synthesized_drives(stage, "test", LIBRARY_MAPS, index, offset=EVAL_SEED_OFFSET)
    return drives | {f"library_{k:02d}": (d, None) for k, d in enumerate(library)}


def stood_in(index, drive: np.ndarray, position: int, neighbours: int | None) -> np.ndarray:
    """OLAT weights with OLAT ``position`` lost: its light from ``neighbours`` nearest LEDs (None: left out)."""
    from gra_mi.capture.reflectance import moved_to_neighbours

    usable = np.zeros(index.num_leds, bool)
    usable[index.leds] = True
    usable[index.leds[position]] = False
    moved = drive.copy()
    if neighbours is None:
        moved[index.leds[position]] = 0.0
    else:
        moved = moved_to_neighbours(drive, usable, index.directions, index.distances, neighbours)[0]
    weights = moved[index.leds] / np.maximum(index.intensity, 1e-30)
    weights[position] = 0.0
    return weights


def relative_rmse(image: np.ndarray, reference: np.ndarray, subject: np.ndarray) -> float:
    return float(np.sqrt(np.mean((image[subject, :3] - reference[subject, :3]) ** 2) / np.mean(reference[subject, :3] ** 2)))


def measure_camera(capture, index, camera: str, drives: dict) -> tuple[list[dict], dict]:
    """Rows (lost LED, lighting, way → error) of one camera, and each lighting's whole sum against its direct render."""
    from gra_mi.capture.dataset import load_observation
    from gra_mi.capture.reflectance import MISSING_SHARE_LIMIT, ReflectanceField

    rf = ReflectanceField.load(capture, camera, index, progress_bar=False)
    names = list(drives)
    lights = np.stack([drives[n][0] for n in names])
    whole = rf.relight(np.stack([index.weights(d, n, quiet=True) for n, d in zip(names, lights, strict=True)]))
    subject = whole[0][..., 3] > 0.5
    noise = {n: relative_rmse(whole[k], load_observation(capture, camera, drives[n][1]), subject)
             for k, n in enumerate(names) if drives[n][1] is not None}  # fmt: skip
    rows = []
    for position in range(0, len(index.leds), LED_STEP):
        share = lights[:, index.leds[position]].sum(axis=1) / lights.sum(axis=(1, 2))
        kept = [k for k in range(len(names)) if 0 < share[k] <= MISSING_SHARE_LIMIT]
        ways = {f"{k} nearest": k for k in NEIGHBOUR_COUNTS} | {"left out": None}
        errors = {}
        for way, neighbours in ways.items():
            start = time.perf_counter()
            images = rf.relight(np.stack([stood_in(index, lights[k], position, neighbours) for k in kept]))
            errors[way] = ([relative_rmse(image, whole[k], subject) for image, k in zip(images, kept, strict=True)],
                           time.perf_counter() - start)  # fmt: skip
        for j, k in enumerate(kept):
            rows.append({"camera": camera, "led": int(index.leds[position]), "lighting": names[k], "share": float(share[k]),
                         **{way: errors[way][0][j] for way in ways}})  # fmt: skip
    return rows, noise


def measure(run: BenchmarkRun) -> str:
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.reflectance import OlatIndex
    from gra_mi.stage.lightstage import load_calibration

    capture = Capture.load(capture_at(run))
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    index = OlatIndex.of(capture, stage)
    drives = lightings(capture, stage, index)
    rows, noise = [], {}
    for camera in capture.train_cameras + capture.eval_cameras:
        camera_rows, noise[camera] = measure_camera(capture, index, camera, drives)
        rows += camera_rows
    return page(rows, noise, len(drives), run)


def kind(lighting: str) -> str:
    return "library maps (sun, rooms)" if lighting.startswith("library") else "the capture's own drives (white, gradients, maps)"


def page(rows: list[dict], noise: dict, lightings: int, run: BenchmarkRun) -> str:
    ways = [f"{k} nearest" for k in NEIGHBOUR_COUNTS] + ["left out"]
    lines = [
        "# Results: a camera that lost an OLAT image",
        "",
        f"Generated by `benchmarks/missing_olats.py` ({run.stamp(PRESET)}).",
        "",
        f"A synthetic `{PRESET}` pose (331 LEDs, 8 cameras, path-traced). Each camera is made to lack the OLAT of every",
        f"{LED_STEP}th LED in turn; its image under each of {lightings} lightings is summed with that LED's light taken from its k",
        "nearest LEDs' OLATs, or left out, and compared with the sum of every OLAT (relative RMSE over the subject).",
        "Pairs where the lost LED carries more than 2 % of a lighting's light are not summed (gra-mi refuses them).",
        "",
        "| lightings | pairs | lost share (median, max) | " + " | ".join(f"{w}: median / 95th / max" for w in ways) + " |",
        "|---|---|---|" + "---|" * len(ways),
    ]
    for group in ("the capture's own drives (white, gradients, maps)", "library maps (sun, rooms)", "all"):
        chosen = [r for r in rows if group == "all" or kind(r["lighting"]) == group]
        share = np.array([r["share"] for r in chosen])
        cells = []
        for way in ways:
            e = np.array([r[way] for r in chosen])
            cells.append(f"{100 * np.median(e):.3f} / {100 * np.percentile(e, 95):.3f} / {100 * e.max():.3f} %")
        lines.append(f"| {group} | {len(chosen)} | {100 * np.median(share):.2f} / {100 * share.max():.2f} % | " + " | ".join(cells) + " |")
    floor = np.array([v for per_camera in noise.values() for v in per_camera.values()])
    ratio = np.array([r["3 nearest"] / max(r["left out"], 1e-12) for r in rows])
    worst = max(rows, key=lambda r: r["3 nearest"])
    lines += [
        "",
        f"- With 3 neighbours (the default) the error is {100 * np.median(ratio):.0f} % of leaving the light out at the median pair "
        f"({100 * np.percentile(ratio, 95):.0f} % at the 95th percentile); it is the larger error in {100 * np.mean(ratio > 1):.1f} % "
        "of the pairs (the neighbours' shadows and highlights fall where the lost LED's would not).",
        f"- The worst pair: camera {worst['camera']}, LED {worst['led']}, {worst['lighting']} ({100 * worst['share']:.2f} % of its "
        f"light): {100 * worst['3 nearest']:.3f} % with 3 neighbours, {100 * worst['left out']:.3f} % left out.",
        f"- For scale: the whole sum against the capture's own direct render of the same drive differs by {100 * np.median(floor):.1f} % "
        f"(median over cameras and drives; {100 * floor.min():.1f}–{100 * floor.max():.1f} %), the renders' noise.",
    ]
    return "\n".join(lines) + "\n"


def arguments(parser) -> None:
    parser.add_argument(
        "--capture", type=Path, default=None, help=f"An OLAT capture (default: `gra-mi capture --preset {PRESET}` in --work)."
    )


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
