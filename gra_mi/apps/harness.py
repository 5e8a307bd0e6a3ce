"""The one harness every script in ``benchmarks/`` runs through, and ``gra-mi bench`` times with.

A benchmark is a function from a :class:`BenchmarkRun` to its Markdown page. The harness gives it:

- its arguments: the benchmark's own plus ``--write PAGE`` (the page, stamped, also written there: docs/results/…),
  ``--work DIR`` (keep intermediate files there; default a temporary folder, removed after) and ``--variant``;
- the runtime it needs (the Mitsuba variant with gra-mi's plugins, the torch device), started once;
- timing side by side in one run (:func:`side_by_side`: calls alternated, so a noisy machine slows them alike; the
  asynchronous Dr.Jit and CUDA queues drained around each call), and :func:`timed` for one call;
- the stamp (:meth:`BenchmarkRun.stamp`: commit, preset, machine, variant, date) and the published page;
- the scenes several benchmarks share (:func:`walking_scene`).

Run a benchmark as ``python benchmarks/NAME.py --help``; nothing needs ``sys.path`` changed (gra-mi is installed).
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gra_mi.core.stamp import publish_page, run_stamp, stamp_said


def drain_queues() -> None:
    """Wait for the asynchronous work a timed call queued: Dr.Jit's (LLVM or CUDA) and torch's CUDA stream."""
    if "drjit" in sys.modules:
        sys.modules["drjit"].sync_thread()
    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def timed(fn: Callable[[], object], repeats: int = 1, warmup: bool = False) -> tuple[float, object]:
    """(median seconds over ``repeats`` calls, the last call's value); ``warmup``: one untimed call first (kernels
    compiled, caches filled)."""
    value = fn() if warmup else None
    times = []
    for _ in range(repeats):
        drain_queues()
        start = time.perf_counter()
        value = fn()
        drain_queues()
        times.append(time.perf_counter() - start)
    return statistics.median(times), value


# A command is started by this small launcher, which reports what wait4 says of it: Linux counts the memory a process
# had at exec (its forked copy of its parent) in its peak, so a command started straight from a benchmark's process
# would report the benchmark's memory wherever that was larger than its own.
_LAUNCHER = """import json, os, subprocess, sys, tempfile, time
with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
    start = time.perf_counter()
    process = subprocess.Popen(sys.argv[1:], stdout=out, stderr=err)
    _, status, usage = os.wait4(process.pid, 0)
    seconds = time.perf_counter() - start
    out.seek(0), err.seek(0)
    print(json.dumps({"seconds": seconds, "peak_mb": usage.ru_maxrss / 1024.0, "code": os.waitstatus_to_exitcode(status),
                      "stdout": out.read(), "stderr": err.read()[-4000:]}))
"""


def run_measured(command: list[str], env: dict | None = None) -> dict:
    """Run ``command`` in its own process: {"seconds": its wall time, "peak_mb": its own peak resident memory,
    "stdout": what it printed}. A command that fails raises RuntimeError with the end of its stderr."""
    import json
    import subprocess

    done = subprocess.run([sys.executable, "-c", _LAUNCHER, *command], env=env, capture_output=True, text=True, check=True)
    result = json.loads(done.stdout)
    if result["code"] != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({result['code']}): {result['stderr']}")
    return result


def gra_mi_command(*args: str) -> list[str]:
    """A `gra-mi` command line run by this Python (its environment, whatever is on PATH)."""
    return [sys.executable, "-m", "gra_mi.cli", *args]


def side_by_side(calls: dict[str, Callable[[], object]], repeats: int, warmup: bool = True) -> dict[str, float]:
    """Median seconds of each call, the calls alternated ``repeats`` times (after one untimed call each)."""
    if warmup:
        for call in calls.values():
            call()
    times: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            times[name].append(timed(call)[0])
    return {name: statistics.median(t) for name, t in times.items()}


RENDER_COLUMNS = ("integrator", "ms per image", "mean relative error", "bias of the mean")
"""The columns of :func:`render_row` and :func:`truth_of`'s rows."""


def direct_integrator(emitter_samples: int = 1, bsdf_samples: int = 0):
    """Mitsuba's ``direct`` with these samples per pass, the reference the scene-file benchmarks measure against.
    Several emitter samples over-weight delta lights (Mitsuba 3 #1861): give them only scenes without."""
    import mitsuba as mi

    return mi.load_dict({"type": "direct", "emitter_samples": emitter_samples, "bsdf_samples": bsdf_samples})


def truth_of(scene, integrator, spp: int, sensor: int = 0) -> tuple:
    """(the truth: ``scene`` at ``spp`` samples, seed 1; the row of its own noise: the same again at seed 2, against it)."""
    import mitsuba as mi
    import numpy as np

    from gra_mi.render.near_field_cases import image_error

    truth, again = (np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed, sensor=sensor)) for seed in (1, 2))
    error, bias = image_error(again, truth)
    return truth, ("the truth again, another seed (its own noise)", "–", f"{100 * error:.2f} %", f"{100 * bias:+.2f} %")


def render_row(label: str, scene, integrator, spp: int, truth, sensor: int = 0) -> tuple:
    """A speed-against-error row for one integrator on ``scene`` (its ``sensor``): (label, ms per image (the median of
    3 renders after one that compiles), mean relative error and bias of the mean against ``truth``)."""
    import mitsuba as mi
    import numpy as np

    from gra_mi.render.near_field_cases import image_error

    def render():
        return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=11, sensor=sensor))

    seconds, image = timed(render, repeats=3, warmup=True)
    error, bias = image_error(image, truth)
    return (label, f"{1000 * seconds:.0f}", f"{100 * error:.2f} %", f"{100 * bias:+.2f} %")


def integrator_rows(scenes: dict, truth_integrator, truth_spp: int, candidates: list[tuple]) -> list[tuple]:
    """Speed against error, :data:`RENDER_COLUMNS` after the scene's name: on each of ``scenes`` (name → scene), each
    candidate (label, integrator, spp) against the truth (``truth_integrator`` at ``truth_spp``), then the truth's
    own noise."""
    rows = []
    for name, scene in scenes.items():
        truth, noise = truth_of(scene, truth_integrator, truth_spp)
        rows += [(name, *render_row(label, scene, integrator, spp, truth)) for label, integrator, spp in candidates]
        rows.append((name, *noise))
    return rows


def table_page(
    title: str, script: str, stamp: str, rows: list[tuple], notes: list[str] = (), columns=("measurement", "value", "note")
) -> str:
    """The page of a benchmark that measures a list of things: a title, the stamp line, ``notes``, one table."""
    lines = [f"# {title}", "", f"Generated by `benchmarks/{script}` ({stamp}).", ""] + [line for note in notes for line in (note, "")]
    return "\n".join(lines + markdown_table(columns, rows))


def markdown_table(columns, rows: list[tuple]) -> list[str]:
    """The lines of a Markdown table: a header of ``columns``, then one line per row."""
    return ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)] + [
        "| " + " | ".join(str(c) for c in row) + " |" for row in rows
    ]


def walking_scene(folder: Path, frames: int, num_cameras: int = 1) -> Path:
    """The scene several benchmarks time: the anny body walking for ``frames`` frames in the 331-LED rig with
    ``num_cameras`` cameras at the demo's (the `small` preset's) image size."""
    from gra_mi.capture.synthetic import PRESETS
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import write_rig, write_scene_file
    from gra_mi.subject.anny_body import anny_sequence
    from gra_mi.subject.sequence import save_sequence

    small = PRESETS["small"]
    stage = default_lightstage(
        num_leds=331, num_cameras=num_cameras, width=small.width, height=small.height, camera_distance=small.camera_distance
    )
    write_rig(stage, folder / "rig")
    save_sequence(anny_sequence(["walk"], frames), folder / "subject")
    return write_scene_file(folder / "scene.xml", folder / "rig", folder / "subject")


def envmap_drives(stage, count: int = 3) -> list:
    """LED radiant intensities (L, 3) of ``count`` seeded environment maps on ``stage``: the new lightings a cached
    view is timed under (one per call, so nothing after the lighting is reused)."""
    from gra_mi.stage.envmap import envmap_to_leds
    from gra_mi.stage.envmap_library import envmap_from_seed

    return [envmap_to_leds(envmap_from_seed(s, 64)[0], stage).radiant_intensity(stage) for s in range(count)]


def relightnet_calls(model, resolution: int, image: tuple[int, int], device: str) -> tuple[Callable, Callable]:
    """(forward, training step) of ``model`` on random inputs at ``resolution``² UV, the step's output rasterised into
    ``image`` (W, H) and compared by L1, then AdamW: what the RelightNet timings measure."""
    import torch

    from gra_mi.render.bridge import IN_CHANNELS, sample_texture

    x, mask = torch.rand(1, IN_CHANNELS, resolution, resolution, device=device), torch.ones(1, 1, resolution, resolution, device=device)
    env = torch.rand(1, 3, 16, 32, device=device)
    grid = torch.rand(1, image[1], image[0], 2, device=device) * 2 - 1
    target = torch.rand(1, 3, image[1], image[0], device=device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)

    def forward():
        with torch.inference_mode():
            model(x, env, mask)

    def step():
        model.train()
        optimizer.zero_grad(set_to_none=True)
        (sample_texture(model(x, env, mask), grid) - target).abs().mean().backward()
        optimizer.step()
        model.eval()

    return forward, step


@dataclass
class BenchmarkRun:
    args: argparse.Namespace
    work: Path  # --work, or a temporary folder removed after the run
    variant: str | None  # the Mitsuba variant started (None: the benchmark runs no Mitsuba)

    def stamp(self, preset: str) -> str:
        """The page's stamp line: commit, ``preset``, machine, variant, date."""
        return stamp_said(run_stamp(preset=preset, variant=self.variant))

    def beside_page(self, name: str) -> Path | None:
        """Where a file that goes with the page (a picture) is written: beside ``--write``, or nowhere without it."""
        return None if self.args.write is None else Path(self.args.write).with_name(name)


def run_benchmark(
    doc: str, measure: Callable[[BenchmarkRun], str], *, arguments: Callable[[argparse.ArgumentParser], None] | None = None,
    mitsuba: bool = True, variant: str | None = "llvm_ad_rgb", torch: bool = False, argv: list[str] | None = None,
) -> None:  # fmt: skip
    """Parse the arguments, start the runtime, run ``measure`` and publish its page. ``variant``: the Mitsuba variant the
    benchmark's tables are made with (None: the GPU's where one works); ``torch``: start the torch device too."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", type=Path, default=None, help="Also write the stamped Markdown page here (docs/results/…).")
    parser.add_argument("--work", type=Path, default=None, help="Keep intermediate files here (default: a temporary folder).")
    if mitsuba:
        said = variant or "cuda_ad_rgb where a CUDA GPU works, else llvm_ad_rgb"
        parser.add_argument("--variant", default=variant, help=f"Mitsuba variant. Default: {said}.")
    if arguments is not None:
        arguments(parser)
    args = parser.parse_args(argv)
    from gra_mi.render.runtime import start_runtime

    started = start_runtime(getattr(args, "variant", None), mitsuba=mitsuba, torch=torch)
    work = args.work or Path(tempfile.mkdtemp(prefix="gra_mi_bench_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        page = measure(BenchmarkRun(args, work, started.variant if mitsuba else None))
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    publish_page(page.rstrip("\n") + "\n", args.write)
