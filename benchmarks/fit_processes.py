"""The material fit over several processes: wall time of `gra-mi fit` as one process and as two (data parallel, every
sum over views crossing them; gra_mi/fit/ranks.py), and how far the two fits' maps are apart.

The two processes are started as torchrun starts them (RANK, WORLD_SIZE, MASTER_ADDR, MASTER_PORT). To stand in for
two machines of one core each, each process is pinned to a core of its own (`taskset`) and compared with one process
pinned to one core; the same fits unpinned show what two processes on one shared 2-core machine give.

Capture: the `small` preset rendered with `--renderer onebounce`; the fit: its defaults on every FRAME_STEP-th training
frame with `--iterations ITERATIONS`, full batch or `--batch-views 8`.

    .venv/bin/python benchmarks/fit_processes.py [--iterations 40] [--frame-step 3] [--write docs/results/fit-processes.md]
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, table_page
from gra_mi.core.shard import free_port


def timed_fit(capture: Path, out: Path, options: list[str], processes: int, pinned: bool) -> float:
    """Seconds until every process of the fit ends (pinned: process k on core k)."""
    shutil.rmtree(out, ignore_errors=True)
    port = str(free_port())
    running = []
    start = time.perf_counter()
    for rank in range(processes):
        env = {**os.environ, "GRA_MI_QUIET": "1"}
        if processes > 1:
            env |= {
                "RANK": str(rank),
                "LOCAL_RANK": str(rank),
                "WORLD_SIZE": str(processes),
                "MASTER_ADDR": "127.0.0.1",
                "MASTER_PORT": port,
            }
        pin = ["taskset", "-c", str(rank)] if pinned else []
        command = [*pin, sys.executable, "-m", "gra_mi.cli", "fit", str(capture), "--out", str(out), *options]
        running.append(subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
    for process in running:
        _, err = process.communicate()
        if process.returncode != 0:
            raise RuntimeError(f"gra-mi fit ({processes} processes) failed: {err[-2000:]}")
    return time.perf_counter() - start


def maps_apart(a: Path, b: Path) -> tuple[float, float]:
    """(largest, mean) absolute difference between two fits' albedo and roughness texels."""
    from gra_mi.core.io import read_exr

    diffs = [np.abs(read_exr(a / f"{m}.exr") - read_exr(b / f"{m}.exr")).ravel() for m in ("albedo", "roughness")]
    every = np.concatenate(diffs)
    return float(every.max()), float(every.mean())


def rows_for(run: BenchmarkRun, capture: Path, label: str, options: list[str]) -> list[tuple]:
    """Pinned (one core each) and on shared cores: both wall times, how far the 2-process fit is from the 1-process one,
    and how far the two 1-process fits (pinned, unpinned) are from each other: the fit's own run-to-run spread."""
    work, times = run.work / label.replace(" ", "_"), {}
    for pinned in (True, False):
        for processes in (1, 2):
            times[pinned, processes] = timed_fit(capture, work / f"{processes}_{pinned}", options, processes, pinned)
    spread = maps_apart(work / "1_True", work / "1_False")
    rows = []
    for pinned, where in ((True, "one core each"), (False, "2 shared cores")):
        one, two = times[pinned, 1], times[pinned, 2]
        apart = maps_apart(work / f"1_{pinned}", work / f"2_{pinned}")
        rows.append((label, where, f"{one:.1f}", f"{two:.1f}", f"{two / one:.2f}", *(f"{a:.1e} / {m:.1e}" for a, m in (apart, spread))))
    return rows


def measure(run: BenchmarkRun) -> str:
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture

    capture = run.work / "capture"
    generate_capture(capture, CaptureConfig(preset="small", renderer="onebounce", measure_noise=False))  # resumes one in --work
    iterations = ["--iterations", str(run.args.iterations), "--frame-step", str(run.args.frame_step)]
    from gra_mi.capture.dataset import Capture

    loaded = Capture.load(capture)
    frames = len([f for f in loaded.frames if f.split == "train"][:: run.args.frame_step])
    width, height = loaded.camera_size(loaded.train_cameras[0])
    views = f"{frames} training frames × {len(loaded.train_cameras)} cameras at {width}×{height}"
    rows = rows_for(run, capture, "every view each step", iterations)
    rows += rows_for(run, capture, "--batch-views 8", [*iterations, "--batch-views", "8"])
    notes = [
        f"The fit: {views}, {run.args.iterations} Adam steps. Wall time of the command line (Python and Mitsuba start-up, the capture read, the closed form, the Adam steps, "
        "rank 0's report). *one core each*: each process pinned to a core of its own, the single process to one core "
        "(two one-core machines against one); *2 shared cores*: unpinned, where one process's Dr.Jit already uses both "
        "cores. *2 vs 1*: the largest / mean difference between the 2-process and the 1-process fit's albedo and "
        "roughness texels; *1 vs 1*: the same between the two 1-process fits (pinned and not), the fit's own run-to-run "
        "spread (Dr.Jit's threads add in any order; the bound the tests allow is 2e-3).",
        "Each process fits every other training frame and traces the visibility of its own frames' poses; the sums "
        "cross the processes once per closed-form pass and per Adam step (two maps of 256² texels). On separate "
        "machines or GPUs the ratio is what *one core each* shows; on one shared machine two processes only compete.",
    ]
    columns = ("fit", "cores", "1 process (s)", "2 processes (s)", "ratio", "2 vs 1: max / mean", "1 vs 1: max / mean")
    return table_page("The material fit over two processes", "fit_processes.py", run.stamp("small (onebounce)"), rows, notes, columns)


def arguments(parser) -> None:
    parser.add_argument("--iterations", type=int, default=40, help="Adam steps of each fit.")
    parser.add_argument("--frame-step", type=int, default=3, help="Fit every FRAME_STEP-th training frame.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
