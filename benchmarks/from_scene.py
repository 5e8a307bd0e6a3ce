"""A stage a user wrote as a Mitsuba scene (scenes/user_stage/scene.xml: 2 cameras, 40 point LEDs, the tiny body with
gra-mi's BSDF), made a gra-mi lightstage by `gra-mi from-scene` and relit under the scene's own LEDs: speed against
error, beside Mitsuba rendering the file as it is.

Per camera, the truth is Mitsuba's `direct` rendering the user's file at 4096 spp (seed 1; its own noise: seed 2
against it). Candidates: `gra-mi relight` of the written stage (UV space; a new frame traces its visibility once, a
further view of it is shaded and rasterised only), `gra_onebounce` on the user's file, Mitsuba's `direct` at 16 to
1024 spp. Error: mean relative error and the bias of the mean over the subject's pixels (image_error). The
conversion's own time is given above the table.

    .venv/bin/python benchmarks/from_scene.py [--write docs/results/from-scene.md]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.apps.harness import RENDER_COLUMNS, BenchmarkRun, direct_integrator, render_row, run_benchmark, table_page, timed, truth_of

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "user_stage" / "scene.xml"
TRUTH_SPP = 4096
DIRECT_SPP = (16, 64, 256, 1024)


def stage_of(run: BenchmarkRun) -> tuple[float, Path]:
    """(seconds the conversion took, the written stage's folder)."""
    from gra_mi.capture.scene_stage import stage_from_scene, write_scene_stage

    folder = run.work / "stage"
    seconds, _ = timed(lambda: write_scene_stage(stage_from_scene(SCENE), folder))
    return seconds, folder


def relight_rows(folder: Path, camera: str, other: str, truth: np.ndarray) -> list[tuple]:
    """gra-mi's relight of the stage into ``camera``: a new frame (a fresh relighter: visibility traced, then the view),
    and a further view of a frame traced for the ``other`` camera. Each a median of 3 fresh relighters after one."""
    from gra_mi.core.io import read_exr
    from gra_mi.render.near_field_cases import image_error
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.lightstage import load_pattern
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(folder / "scene.xml")
    maps = {name: read_exr(folder / f"{name}.exr")[..., : 3 if name == "albedo" else 1] for name in ("albedo", "roughness")}
    drive = load_pattern(ls.stage, folder / "lighting.json")  # as `gra-mi relight --pattern` reads it
    rows = []
    for label, primed in (("gra-mi relight, a new frame (visibility + view)", None), ("gra-mi relight, another view", other)):
        times, view = [], None
        for _ in range(4):
            relighter = Relighter(ls, albedo=maps["albedo"], roughness=maps["roughness"])
            if primed:
                relighter.render(0, primed, drive)  # traced: the timed call shades and rasterises only
            seconds, view = timed(lambda r=relighter: r.render(0, camera, drive))
            times.append(seconds)
        error, bias = image_error(view.image, truth)
        rows.append((label, f"{1000 * np.median(times[1:]):.0f}", f"{100 * error:.2f} %", f"{100 * bias:+.2f} %"))
    return rows


def measure(run: BenchmarkRun) -> str:
    import mitsuba as mi

    convert, folder = stage_of(run)
    scene = mi.load_file(str(SCENE), parallel=False)
    rows = []
    names = [sensor.id() for sensor in scene.sensors()]
    for index, name in enumerate(names):
        truth, noise = truth_of(scene, direct_integrator(), TRUTH_SPP, sensor=index)
        rows += [(name, *row) for row in relight_rows(folder, name, names[index - 1], truth)]
        onebounce = mi.load_dict({"type": "gra_onebounce"})
        rows.append((name, *render_row("gra_onebounce on the file, 16 spp", scene, onebounce, 16, truth, sensor=index)))
        rows += [(name, *render_row(f"Mitsuba direct, {n} spp", scene, direct_integrator(), n, truth, sensor=index)) for n in DIRECT_SPP]
        rows.append((name, *noise))
    notes = [
        f"`gra-mi from-scene` read the scene and wrote the stage (rig, subject, lighting, the albedo baked from its PNG) in "
        f"{convert:.2f} s. Each row renders one camera's image under the scene's own 40 LEDs; ms per image is the median of "
        "3 renders after one that compiles (gra-mi relight: the median of 3 fresh relighters after one).",
    ]
    return table_page("Results: a user's own stage, relit by gra-mi and by Mitsuba", "from_scene.py", run.stamp("scenes/user_stage"),
                      rows, notes, columns=("camera", *RENDER_COLUMNS))  # fmt: skip


if __name__ == "__main__":
    run_benchmark(__doc__, measure)
