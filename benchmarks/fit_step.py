"""An Adam step of the material fit: its views joined into one LED-loop kernel per ~8 M footprint entries
(``gra_mi.fit.optimize.BATCH_ENTRIES``) against one kernel per view, side by side in one run on one capture.

A step shades every training view's texels at the current roughness (the LED loop with its derivative), averages
them into pixel footprints, and differentiates the weighted L1 back to the maps. One view at a time, a small
capture's views (thousands of texels each) leave a step's host work (tracing, launching, a sync per view) beside
kernels too short to hide it, and a GPU waits on the host; joined, a step is a few large kernels. The page gives,
per step: wall time, the kernels' own time (Dr.Jit's kernel history), the host's share (the difference), how many
kernels and memory operations ran, and how far the two agree.

    .venv/bin/python benchmarks/fit_step.py [--capture DIR | --preset small] [--repeats 5] [--write docs/results/fit-step.md]
"""

from __future__ import annotations

import statistics
import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, drain_queues, run_benchmark, table_page


def optimizer(fitter, joined: bool):
    """(TrainingViews built joined or one batch per view, a MapOptimizer on them at fixed random maps, build seconds)."""
    from gra_mi.fit import optimize as opt
    from gra_mi.fit.prior import SurfaceGraph

    cfg, entries = fitter.config, opt.BATCH_ENTRIES
    opt.BATCH_ENTRIES = entries if joined else 0  # 0: every view its own batch, as before they were joined
    try:
        start = time.perf_counter()
        views = opt.build_batches(fitter, cfg.min_view_cos, progress_bar=False)
        drain_queues()
        seconds = time.perf_counter() - start
    finally:
        opt.BATCH_ENTRIES = entries
    m = fitter.atlas.num_texels
    geom = fitter.relighter.geometry(fitter.train[0].mesh_frame)
    graph = SurfaceGraph.build(np.array(geom.position).T.astype(np.float64), np.array(geom.normal).T.astype(np.float64))
    settings = opt.OptimizeSettings(1, cfg.lr_albedo, cfg.lr_roughness, cfg.smooth_albedo, cfg.smooth_roughness)
    run = opt.MapOptimizer(views, graph, np.ones(m, bool), np.ones(m, bool), settings)
    rng = np.random.default_rng(0)
    run.set_maps(rng.uniform(0.2, 0.8, (m, 3)), rng.uniform(0.15, 0.8, m))
    return views, run, seconds


def step(run) -> tuple[float, float, np.ndarray]:
    """One step's data term with its gradient: (seconds, value, the albedo and roughness gradients)."""
    import drjit as dr

    for key in ("albedo", "roughness"):
        dr.clear_grad(run.adam[key])
    drain_queues()
    start = time.perf_counter()
    value = run.data_term(np.arange(len(run.batches)), with_grad=True)
    drain_queues()
    seconds = time.perf_counter() - start
    grads = [np.array(dr.grad(run.adam[k])).reshape(-1) for k in ("albedo", "roughness")]
    return seconds, value, np.concatenate(grads)


def kernel_time(run) -> tuple[float, int, float]:
    """One more step, with Dr.Jit's kernel history on: (seconds its kernels ran, as the history times them; how many
    ran; the step's wall seconds)."""
    import drjit as dr

    drain_queues()
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        wall = step(run)[0]
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return sum(h.get("execution_time", 0.0) for h in history) / 1e3, len(history), wall


def measure(run: BenchmarkRun) -> str:
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.errors import require_positive
    from gra_mi.fit.materials import FitConfig, MaterialFitter

    require_positive({"repeats": run.args.repeats})
    capture_dir = run.args.capture or make_capture(run.work / run.args.preset, run.args.preset)
    capture = Capture.load(capture_dir)
    fitter = MaterialFitter(capture, FitConfig(), cache_dir=run.work / "cache")
    for frame in fitter.train:  # traced (or read) once, before either build is timed
        fitter.relighter.visibility(frame.mesh_frame, False)
    built = {name: optimizer(fitter, name == "joined") for name in ("joined", "per view")}
    for _, opt_run, _ in built.values():
        step(opt_run)  # kernels compiled, visibility cached
    times: dict[str, list[float]] = {name: [] for name in built}
    results: dict[str, list] = {name: [] for name in built}
    for _ in range(run.args.repeats):
        for name, (_, opt_run, _) in built.items():
            seconds, value, grad = step(opt_run)
            times[name].append(seconds)
            results[name].append((value, grad))
    kernels = {name: kernel_time(opt_run) for name, (_, opt_run, _) in built.items()}
    return page(run, capture_dir, built, times, kernels, results)


def page(run: BenchmarkRun, capture_dir: Path, built: dict, times: dict, kernels: dict, results: dict) -> str:
    views = built["joined"][0]
    lanes = sum(b.count for b in views.in_batches())
    base = statistics.median(times["per view"])
    rows = []
    for name, (training, _, build_seconds) in built.items():
        wall = statistics.median(times[name])
        kernel_seconds, count, traced_wall = kernels[name]
        batches = sum(1 for _ in training.in_batches())
        rows.append(
            (name, batches, count, f"{1e3 * wall:.0f}", f"{1e3 * kernel_seconds:.0f}", f"{1e3 * max(traced_wall - kernel_seconds, 0.0):.0f}",
             f"{wall / base:.2f}", f"{build_seconds:.1f}")
        )  # fmt: skip
    (v_joined, g_joined), (v_view, g_view) = results["joined"][0], results["per view"][0]
    scale = np.abs(g_view).max()
    itself = max(np.abs(g - g_view).max() for _, g in results["per view"]) / scale
    notes = [
        f"Capture `{capture_dir.name}`: {len(views)} training views, {views.n_obs:,} pixels, {lanes:,} lanes "
        f"(a view's texels), maps at fixed random values. Median of {run.args.repeats} steps each, alternated. "
        "Launches: kernels and memory operations; kernels ms: their time in Dr.Jit's kernel history, one more step each; "
        "host ms: that step's wall time less its kernels'.",
        f"The two agree: data term {v_joined:.9f} joined, {v_view:.9f} per view (relative "
        f"{abs(v_joined - v_view) / abs(v_view):.1e}); largest gradient difference "
        f"{np.abs(g_joined - g_view).max() / scale:.1e} of the largest gradient; the per-view step's own repeats differ by up to "
        f"{itself:.1e} (float atomics add in any order).",
    ]
    columns = ("views shaded", "batches", "launches per step", "ms per step", "kernels ms", "host ms", "× per view", "build s")
    return table_page(
        "An Adam step of the material fit: views joined",
        "fit_step.py",
        run.stamp(capture_dir.name),
        rows,
        notes,
        columns,
    )


def make_capture(folder: Path, preset: str) -> Path:
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture

    generate_capture(folder, CaptureConfig(preset=preset))  # resumes a capture already in --work
    return folder


def arguments(parser) -> None:
    from gra_mi.capture.synthetic import PRESETS

    parser.add_argument("--capture", type=Path, default=None, help="A capture folder to time (default: make --preset's).")
    parser.add_argument(
        "--preset", default="small", choices=sorted(PRESETS), help="Capture made in --work when --capture is not given. Default: small."
    )
    parser.add_argument("--repeats", type=int, default=5, help="Steps timed per variant, alternated. Default: 5.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, variant=None)
