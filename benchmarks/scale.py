"""How capture, fit and relight grow with the capture: wall time and peak memory (the process's maximum resident set)
at 1×, 4× and 16× the `small` capture's training frames, each stage a `gra-mi` command line in its own process.

The captures are `small`'s rig (8 cameras at 256×135, 6 for training; 331 LEDs; UV 256²) with 8 × k training frames
of the walk (so 48 × k training views) and 2 test frames, rendered with `--renderer onebounce` (the path tracer would
take hours at 16×; the fit's cost does not depend on how its images were made). The fit runs streamed with
`--batch-views 8` (the paper's 8 accumulation steps) and 60 steps at every size, and full batch (every view held)
where it fits the benchmark's time. The relight renders every frame from one held-out camera under an envmap with the
fitted maps, reading the fit's visibility cache. Shards: the 4× relight as 2 processes at once against 1.

    .venv/bin/python benchmarks/scale.py [--scales 1,4,16] [--write docs/results/scale.md]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

from gra_mi.apps.harness import BenchmarkRun, gra_mi_command, run_benchmark, run_measured

BATCH_VIEWS = 8
FULL_BATCH_UP_TO = 4  # scales at which the full-batch fit is run too (at 16× it alone would take longer than the rest)
PAPER = {"cameras": 40, "frames": 28_420, "pixels": 1024 * 540}
SMALL_PIXELS = 256 * 135


def scaled_preset(scale: int) -> str:
    """Register `small` with ``scale`` × its training frames (in this process) and return its name."""
    from gra_mi.capture.synthetic import PRESETS

    name = f"small_x{scale}"
    PRESETS[name] = replace(PRESETS["small"], name=name, frames_per_clip=8 * scale, test_frames_per_clip=2)
    return name


CAPTURE_JOB = "--capture-job"  # the child process whose time and memory run_scale measures: SCALE OUT


def capture_job(scale: int, out: Path) -> None:
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture
    from gra_mi.render.runtime import start_runtime

    start_runtime("llvm_ad_rgb")
    generate_capture(out, CaptureConfig(preset=scaled_preset(scale), renderer="onebounce", measure_noise=False))


def measured(command: list[str]) -> dict:
    """Run ``command`` quietly; its wall time and peak resident memory."""
    result = run_measured(command, env={**os.environ, "GRA_MI_QUIET": "1"})
    return {"seconds": result["seconds"], "peak_mb": result["peak_mb"]}


def run_scale(scale: int, work: Path, envmap: Path, stages: set[str]) -> list[dict]:
    cap, fit = work / f"capture_x{scale}", work / f"fit_x{scale}"
    views, frames = 48 * scale, 8 * scale
    rows = []
    if "capture" in stages:
        rows.append({"stage": "capture", "scale": scale, "units": frames + 2, "unit": "frame"})
        rows[-1] |= measured([sys.executable, __file__, CAPTURE_JOB, str(scale), str(cap)])
    fit_args = ["fit", str(cap), "--iterations", "60", "--overwrite"]
    if "fit" in stages:
        rows.append({"stage": f"fit, --batch-views {BATCH_VIEWS}", "scale": scale, "units": views, "unit": "view"})
        rows[-1] |= measured(gra_mi_command(*fit_args, "--batch-views", str(BATCH_VIEWS), "--out", str(fit)))
    if "full-batch" in stages and scale <= FULL_BATCH_UP_TO:
        rows.append({"stage": "fit, full batch", "scale": scale, "units": views, "unit": "view"})
        rows[-1] |= measured(gra_mi_command(*fit_args, "--out", str(work / f"fit_full_x{scale}")))
    if "relight" not in stages:
        return rows
    relight = ["relight", str(cap / "scene.xml"), "--frames", "all", "--cameras", "cam06", "--envmap", str(envmap)]
    relight += ["--albedo", str(fit / "albedo.exr"), "--roughness", str(fit / "roughness.exr"), "--vis-cache", str(fit / "cache")]
    rows.append({"stage": "relight", "scale": scale, "units": frames + 2, "unit": "frame"})
    rows[-1] |= measured(gra_mi_command(*relight, "--out", str(work / f"relight_x{scale}")))
    if scale == 4:
        rows.append(shards_compared(relight, work, frames + 2))
    return rows


def shards_compared(relight: list[str], work: Path, frames: int) -> dict:
    """The relight again as 1 process, then as 2 shards started together (both after the run above: the same warm
    kernel and visibility caches)."""
    one = measured(gra_mi_command(*relight, "--out", str(work / "relight_one")))
    env = {**os.environ, "GRA_MI_QUIET": "1"}
    start = time.perf_counter()
    procs = [
        subprocess.Popen(gra_mi_command(*relight, "--out", str(work / "relight_shards"), "--shard", f"{i}/2"), env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        for i in range(2)
    ]  # fmt: skip
    for p in procs:
        _, status, _ = os.wait4(p.pid, 0)
        if os.waitstatus_to_exitcode(status) != 0:
            raise RuntimeError(f"a relight shard failed: {p.stderr.read()[-2000:]}")
    return {"stage": "shards", "scale": 4, "units": frames, "one": one["seconds"], "two": time.perf_counter() - start}


def markdown(rows: list[dict], stamp: str) -> str:
    lines = [
        "# Scale: time and memory as the capture grows",
        "",
        f"Generated by `benchmarks/scale.py` ({stamp}). Each stage is a `gra-mi` command in its own process; *peak*",
        "is its maximum resident memory (Python, Dr.Jit's LLVM backend and its caches included). `small` ×k: 8k training",
        "frames × 6 training cameras = 48k views at 256×135, one-bounce ground truth; the fit: 60 Adam steps of",
        f"{BATCH_VIEWS} views (streamed from scratch files) or of every view (full batch, all held).",
        "",
        "| stage | scale | frames / views | time (s) | per frame / view (s) | peak memory (MB) | peak vs 1× |",
        "|---|---|---|---|---|---|---|",
    ]
    shards = [r for r in rows if r["stage"] == "shards"]
    rows = [r for r in rows if r["stage"] != "shards"]
    base = {r["stage"]: r["peak_mb"] for r in rows if r["scale"] == 1}
    for r in rows:
        ratio = r["peak_mb"] / base[r["stage"]] if r["stage"] in base else float("nan")
        lines.append(
            f"| {r['stage']} | {r['scale']}× | {r['units']} {r['unit']}s | {r['seconds']:.0f} | {r['seconds'] / r['units']:.2f} "
            f"| {r['peak_mb']:.0f} | {ratio:.2f} |"
        )
    for r in shards:
        lines += [
            "",
            f"Shards: the {r['scale']}× relight ({r['units']} frames) took {r['one']:.1f} s as one process and {r['two']:.1f} s as",
            f"two shards started together ({r['two'] / r['one']:.2f}×): on 2 cores Dr.Jit already spreads one process over both",
            "(docs/results/shards.md); shards pay off across GPUs and machines.",
        ]
    lines += ["", *estimate(rows)]
    return "\n".join(lines) + "\n"


def estimate(rows: list[dict]) -> list[str]:
    """The paper's data from the largest streamed fit's per-view cost (an estimate, stated as one)."""
    fits = [r for r in rows if r["stage"].startswith("fit, --batch")]
    if not fits:
        return []
    largest = max(fits, key=lambda r: r["scale"])
    per_view = largest["seconds"] / largest["units"]
    views = PAPER["cameras"] * PAPER["frames"]
    cpu_hours = per_view * views * PAPER["pixels"] / SMALL_PIXELS / 3600
    return [
        "## Estimate for the paper's data (not measured)",
        "",
        f"The paper's capture is {PAPER['cameras']} cameras × {PAPER['frames']:,} frames = {views:,} views at 1024×540. At the "
        f"{largest['scale']}× fit's {per_view:.2f} s per view on 2 cores, scaled by pixels ({PAPER['pixels'] / SMALL_PIXELS:.0f}×: "
        f"the per-view passes are per pixel and per observed texel), one pass-set over every view is about {cpu_hours:,.0f} CPU hours. ",
        "Its memory is the streamed fit's, set by the batch (above), plus one 512² atlas. On a GPU the per-view work is the "
        "LED loop and ray casts that `docs/results/speed.md` measured at 40–60× the 2-core CPU (visibility of a new "
        f"frame 33 ms on an H100 against 1.6–2 s here): about {cpu_hours / 50:,.0f} GPU hours on one GPU, "
        f"{cpu_hours / 200:,.0f} on a node of 4 and {cpu_hours / 400:,.0f} on 8 with the per-frame stages sharded "
        "(`--shard`) and the fit on torchrun's processes (each its share of the frames; fit-processes.md), one "
        "process per GPU.",
    ]


def measure(run: BenchmarkRun) -> str:
    from gra_mi.core.io import write_exr
    from gra_mi.stage.envmap_library import reference_map

    write_exr(run.work / "sun.exr", reference_map("sun", 64))
    rows = []
    for scale in (int(s) for s in run.args.scales.split(",")):
        rows += run_scale(scale, run.work, run.work / "sun.exr", set(run.args.stages.split(",")))
        print(json.dumps(rows[-1]), flush=True)
    return markdown(rows, run.stamp("small ×k"))


def arguments(parser) -> None:
    parser.add_argument("--scales", default="1,4,16", help="Multiples of `small`'s training frames, comma-separated.")
    parser.add_argument(
        "--stages", default="capture,fit,full-batch,relight",
        help="What to measure, comma-separated: capture, fit (streamed), full-batch (fit), relight (with shards at 4×). "
        "Without capture, the captures (and for relight, the fits) must already be in --work.",
    )  # fmt: skip


if __name__ == "__main__":
    if sys.argv[1:2] == [CAPTURE_JOB]:
        capture_job(int(sys.argv[2]), Path(sys.argv[3]))
    else:
        run_benchmark(__doc__, measure, arguments=arguments)
