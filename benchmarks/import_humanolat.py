"""Import speed and memory of a full-size HumanOLAT pose, measured on a synthetic stand-in at the dataset's image size.

A static pose (tiny subject, 24 LEDs) rendered by 2 cameras at 810×1440 and written in HumanOLAT's layout (8-bit
AVIF) is imported in a fresh process at scale 1 and 0.25; the time per image and the peak memory are measured and the
time extrapolated to a full pose (40 cameras × 343 images). Prints a Markdown table.

    .venv/bin/python benchmarks/import_humanolat.py [--work DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FULL_IMAGES = 40 * 343  # cameras × images of a pose (the count; about 13,700)

IMPORT = """
import json, resource, sys, time
from gra_mi.render.runtime import start_runtime
start_runtime("llvm_ad_rgb")
from gra_mi.capture.humanolat import import_humanolat
from gra_mi.capture.source import ImportConfig
start = time.perf_counter()
capture = import_humanolat(sys.argv[1], sys.argv[2], ImportConfig(scale=float(sys.argv[3]), uv_resolution=64))
seconds = time.perf_counter() - start
images = len(capture.frames) * (len(capture.train_cameras) + len(capture.eval_cameras))
print(json.dumps({"seconds": seconds, "images": images, "peak_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def stand_in(work: Path) -> Path:
    from gra_mi.capture import synthetic
    from gra_mi.capture.humanolat import write_humanolat
    from gra_mi.render.runtime import start_runtime

    start_runtime("llvm_ad_rgb")
    shrunk = dict(subject="tiny", num_leds=24, num_cameras=2, eval_cameras=1, width=810, height=1440, uv_resolution=64)
    shrunk |= dict(envmap_height=16, spp=4, indirect_spp=4, envmap_frames=2, camera_distance=1.2)
    synthetic.PRESETS["olat"] = dataclasses.replace(synthetic.PRESETS["olat"], **shrunk)
    capture = synthetic.generate_capture(work / "native", synthetic.CaptureConfig(preset="olat", measure_noise=False))
    return write_humanolat(capture, work / "layout")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=None, help="Folder for the stand-in (default: a temporary one).")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="gra_mi_import_bench_"))
    start = time.perf_counter()
    subject = stand_in(work)
    print(f"stand-in written in {time.perf_counter() - start:.0f} s: {subject}", file=sys.stderr)
    rows = []
    for scale in (1.0, 0.25):
        out = work / f"imported_{scale}"
        done = subprocess.run([sys.executable, "-c", IMPORT, str(subject), str(out), str(scale)], capture_output=True, text=True)
        if done.returncode:
            sys.exit(done.stderr)
        m = json.loads(done.stdout.strip().splitlines()[-1])
        per = m["seconds"] / m["images"]
        rows.append((scale, m["images"], per, per * FULL_IMAGES / 3600, m["peak_mib"]))
    print("| scale | images imported | s / image | a full pose (40 × 343), extrapolated | peak memory |")
    print("|---|---|---|---|---|")
    for scale, images, per, hours, peak in rows:
        print(f"| {scale:g} | {images} | {per:.3f} | {hours:.1f} h | {peak:.0f} MiB |")


if __name__ == "__main__":
    main()
