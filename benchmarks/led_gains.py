"""LED gains measured from a capture's own OLATs (`gra-mi import --estimate-led-gains`): how close to the stage's true
gains, and what the fit and its relighting of held-out cameras under held-out OLATs gain from them.

A synthetic `olat_quick` pose (331 LEDs, path-traced: interreflections, sheen, a diffuse lobe that is not the fit's
model) is written as HumanOLAT ships a pose; for each gain draw, every OLAT photo is scaled by its LED's RGB gain
(uniform in [0.5, 1], as a stage with ageing LEDs of varied colour). Each stage is imported without gains, with
estimated gains and with the true gains as a --led-gains file; each import is fitted (`gra-mi fit`, defaults) and
scored by `gra-mi eval` on the held-out cameras and OLATs. The stage with equal gains is the estimate's floor: what it
finds where there is nothing to find, and whether the fit loses by it.

    .venv/bin/python benchmarks/led_gains.py [--draws 2] [--work DIR] [--write docs/results/led-gains.md]
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark

PRESET = "olat_quick"
LEDS = 331  # the preset's LEDs, HumanOLAT's
TEST_OLAT_EVERY = 10  # every 10th OLAT held out, as the olat demo does
WAYS = ("equal gains (none given)", "estimated (--estimate-led-gains)", "true gains (--led-gains)")


def layout(work: Path) -> tuple[Path, float]:
    """The synthetic pose in HumanOLAT's layout (made once per --work): (its subject folder, the --led-intensity that
    gives the true albedo's scale)."""
    from gra_mi.cli.main import main

    if not (work / "capture" / "humanolat").is_dir():
        assert main(["capture", "--preset", PRESET, "--layout", "humanolat", "--out", str(work / "capture")]) == 0
    subject = next((work / "capture" / "humanolat").iterdir())
    return subject, json.loads((subject / "synthetic.json").read_text())["import_led_intensity"]


def gained(subject: Path, folder: Path, gains: np.ndarray) -> Path:
    """A copy of the layout whose OLAT photos are scaled by their LED's gain (row k: LED k)."""
    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers, read_calib, read_spiral, write_avif
    from gra_mi.capture.source_files import read_image

    target = folder / subject.name
    if target.is_dir():
        return target
    shutil.copytree(subject, folder / "partial" / subject.name)
    leds = len(gains)
    order = read_spiral(folder / "partial" / subject.name / "shared" / "LSX3_light_z_spiral.txt", leds)
    for cam in range(len(read_calib(subject / "shared" / "cameras.calib"))):
        images = images_of(folder / "partial" / subject.name / "POSE_00" / "images_processed" / camera_name(cam))
        for position, number in enumerate(olat_numbers(leds)[0]):
            write_avif(images[number], read_image(images[number])[0] * gains[order[position]])
    (folder / "partial" / subject.name).rename(target)
    return target


def imported(subject: Path, out: Path, intensity: float, *extra: str) -> tuple[Path, float]:
    from gra_mi.cli.main import main

    start = time.perf_counter()
    if not (out / "capture.json").is_file():
        args = ["import", "humanolat", str(subject), "--out", str(out), "--uv-resolution", "128", "--test-olat-every", str(TEST_OLAT_EVERY)]
        assert main([*args, "--led-intensity", str(intensity), *extra]) == 0
    return out, time.perf_counter() - start


def gain_error(capture: Path, truth: np.ndarray | None) -> dict:
    """The capture's gains against ``truth`` (None: equal; row k: the source's LED k) over the LEDs the estimate
    measured, each channel's mean 1."""
    from gra_mi.capture.humanolat import DOOR_LEDS
    from gra_mi.stage.lightstage import load_calibration

    stage = load_calibration(capture / "rig" / "calibration.json")
    report = json.loads((capture / "import_report.json").read_text())["leds"]
    estimate = report.get("estimate") or {}
    numbers = [k for k in range(LEDS) if k not in DOOR_LEDS]  # the rig's LEDs: the door LEDs are left out
    assert len(numbers) == stage.num_leds, (len(numbers), stage.num_leds)
    measured = np.isin(numbers, estimate.get("unmeasured_leds", []), invert=True)
    truth = np.ones((stage.num_leds, 3)) if truth is None else truth[numbers]
    truth, mine = truth / truth[measured].mean(axis=0), stage.gains / stage.gains[measured].mean(axis=0)
    error = np.abs(mine / truth - 1.0)[measured]
    return {"mean": float(error.mean()), "max": float(error.max()), "measured": int(measured.sum()), "estimate": estimate}


def fit_and_score(capture: Path, work: Path) -> dict:
    """`gra-mi fit` and `gra-mi eval` of the microfacet render: PSNR / SSIM over the held-out splits."""
    from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate
    from gra_mi.fit.materials import FitConfig, run_fit

    start = time.perf_counter()
    if not (work / "fit" / "fit.json").is_file():
        run_fit(capture, work / "fit", FitConfig(), overwrite=True)
    seconds = time.perf_counter() - start
    report = evaluate(EvalInputs(capture, work / "fit"), work / "eval", EvalConfig())
    splits = report["stages"]["microfacet"]["splits"]
    return {
        "psnr": float(np.mean([s["psnr"] for s in splits.values()])),
        "ssim": float(np.mean([s["ssim"] for s in splits.values()])),
        "splits": len(splits),
        "fit_seconds": seconds,
    }


def measure(run: BenchmarkRun) -> str:
    subject, intensity = layout(run.work)
    stages = {"equal-gain stage": None} | {
        f"draw {k}": np.random.default_rng(k).uniform(0.5, 1.0, (LEDS, 3)) for k in range(run.args.draws)
    }
    rows = []
    for name, gains in stages.items():
        folder = run.work / name.replace(" ", "_")
        ways = {WAYS[0]: (), WAYS[1]: ("--estimate-led-gains",)}
        if gains is not None:
            (folder / "gains.txt").parent.mkdir(parents=True, exist_ok=True)
            (folder / "gains.txt").write_text("".join(f"{r} {g} {b}\n" for r, g, b in gains))
            ways[WAYS[2]] = ("--led-gains", str(folder / "gains.txt"))
        stage = subject if gains is None else gained(subject, folder / "layout", gains)
        for k, (way, extra) in enumerate(ways.items()):
            capture, seconds = imported(stage, folder / f"import{k}", intensity, *extra)
            score = fit_and_score(capture, folder / f"fit{k}")
            rows.append({"stage": name, "way": way, **gain_error(capture, gains), "score": score, "import_seconds": seconds})
            if way == WAYS[1]:  # the same import fitted and scored again: the spread a difference must beat
                rows[-1]["rerun_psnr"] = fit_and_score(capture, folder / f"fit{k}_again")["psnr"]
            print(json.dumps(rows[-1], default=str), file=sys.stderr)
    (run.work / "rows.json").write_text(json.dumps(rows, indent=1, default=str))
    return page(rows, run)


def page(rows: list[dict], run: BenchmarkRun) -> str:
    lines = [
        "# Results: LED gains measured on the OLATs",
        "",
        f"Generated by `benchmarks/led_gains.py` ({run.stamp(PRESET)}).",
        "",
        f"A synthetic `{PRESET}` pose (331 LEDs, 8 cameras of which 2 held out, path-traced) written as HumanOLAT ships a",
        "pose; each draw scales every OLAT photo by its LED's RGB gain, uniform in [0.5, 1]. Gain error: |gain / truth − 1|",
        "over the LEDs the estimate measured, each channel's mean 1 (a colour common to every LED cannot be told from",
        "the subject's). Model L1: the one-bounce model's relative L1 on the texels several LEDs light, with equal gains →",
        "with the estimate. Fit and score: `gra-mi fit` (defaults) and `gra-mi eval` on the 2 held-out cameras under the",
        f"held-out OLATs (every {TEST_OLAT_EVERY}th; their LEDs' gains were measured on the training cameras' photos).",
        "",
        "| stage | gains | gain error mean | max | LEDs measured | model L1 | estimate (s) | held-out PSNR (dB) | SSIM |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        e, s = r["estimate"], r["score"]
        l1 = f"{100 * e['relative_l1']['equal gains']:.1f} → {100 * e['relative_l1']['estimated']:.1f} %" if e else "—"
        seconds = f"{e['seconds']:.0f}" if e else "—"
        lines.append(
            f"| {r['stage']} | {r['way']} | {100 * r['mean']:.1f} % | {100 * r['max']:.1f} % | {r['measured']} | {l1} | {seconds} "
            f"| {s['psnr']:.2f} | {s['ssim']:.4f} |"
        )
    lines += ["", *reading(rows)]
    return "\n".join(lines) + "\n"


def reading(rows: list[dict]) -> list[str]:
    """What the table says per stage: the estimate's held-out PSNR against equal and true gains."""
    said = []
    for stage in dict.fromkeys(r["stage"] for r in rows):
        psnr = {r["way"]: r["score"]["psnr"] for r in rows if r["stage"] == stage}
        rerun = next(r["rerun_psnr"] for r in rows if r["stage"] == stage and r["way"] == WAYS[1])
        line = f"- {stage}: estimated − equal gains {psnr[WAYS[1]] - psnr[WAYS[0]]:+.3f} dB"
        if WAYS[2] in psnr:
            line += f", estimated − true gains {psnr[WAYS[1]] - psnr[WAYS[2]]:+.3f} dB"
        said.append(line + f"; the estimated import fitted and scored again: {rerun - psnr[WAYS[1]]:+.4f} dB (the run-to-run spread)")
    return said


def arguments(parser) -> None:
    parser.add_argument("--draws", type=int, default=2, help="Gain draws (seeds 0, 1, …). Default: 2.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
