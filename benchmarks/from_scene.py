"""A stage a user wrote as a Mitsuba scene (scenes/user_stage/scene.xml: 2 cameras, 40 point LEDs, the tiny body with
gra-mi's BSDF), made a gra-mi lightstage by `gra-mi from-scene` and relit under the scene's own LEDs: speed against
error, beside Mitsuba rendering the file as it is.

Per camera, the truth is Mitsuba's `direct` rendering the user's file at 4096 spp (seed 1; its own noise: seed 2
against it). Candidates: `gra-mi relight` of the written stage (UV space; a new frame traces its visibility once, a
further view of it is shaded and rasterised only), `gra_onebounce` on the user's file, Mitsuba's `direct` at 16 to
1024 spp. Error: mean relative error and the bias of the mean over the subject's pixels (image_error). The
conversion's own time is given above the table.

Then the same stage in a set (a floor, a room's wall, a lamp, a pole before a camera): gra-mi's relight of the stage
`from-scene` writes with the set, and of the stage without it (what it wrote before it kept the set), against Mitsuba's
`direct` on the file with the set, scored where each camera sees the subject first.

Then the stage photographed, as a capture on it would be: the scene with its films at twice the size and a third
sensor between the two (held out), path-traced by Mitsuba's `path` at max_depth 3 (with the light reflected once
more between the body's parts, glossy and diffuse, which gra-mi's one bounce leaves out and its `--bounces 2` adds
diffusely) under all LEDs at once and each LED alone, imported with `gra-mi import mitsuba` and fitted with
`gra-mi fit`. The fitted maps are scored against the scene's own (the albedo baked from its PNG, roughness 0.45) on
the texels the training cameras see, beside a constant (the true maps' median); two held-out lightings (a key light,
a rim light) are relit from the held-out and a training camera with the fitted, the constant and the true maps,
against the photographs.

    .venv/bin/python benchmarks/from_scene.py [--write docs/results/from-scene.md]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.apps.harness import (
    RENDER_COLUMNS,
    BenchmarkRun,
    direct_integrator,
    markdown_table,
    render_row,
    run_benchmark,
    table_page,
    timed,
    truth_of,
)
from gra_mi.eval.photographed_stage import HELD_OUT, HELD_OUT_LIGHTINGS, PHOTO_SPP, photograph, photographed_stage, stage_lightings

SCENE = Path(__file__).resolve().parent.parent / "scenes" / "user_stage" / "scene.xml"
TRUTH_SPP = 4096
DIRECT_SPP = (16, 64, 256, 1024)
SET_SHAPES = """    <shape type="rectangle" id="floor"><transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/>
        <translate y="0.44"/></transform></shape>
    <shape type="rectangle" id="wall"><transform name="to_world"><scale value="3"/><translate z="-2.4"/></transform></shape>
    <shape type="sphere" id="lamp"><point name="center" x="0.75" y="1.85" z="0.45"/><float name="radius" value="0.18"/></shape>
    <shape type="cylinder" id="pole"><point name="p0" x="0.1" y="0.44" z="1.3"/><point name="p1" x="0.1" y="2.2" z="1.3"/>
        <float name="radius" value="0.03"/></shape>
"""


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


def relight_section(run: BenchmarkRun) -> str:
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


def set_scene(folder: Path) -> Path:
    """The user's stage with a set: a floor just under the feet, a wall behind the LEDs (a room's), a lamp between the
    key LEDs and the body and a pole in front of the camera `front`."""
    import shutil

    folder.mkdir(parents=True, exist_ok=True)
    for name in ("body.obj", "albedo.png"):
        shutil.copyfile(SCENE.parent / name, folder / name)
    (folder / "scene.xml").write_text(SCENE.read_text().replace("</scene>", SET_SHAPES + "</scene>"))
    return folder / "scene.xml"


def set_section(run: BenchmarkRun) -> str:
    """gra-mi's relight of the stage with its set and of the stage without it against Mitsuba on the file with the set,
    scored on the pixels where each camera sees the subject first (whole pixels: the set's borders left out)."""
    import mitsuba as mi
    from scipy.ndimage import binary_erosion

    from gra_mi.capture.scene_stage import stage_from_scene, write_scene_stage
    from gra_mi.render.near_field_cases import image_error
    from gra_mi.render.scene_file import subject_pixels

    path = set_scene(run.work / "set_user")
    write_scene_stage(stage_from_scene(path), run.work / "set_stage")
    _, bare = stage_of(run)
    scene = mi.load_file(str(path), parallel=False)
    names, rows = [sensor.id() for sensor in scene.sensors()], []
    for index, name in enumerate(names):
        truth, again = (
            np.array(mi.render(scene, integrator=direct_integrator(), spp=TRUTH_SPP, seed=seed, sensor=index)) for seed in (1, 2)
        )
        truth[..., 3] = binary_erosion(subject_pixels(scene, index))  # image_error scores where the truth's alpha is 1
        for label, folder in (
            ("with its set", run.work / "set_stage"),
            ("without its set (as from-scene wrote it before: no shadows, nothing hidden)", bare),
        ):
            row = relight_rows(folder, name, names[index - 1], truth)[0]
            rows.append((name, f"gra-mi relight of the stage {label}, a new frame", *row[1:]))
        rows.append((name, *render_row("Mitsuba direct, 1024 spp", scene, direct_integrator(), 1024, truth, sensor=index)))
        error, bias = image_error(again, truth)
        rows.append((name, "the truth again, another seed (its own noise)", "–", f"{100 * error:.2f} %", f"{100 * bias:+.2f} %"))
    lines = ["", "## The same stage in a set", "", "The scene with a floor just under the feet, a room's wall behind the "
             "LEDs, a lamp between the key LEDs and the body and a pole in front of the camera `front` (scored where "
             "each camera sees the subject first: Mitsuba's own sensor rays; whole pixels). `from-scene` keeps them as "
             "the stage's set: they shadow the subject and hide it.", ""]  # fmt: skip
    return "\n".join(lines + markdown_table(("camera", *RENDER_COLUMNS), rows))


def import_and_fit(run: BenchmarkRun) -> tuple[Path, Path, dict, dict[str, float]]:
    """(capture, fit folder, the scene's true maps, seconds per step) of photographs of the stage."""
    from gra_mi.capture.mitsuba_capture import MitsubaOptions, import_mitsuba
    from gra_mi.capture.scene_stage import stage_from_scene
    from gra_mi.capture.source import ImportConfig
    from gra_mi.fit.materials import FitConfig, run_fit

    path = photographed_stage(SCENE, run.work / "photos")
    stage = stage_from_scene(path)
    lighting, frames = stage_lightings(path.parent, stage.stage, stage.intensities)
    seconds = {}
    seconds["photographs"], _ = timed(lambda: photograph(path, frames))
    photograph(path, frames[-len(HELD_OUT_LIGHTINGS) :], run.work / "again", seed=10_000)  # the held-out ones' own noise
    config = ImportConfig(eval_cameras=[HELD_OUT], uv_resolution=stage.maps["albedo"].shape[0])
    seconds["import"], _ = timed(lambda: import_mitsuba(path.parent, run.work / "capture", config, MitsubaOptions(), lighting))
    seconds["fit"], _ = timed(lambda: run_fit(run.work / "capture", run.work / "fit", FitConfig()))
    return run.work / "capture", run.work / "fit", stage.maps, seconds


def map_rows(fit: Path, truth: dict) -> tuple[list[tuple], dict]:
    """The fitted maps against the true ones on the texels a training camera sees, beside the true maps' median;
    returns the rows and the three map sets (fitted, constant, true) for the relight."""
    from gra_mi.core.io import read_exr, read_exr_channels
    from gra_mi.fit.report import map_errors

    albedo, roughness = read_exr(fit / "albedo.exr")[..., :3], read_exr(fit / "roughness.exr")[..., :1]
    seen = read_exr_channels(fit / "confidence.exr")["views"] > 0
    constant = {name: np.broadcast_to(np.median(m[seen], axis=0), m.shape).copy() for name, m in truth.items()}
    sets = {"fitted": {"albedo": albedo, "roughness": roughness}, "constant (the true maps' median)": constant, "true": truth}
    rows = []
    for label in ("fitted", "constant (the true maps' median)"):
        m = sets[label]
        e = map_errors(m["albedo"][seen], m["roughness"][seen][:, 0], truth["albedo"][seen], truth["roughness"][seen][:, 0])
        rows.append((label, int(seen.sum()), f"{e['albedo_mae']:.4f}", f"{100 * e['albedo_rel_median']:.1f} %",
                     f"{100 * e['albedo_bias']:+.1f} %", f"{e['roughness_mae']:.3f}"))  # fmt: skip
    return rows, sets


def held_out_rows(capture_dir: Path, again_dir: Path, sets: dict, names: tuple[str, ...]) -> tuple[list[tuple], np.ndarray]:
    """Each held-out lighting (``names``, in the capture's order) relit from the held-out and a training camera with
    each map set, with one bounce and with two (`--bounces 2`), against the photograph, beside the photograph taken
    again (``again_dir``, another seed); and a picture: per lighting,
    the held-out camera's photograph beside the fitted maps relit (2 bounces), each lighting at its photograph's
    exposure."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.io import auto_exposure, read_exr
    from gra_mi.render.near_field_cases import image_error
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    capture = Capture.load(capture_dir)
    ls = capture.load_scene()
    relighters = {}
    for bounces in (1, 2):
        first = Relighter(
            ls, albedo=sets["fitted"]["albedo"], roughness=sets["fitted"]["roughness"], transport=LightTransport(bounces=bounces)
        )
        relighters |= {(label, bounces): first.with_maps(m["albedo"], m["roughness"]) for label, m in sets.items()}
    rows, panels = [], []
    for name, entry in zip(names, [f for f in capture.frames if f.split == "test"], strict=True):
        for camera in (HELD_OUT, capture.train_cameras[0]):
            truth = read_exr(capture.image_path(camera, entry.frame))
            again = read_exr(again_dir / "images" / camera / f"{entry.frame:06d}.exr")
            error, bias = image_error(again, truth)
            rows.append(
                (name, camera, "the photograph again, another seed (its own noise)", "–", f"{100 * error:.1f} %", f"{100 * bias:+.1f} %")
            )
            for (label, bounces), relighter in relighters.items():
                view = relighter.render(entry.mesh_frame, camera, capture.lighting(ls.stage, entry))
                error, bias = image_error(view.image, truth)
                rows.append((name, camera, label, bounces, f"{100 * error:.1f} %", f"{100 * bias:+.1f} %"))
                if (camera, label, bounces) == (HELD_OUT, "fitted", 2):
                    panels.append(np.concatenate([truth[..., :3], view.image[..., :3]], axis=1) * auto_exposure(truth[..., :3]))
    return rows, np.concatenate(panels, axis=1)


def fit_section(run: BenchmarkRun) -> str:
    from gra_mi.core.io import write_png

    capture, fit, truth, seconds = import_and_fit(run)
    maps, sets = map_rows(fit, truth)
    lines = ["", "## Photographs on the stage, imported and fitted", "",
             f"Photographs: {len(list((capture / 'images' / HELD_OUT).glob('*.exr')))} lightings × 3 cameras, path-traced (max_depth 3) at "
             f"{PHOTO_SPP} spp in {seconds['photographs']:.0f} s; `import mitsuba` {seconds['import']:.0f} s; `fit` "
             f"{seconds['fit']:.0f} s (its default steps). Training: all LEDs at once and each LED alone, from the scene's "
             f"two cameras; held out: a key light and a rim light (LED patterns) and the camera `{HELD_OUT}`. The "
             "photographs hold the light reflected once more between the body's parts, glossy and diffuse; gra-mi's "
             "`--bounces 2` adds it diffusely.", ""]  # fmt: skip
    lines += markdown_table(("maps", "texels scored", "albedo MAE", "albedo median relative error", "albedo bias", "roughness MAE"), maps)
    lines += ["", "Held-out lightings (error over the subject's pixels of the photograph, image_error):", ""]
    rows, picture = held_out_rows(capture, run.work / "again", sets, HELD_OUT_LIGHTINGS)
    if (path := run.beside_page("from-scene.png")) is not None:
        write_png(path, picture, exposure=1.0)
        lines += [f"![{HELD_OUT}: the photograph, then the fitted maps relit (2 bounces), per held-out lighting: "
                  f"{', '.join(HELD_OUT_LIGHTINGS)}](from-scene.png)", ""]  # fmt: skip
    columns = ("lighting", "camera", "maps", "bounces", "mean relative error", "bias of the mean")
    lines += markdown_table(columns, rows)
    return "\n".join(lines)


def measure(run: BenchmarkRun) -> str:
    return relight_section(run) + "\n" + set_section(run) + "\n" + fit_section(run)


if __name__ == "__main__":
    run_benchmark(__doc__, measure)
