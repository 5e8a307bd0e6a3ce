"""Speed of the material fit, side by side with a tutorial-style Mitsuba fit (prb + Adam on the textures).

    .venv/bin/python benchmarks/fit.py [--preset small] [--capture DIR] [--budget 600] [--write docs/results/fit.md]

Its page's table:
  - gra-mi's fit on the preset's capture: total time, time to reach 1.01× its final L1;
  - one fit pass (all LEDs, one view) at the ``full`` preset's sizes (512² UV, 1024×540), and the time of one pass
    over all of full's training views, extrapolated;
  - the tutorial-style fit: Mitsuba's ``prb`` integrator rendering the textured ``gra_microfacet`` scene with
    sampling, an L1 image loss and Adam on the albedo/roughness textures, one training view per step, until it
    reaches gra-mi's final error (or the time budget); both errors are measured the same way (mean L1 over covered
    pixels of a fixed set of training views rendered by ``gra_onebounce``).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, table_page, timed


def ours_fit(capture, preset: str) -> tuple[object, object, float, list[tuple]]:
    """gra-mi's fit of ``capture``: (fitter, result, its seconds, the table's rows)."""
    from gra_mi.fit.materials import FitConfig, MaterialFitter

    rows = []
    fitter = MaterialFitter(capture, FitConfig())
    t = time.perf_counter()
    result = fitter.fit()
    t_fit = time.perf_counter() - t
    curve = [(s, loss) for s, loss, _ in result.loss_curve if np.isfinite(loss)]
    final = curve[-1][1]
    t_reach = next(s for s, loss in curve if loss <= 1.01 * final)
    n_views = len(fitter.train) * len(capture.train_cameras)
    rows.append(
        (
            f"gra-mi fit, `{preset}` ({n_views} views, {fitter.atlas.num_texels} texels)",
            f"{t_fit:.1f} s",
            f"final L1 {final:.5f} ({result.loss_measure})",
        )
    )
    rows.append(("  time to reach 1.01× its final L1", f"{t_reach:.1f} s", ""))
    return fitter, result, t_fit, rows


def full_pass_rows(capture_dir: Path, work: Path) -> list[tuple]:
    """One view pass at the ``full`` preset's sizes, and one pass over all its training views, extrapolated."""
    from gra_mi.capture.synthetic import PRESETS
    from gra_mi.core.io import atomic_write_text
    from gra_mi.fit.materials import FitConfig
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.lightstage import default_lightstage, uniform_pattern
    from gra_mi.stage.scene import LightstageScene, subject_scene_xml, write_rig

    rows = []
    full = PRESETS["full"]
    stage = default_lightstage(width=full.width, height=full.height)
    write_rig(stage, work / "full_rig")
    atomic_write_text(work / "full_scene.xml", subject_scene_xml("full_rig", str((capture_dir / "subject").resolve())))
    ls_full = LightstageScene.load(work / "full_scene.xml")
    relighter = Relighter(ls_full, full.uv_resolution)
    relighter.visibility(0)
    intensities = uniform_pattern(stage, 0.5)
    views = iter(range(4))  # one untimed pass, then three timed ones on views 1, 2, 0
    t_pass, _ = timed(lambda: relighter.render(0, next(views) % 3, intensities), repeats=3, warmup=True)
    full_views = (full.num_cameras - full.eval_cameras) * len(full.train_clips) * full.frames_per_clip
    cfg = FitConfig()
    passes = cfg.roughness_candidates + 1 + cfg.irls_iterations + (2 * cfg.iterations if cfg.solver == "adam" else 0)
    rows.append(
        (
            f"one view pass at `full` sizes ({relighter.atlas.num_texels} texels at {full.uv_resolution}², {full.width}×{full.height})",
            f"{1e3 * t_pass:.0f} ms",
            "shade + rasterise, visibility cached (a fit pass shades and projects)",
        )
    )
    rows.append(
        (
            f"one iteration (pass over all {full_views} training views of `full`), extrapolated",
            f"{t_pass * full_views:.0f} s",
            f"the fit makes about {passes} such passes (an Adam iteration shades with the roughness derivative: ~2)",
        )
    )
    return rows


def image_error(capture, fitter, result, work: Path, eval_views: int):
    """(scene with textured ``gra_microfacet``, its texture keys, the lighting per frame, the error measure): mean L1
    over covered pixels of ``eval_views`` training views rendered by ``gra_onebounce``, for any maps."""
    import mitsuba as mi

    from gra_mi.capture.dataset import load_observation
    from gra_mi.core.io import atomic_write_text, write_exr
    from gra_mi.stage.scene import LightstageScene, subject_scene_xml

    ls = LightstageScene.load(capture.folder / "scene.xml")
    stage = ls.stage
    n_views = len(fitter.train) * len(capture.train_cameras)
    views = [(f, c) for f in fitter.train for c in capture.train_cameras][:: max(1, n_views // eval_views)][:eval_views]
    observed = {(f.frame, c): load_observation(capture, c, f.frame) for f, c in views}
    write_exr(work / "albedo.exr", np.full_like(result.albedo, 0.5))
    write_exr(work / "rough.exr", np.full_like(result.roughness, 0.5))
    bsdf = (
        '<bsdf type="gra_microfacet" id="material">'
        f'<texture type="bitmap" name="albedo"><string name="filename" value="{work / "albedo.exr"}"/></texture>'
        f'<texture type="bitmap" name="roughness"><string name="filename" value="{work / "rough.exr"}"/><boolean name="raw" value="true"/></texture></bsdf>'
    )
    atomic_write_text(capture.folder / "scene_bench.xml", subject_scene_xml("rig", "subject", bsdf_xml=bsdf))
    scene = LightstageScene.load(capture.folder / "scene_bench.xml")
    keys = {name: next(k for k in scene.params.keys() if k.endswith(f"{name}.data")) for name in ("albedo", "roughness")}
    onebounce = mi.load_dict({"type": "gra_onebounce"})
    lighting = {f.frame: capture.lighting(stage, f) for f in fitter.train}

    def image_l1(albedo, roughness) -> float:
        scene.params[keys["albedo"]] = mi.TensorXf(albedo)
        scene.params[keys["roughness"]] = mi.TensorXf(roughness)
        scene.params.update()
        errors = []
        for f, c in views:
            scene.set_frame(f.frame)
            scene.set_led_intensities(lighting[f.frame])
            img = np.array(mi.render(scene.scene, sensor=scene.sensor_index(c), integrator=onebounce, spp=4, seed=1))
            gt = observed[(f.frame, c)]
            mask = (img[..., 3] > 0.99) & (gt[..., 3] > 0.99)
            errors.append(np.abs(img[..., :3] - gt[..., :3])[mask].mean())
        return float(np.mean(errors))

    return scene, keys, lighting, image_l1


def tutorial_fit(capture, fitter, result, probe, ours: float, budget: float) -> tuple[float | None, float, int, float]:
    """A Mitsuba-tutorial fit: ``prb`` + Adam on the textures, one view per step, until it reaches ``ours`` or the
    budget: (seconds when it reached it or None, seconds spent, steps, its best error)."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.capture.dataset import load_observation

    scene, keys, lighting, image_l1 = probe
    prb = mi.load_dict({"type": "prb", "max_depth": 2})
    params = scene.params
    params[keys["albedo"]] = mi.TensorXf(np.full_like(result.albedo, 0.5))
    params[keys["roughness"]] = mi.TensorXf(np.full_like(result.roughness, 0.5))
    params.update()
    opt = mi.ad.Adam(lr=0.02)
    for k in keys.values():
        opt[k] = params[k]
    params.update(opt)
    train_views = [(f, c) for f in fitter.train for c in capture.train_cameras]
    gts = {}
    start = time.perf_counter()
    reached, step, history = None, 0, []
    while time.perf_counter() - start < budget:
        f, c = train_views[step % len(train_views)]
        if (f.frame, c) not in gts:
            gts[(f.frame, c)] = mi.TensorXf(load_observation(capture, c, f.frame))
        scene.set_frame(f.frame)
        scene.set_led_intensities(lighting[f.frame])
        params.update(opt)
        img = mi.render(scene.scene, params, sensor=scene.sensor_index(c), integrator=prb, spp=4, seed=step)
        gt = gts[(f.frame, c)]
        loss = dr.mean(dr.abs(img[..., :3] - gt[..., :3]) * gt[..., 3:4], axis=None)
        dr.backward(loss)
        opt.step()
        for k in keys.values():
            opt[k] = dr.clip(opt[k], 0.0, 1.0)
        params.update(opt)
        step += 1
        if step % len(train_views) == 0:  # one epoch: measure
            elapsed = time.perf_counter() - start
            err = image_l1(np.array(opt[keys["albedo"]]), np.array(opt[keys["roughness"]]))
            start += time.perf_counter() - start - elapsed  # measuring is not part of the fit's time
            history.append((elapsed, err))
            if err <= ours:
                reached = elapsed
                break
    t_tutorial = reached if reached is not None else time.perf_counter() - start
    return reached, t_tutorial, step, min((e for _, e in history), default=float("nan"))


def measure(run: BenchmarkRun) -> str:
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture

    args = run.args
    capture_dir = args.capture or run.work / "capture"
    t = time.perf_counter()
    if args.capture is None:
        generate_capture(capture_dir, CaptureConfig(preset=args.preset))
    t_capture = time.perf_counter() - t
    capture = Capture.load(capture_dir)
    fitter, result, t_fit, rows = ours_fit(capture, args.preset)
    rows += full_pass_rows(capture_dir, run.work)
    probe = image_error(capture, fitter, result, run.work, args.eval_views)
    ours = probe[3](result.albedo, result.roughness)
    rows.append(("gra-mi fit, image-space L1 on the evaluation views", f"{ours:.5f}", ""))
    reached, t_tutorial, step, best = tutorial_fit(capture, fitter, result, probe, ours, args.budget)
    rows.append(
        (
            f"tutorial-style fit (`prb` + Adam, spp 4, one view per step), {step} steps",
            f"{t_tutorial:.0f} s",
            f"best image L1 {best:.5f}" + ("" if reached else " (budget ran out before gra-mi's error)"),
        )
    )
    speedup = t_tutorial / t_fit
    rows.append(("speedup at equal final error", f"{'≥ ' if reached is None else ''}{speedup:.1f}×", "goal ≥ 10×"))
    title = f"Material fit — capture `{args.preset}` ({capture.renderer}, made in {t_capture:.0f} s)"
    return table_page(title, "fit.py", run.stamp(args.preset), rows)


def arguments(parser) -> None:
    parser.add_argument("--preset", choices=["tiny", "small"], default="small", help="Capture preset to fit. Default: small.")
    parser.add_argument("--capture", type=Path, default=None, help="Reuse an existing capture of that preset (default: generate one).")
    parser.add_argument("--budget", type=float, default=600.0, help="Time budget of the tutorial-style fit in seconds. Default: 600.")
    parser.add_argument("--eval-views", type=int, default=6, help="Training views used to measure both fits' error. Default: 6.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, variant=None)
