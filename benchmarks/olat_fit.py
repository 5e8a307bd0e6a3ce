"""The material fit from OLATs: how the error of the fitted maps falls with the number of OLATs used.

On a synthetic `olat` capture (331 LEDs, every 10th OLAT held out), `gra-mi fit` is run on evenly spaced subsets of
the training frames (`--frame-step`: about 16, 64 and all ~300 OLATs, the white frame always in), without the
brightness calibration (and, for the smallest subset, with it: what it does to OLAT fits), and each fit's maps are scored against the true maps on the texels ≥ 3 training cameras
see, per region, next to the constant baseline (the true map's median), with the held-out lighting relit from the
held-out cameras. Prints a Markdown page.

    .venv/bin/python benchmarks/olat_fit.py --capture DIR [--steps 19,5,1] [--write docs/results/olat-fit.md]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path


def run(capture: Path, out: Path, step: int, calibrate: bool) -> dict:
    from gra_mi.fit.materials import FitConfig, run_fit

    start = time.perf_counter()
    run_fit(capture, out, FitConfig(frame_step=step, calibrate_brightness=calibrate), overwrite=True)
    record = json.loads((out / "fit.json").read_text())
    return record | {"seconds": time.perf_counter() - start}


def rows_of(record: dict, olats: int, calibrate: bool) -> list[str]:
    rows = []
    relight = record["relight"]["held-out cameras"]
    for region in ("skin", "cloth"):
        ours, base = record["regions"][region], record["baseline"][region]
        rows.append(
            f"| {olats} | {'on' if calibrate else 'off'} | {region} | {record['scored_texels'][region]} "
            f"| {ours['roughness_mae']:.4f} | {base['roughness_mae']:.4f} | {ours['roughness_mae'] / base['roughness_mae']:.2f} "
            f"| {100 * ours['albedo_rel_median']:.1f} % | {100 * base['albedo_rel_median']:.1f} % "
            f"| {relight['psnr']:.2f} | {record['seconds']:.0f} |"
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capture", type=Path, required=True, help="An `olat` capture (`gra-mi capture --preset olat`).")
    parser.add_argument("--steps", default="19,5,1", help="Frame steps to fit with (comma-separated). Default: 19,5,1.")
    parser.add_argument("--calibrated", default="19", help="Frame steps also fitted with the brightness calibration. Default: 19.")
    parser.add_argument("--work", type=Path, default=None, help="Folder for the fits (default: a temporary one).")
    parser.add_argument("--write", type=Path, default=None, help="Also write the Markdown page here.")
    args = parser.parse_args()
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.stamp import run_stamp, stamp_said
    from gra_mi.render.runtime import start_runtime

    variant = start_runtime("llvm_ad_rgb").variant
    work = args.work or Path(tempfile.mkdtemp(prefix="gra_mi_olat_fit_"))
    capture = Capture.load(args.capture)
    train = [f for f in capture.frames if f.split == "train"]
    table = []
    for step in (int(s) for s in args.steps.split(",")):
        olats = sum("olat_" in (f.pattern or "") for f in train[::step])
        for calibrate in (False, True)[: 2 if str(step) in args.calibrated.split(",") else 1]:
            record = run(args.capture, work / f"step{step}_{'cal' if calibrate else 'raw'}", step, calibrate)
            table += rows_of(record, olats, calibrate)
            print(table[-2] + "\n" + table[-1], file=sys.stderr)
    stamp = stamp_said(run_stamp(preset="olat", variant=variant))
    page = "\n".join(
        [
            "# Results: the material fit from OLATs",
            "",
            f"> `benchmarks/olat_fit.py`, {stamp}. Capture: `gra-mi capture --preset olat` (331 LEDs, 6 training",
            "> cameras at 90×160, every 10th OLAT held out), the fit's defaults (closed form, then 60 Adam iterations).",
            "",
            "Scored on the texels ≥ 3 training cameras see, against the true maps; the baseline is the true map's median",
            "(a constant). *ratio*: the fit's roughness MAE over the baseline's. *Calibration*: the fit's brightness",
            "calibration (one albedo gain so the training views' renders hold their captured light). Relit PSNR: the",
            "held-out lighting (the envmap frames and the held-out OLATs) from the held-out cameras, one bounce.",
            "",
            "| OLATs | calibration | region | texels | roughness MAE | constant | ratio | albedo median rel. error | constant | relit PSNR (dB) | fit time (s) |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *table,
        ]
    )
    print(page)
    if args.write:
        args.write.write_text(page + "\n")


if __name__ == "__main__":
    main()
