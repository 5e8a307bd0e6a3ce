"""The light the set reflects onto the subject (``--bounces 2`` in a scene with a floor): accuracy against Mitsuba's own
``path`` on the same shapes, and its cost on the demo's body, side by side in one run.

1. Accuracy: the anny body walking, standing on a floor 2 mm under its feet (grey 0.5 as a stage floor, and white 0.8)
   in the default 331-LED rig, under the `interior` envmap on the LEDs and under a near light by the knee (LEDs off).
   gra-mi at UV 256² with K rays per texel, against ``path`` at max_depth 2 and 3 with the same mesh, maps and floor;
   beside one bounce and two bounces whose floor reflects nothing (what gra-mi rendered before the set reflected light).
   Reference noise: the same ``path`` render with another seed.
2. Cost: per new frame, the bounce operator with and without the floor (its hits on the floor, their cells, the
   cells' visibility); per view of a cached frame under a new envmap, one bounce, two without and two with the floor.
3. Fitting: the shipped user stage on a white floor, photographed by ``path`` (gra_mi.eval.photographed_stage),
   imported and fitted with one bounce, two on a floor made black, and two: the maps against the scene's, and held-out
   lightings and a held-out camera relit against the photographs.

    .venv/bin/python benchmarks/set_light.py [--quick] [--write docs/results/set-light.md]
    .venv/bin/python benchmarks/set_light.py --glossy [--write docs/results/set-light-glossy.md]
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, markdown_table, run_benchmark, side_by_side

SPP = 512
USER_STAGE = Path(__file__).resolve().parent.parent / "scenes" / "user_stage" / "scene.xml"
FLOOR_ON_USER_STAGE = (
    '<transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/><translate y="0.44"/></transform>'
    '<bsdf type="diffuse"><rgb name="reflectance" value="0.8"/></bsdf>'
)
FLOORS = {"grey 0.5": 0.5, "white 0.8": 0.8}
CAMERAS = ("cam00", "cam05")


GLOSSY_FLOORS = {
    "diffuse 0.5": '<bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf>',
    "rough plastic (α 0.2, 0.5)": '<bsdf type="roughplastic"><float name="alpha" value="0.2"/><rgb name="diffuse_reflectance" value="0.5"/></bsdf>',
    "rough metal (α 0.3)": '<bsdf type="roughconductor"><float name="alpha" value="0.3"/></bsdf>',
}  # fmt: skip


GLOSSY_SPP = 1024  # a glossy floor's highlights are rarer paths: `path` at 256 spp was 3 % dark on the tiny rig


def set_models() -> dict:
    """How the set's light at a hit is found, as (its Lambertian reflectance, whether its glossy lobes add their own):
    gra-mi's, and the ways measured against it."""
    from gra_mi.render.bounce import albedo, has_glossy_lobe  # (the functions themselves: the models stand in for them)

    def none(bsdf):
        return has_glossy_lobe(bsdf) & False

    return {
        "diffuse albedo + glossy lobes toward each light (gra-mi)": (albedo, has_glossy_lobe),
        "diffuse albedo only": (albedo, none),
        "every lobe's albedo, spread evenly": (lambda bsdf, si, active, samples: albedo(bsdf, si, active, samples, False), none),
        "eval_diffuse_reflectance (before)": (lambda bsdf, si, active, samples: bsdf.eval_diffuse_reflectance(si, active), none),
    }


def floor_xml(reflectance: float | str) -> str:
    """The floor 2 mm under the feet: a diffuse one of this reflectance, or this BSDF's XML."""
    bsdf = reflectance if isinstance(reflectance, str) else f'<bsdf type="diffuse"><rgb name="reflectance" value="{reflectance}"/></bsdf>'
    return (f'<shape type="rectangle" id="floor"><transform name="to_world"><scale value="4"/><rotate x="1" angle="-90"/>'
            f'<translate y="-0.002"/></transform>{bsdf}</shape>')  # fmt: skip


def stages(folder: Path, frames: int, floors: dict | None = None):
    """The walk in the small rig, as a plain scene and as scenes on each floor (default: :data:`FLOORS` and a black one)."""
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, rig_scene
    from gra_mi.subject.anny_body import anny_sequence

    plain = rig_scene(folder / "walk", anny_sequence(["walk"], frames_per_clip=2 * frames), default_lightstage(width=216, height=312))
    scenes = {"none": LightstageScene.load(plain, spp=1)}
    for k, (name, value) in enumerate((floors or {**FLOORS, "black": 0.0}).items()):
        path = plain.with_name(f"scene_{k}.xml")
        path.write_text(plain.read_text().replace("</scene>", f"{floor_xml(value)}</scene>"))
        scenes[name] = LightstageScene.load(path, spp=1)
    return scenes


def lightings(ls):
    from gra_mi.render.point_light import PointLight
    from gra_mi.stage.envmap import envmap_to_leds
    from gra_mi.stage.envmap_library import reference_map

    leds = envmap_to_leds(reference_map("interior", 64), ls.stage).radiant_intensity(ls.stage)
    lamp = PointLight(np.array([0.35, 0.35, 0.35]), np.full(3, 0.3), radius=0.0)
    return {"interior (LEDs)": (leds, []), "near light by the knee": (np.zeros_like(leds), [lamp])}


def accuracy_rows(scenes, folder: Path, rays_list, frame: int) -> list[dict]:
    from gra_mi.render.path_reference import bounce_errors, path_reference
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    rows = []
    for floor, value in FLOORS.items():
        ls, black = scenes[floor], scenes["black"]
        one = Relighter(ls, 256)
        for lighting, (leds, near) in lightings(ls).items():
            for cam in CAMERAS:
                refs = [path_reference(one, frame, cam, leds, near, d, SPP, folder / "path", set_xml=floor_xml(value)) for d in (2, 3)]
                again = path_reference(one, frame, cam, leds, near, 3, SPP, folder / "path", seed=1, set_xml=floor_xml(value))
                image_one = one.render(frame, cam, leds, near).image
                row = {"floor": floor, "lighting": lighting, "camera": cam, "noise": bounce_errors(refs[0], again, *refs)["bias_more"]}
                dark = Relighter(black, 256, transport=LightTransport(bounces=2)).render(frame, cam, leds, near).image
                row["black"] = bounce_errors(image_one, dark, *refs)
                for rays in rays_list:
                    two = Relighter(ls, 256, transport=LightTransport(bounces=2, bounce_rays=rays)).render(frame, cam, leds, near).image
                    rows.append(row | {"rays": rays, **bounce_errors(image_one, two, *refs)})
    return rows


def _frame_costs(scenes, resolution: int, frame: int, leds: np.ndarray, repeats: int) -> dict:
    import drjit as dr

    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    rel = {
        "one": Relighter(scenes["none"], resolution),
        "two": Relighter(scenes["none"], resolution, transport=LightTransport(bounces=2)),
        "floor": Relighter(scenes["grey 0.5"], resolution, transport=LightTransport(bounces=2)),
    }
    for r in rel.values():
        r.only_for([CAMERAS[0]])  # as `gra-mi relight` renders one camera
    hits = rel["floor"].bounce_operator(frame).set_hits
    cells, _ = hits.geometry

    def set_visibility():
        rel["floor"].set_cache = type(rel["floor"].set_cache)()
        return rel["floor"].set_light(frame, hits, leds, [], False)

    def new_operator(name):
        rel[name]._operators.clear()
        return rel[name].bounce_operator(frame)

    trace = side_by_side({"two": lambda: new_operator("two"), "floor": lambda: new_operator("floor"), "set": set_visibility}, repeats)
    change = iter(range(1, 10**9))  # a new lighting per call: nothing after the first bounce is reused
    views = side_by_side({k: lambda r=r: r.render(frame, CAMERAS[0], leds * (1 + 1e-6 * next(change))) for k, r in rel.items()}, repeats)
    ops = {k: rel[k].bounce_operator(frame) for k in ("two", "floor")}
    return {
        "resolution": resolution, "frame": frame, "entries": ops["two"].entries, "traced": (ops["two"].traced, ops["floor"].traced),
        "hits": hits.count, "cells": dr.width(cells.position), "mb": (ops["two"].nbytes / 2**20, ops["floor"].nbytes / 2**20),
        "op_ms": (1e3 * trace["two"], 1e3 * trace["floor"]), "set_ms": 1e3 * trace["set"],
        "view_ms": tuple(1e3 * views[k] for k in ("one", "two", "floor")),
    }  # fmt: skip


def cost_rows(scenes, resolutions, frames: int, repeats: int) -> list[dict]:
    leds = lightings(scenes["none"])["interior (LEDs)"][0]
    return [_frame_costs(scenes, r, f, leds, repeats) for r in resolutions for f in range(0, 2 * frames, 2)]


def markdown(accuracy: list[dict], cost: list[dict], stamp: str) -> str:
    pct = lambda x: "–" if not np.isfinite(x) else f"{100 * x:+.2f} %"  # noqa: E731
    lines = [
        "# The light the set reflects onto the subject",
        "",
        f"Generated by `benchmarks/set_light.py` ({stamp}).",
        "",
        "## Against Mitsuba's `path` on a floor",
        "",
        "The anny body walking (frame 2), on a floor 2 mm under its feet, in the default 331-LED rig at 216×312; the "
        "body's own colours, roughness 0.5 (gra-mi's default maps), UV 256², the default smoothing. `path` at "
        f"{SPP} spp with `gra_microfacet`, the same maps and the same floor (Mitsuba `diffuse`). *bias*: Σ render / Σ "
        "`path` (max_depth 3) − 1 over the pixels all renders cover (the floor's pixels are not the subject's); *black "
        "floor*: two bounces whose floor reflects nothing, as gra-mi rendered a set before; *blocks*: 8×8 blocks where "
        "Mitsuba's one bounce is ≥ 10 % darker than max_depth 3, the largest error there; *noise*: a second `path` "
        "render (another seed) against the first; *own*: gra-mi's one bounce against `path` max_depth 2 (UV resampling at "
        "256², no bounce involved: a near light's hard shadows are a texel wide).",
        "",
        "| floor | lighting | camera | K | own | bias 1 bounce | 2 bounces, black floor | 2 bounces | blocks | block error 1 / black / 2 | noise |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    size = lambda x: "–" if not np.isfinite(x) else f"{100 * x:.1f} %"  # noqa: E731
    for r in accuracy:
        blocks = f"{size(r['dark_block_error_one'])} / {size(r['black']['dark_block_error_more'])} / {size(r['dark_block_error_more'])}"
        lines.append(
            f"| {r['floor']} | {r['lighting']} | {r['camera']} | {r['rays']} | {pct(r['bias_one_vs_path_one'])} | {pct(r['bias_one'])} | "
            f"{pct(r['black']['bias_more'])} | "
            f"{pct(r['bias_more'])} | {r['dark_blocks']} | {blocks if r['dark_blocks'] else '–'} | {pct(r['noise'])} |"
        )
    lines += [
        "",
        "## Cost on the demo's body",
        "",
        "The same walk on the grey floor against no floor, K = 32 (the default), `interior` on every LED, near field, "
        f"as `gra-mi relight` renders one camera ({CAMERAS[0]}); medians over repeats, side by side in one run. *operator "
        "ms*: a new frame's bounce operator, without / with the floor (its rays that hit the floor are traced again for "
        "their surface); *floor hits*: those rays; *cells*: where the floor's light is computed (SetHits.grouped); *floor "
        "light ms*: the cells' LED visibility and LED sum for a new frame; *view ms*: a cached frame under a new lighting.",
        "",
        "| UV | frame | texels tracing, no floor / floor | body entries | floor hits | cells | MB | operator ms | floor light ms | view ms: 1 bounce / 2 / 2 on the floor |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in cost:
        lines.append(
            f"| {r['resolution']}² | {r['frame']} | {r['traced'][0]:,} / {r['traced'][1]:,} | {r['entries']:,} | {r['hits']:,} | {r['cells']:,} | "
            f"{r['mb'][0]:.1f} / {r['mb'][1]:.1f} | {r['op_ms'][0]:.0f} / {r['op_ms'][1]:.0f} | {r['set_ms']:.0f} | "
            + " / ".join(f"{v:.0f}" for v in r["view_ms"]) + " |"
        )  # fmt: skip
    return "\n".join(lines) + "\n"


def fitted_on_floor(work: Path) -> tuple[Path, dict, dict]:
    """The user's stage on a white floor, photographed (path-traced) and imported; fitted with one bounce, with two on a
    floor made black in the capture's scene (as gra-mi's set reflected nothing) and with two. Returns (capture, the
    scene's true maps, {label: (fit folder, bounces)})."""
    from gra_mi.capture.mitsuba_capture import MitsubaOptions, import_mitsuba
    from gra_mi.capture.scene_stage import stage_from_scene
    from gra_mi.capture.source import ImportConfig
    from gra_mi.eval.photographed_stage import HELD_OUT, HELD_OUT_LIGHTINGS, photograph, photographed_stage, stage_lightings
    from gra_mi.fit.materials import FitConfig, run_fit
    from gra_mi.render.transport import LightTransport

    path = photographed_stage(USER_STAGE, work / "photos", f'<shape type="rectangle" id="floor">{FLOOR_ON_USER_STAGE}</shape>')
    stage = stage_from_scene(path)
    lighting, frames = stage_lightings(path.parent, stage.stage, stage.intensities)
    photograph(path, frames)
    photograph(path, frames[-len(HELD_OUT_LIGHTINGS) :], work / "again", seed=10_000)  # the held-out ones' own noise
    capture = work / "capture"
    import_mitsuba(
        path.parent, capture, ImportConfig(eval_cameras=[HELD_OUT], uv_resolution=stage.maps["albedo"].shape[0]), MitsubaOptions(), lighting
    )
    black = work / "capture_black_floor"
    shutil.copytree(capture, black)
    text = (capture / "scene.xml").read_text()
    (black / "scene.xml").write_text(text.replace('name="reflectance" value="0.8"', 'name="reflectance" value="0"'))
    assert (black / "scene.xml").read_text() != text, "the capture's floor was not found"
    fits = {"1 bounce": (capture, 1), "2 bounces, black floor": (black, 2), "2 bounces": (capture, 2)}
    for label, (source, bounces) in fits.items():
        run_fit(source, work / label, FitConfig(transport=LightTransport(bounces=bounces)))
    return capture, stage.maps, {label: (work / label, bounces) for label, (_, bounces) in fits.items()}


def fit_rows(work: Path) -> tuple[list[tuple], list[tuple]]:
    """The fits' maps against the scene's on the texels the training cameras see, and their held-out relights (each
    with its own bounces, its own floor) against the photographs, beside the photographs taken again."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.io import read_exr, read_exr_channels
    from gra_mi.eval.photographed_stage import HELD_OUT, HELD_OUT_LIGHTINGS
    from gra_mi.fit.report import map_errors
    from gra_mi.render.near_field_cases import image_error
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    capture_dir, truth, fits = fitted_on_floor(work)
    capture = Capture.load(capture_dir)
    maps, held_out = [], []
    tests = [f for f in capture.frames if f.split == "test"]
    for label, (fit, bounces) in fits.items():
        albedo, roughness = read_exr(fit / "albedo.exr")[..., :3], read_exr(fit / "roughness.exr")[..., :1]
        seen = read_exr_channels(fit / "confidence.exr")["views"] > 0
        e = map_errors(albedo[seen], roughness[seen][:, 0], truth["albedo"][seen], truth["roughness"][seen][:, 0])
        maps.append((label, f"{100 * e['albedo_rel_median']:.1f} %", f"{100 * e['albedo_bias']:+.1f} %", f"{e['roughness_mae']:.3f}"))
        scene_of = capture_dir if "black" not in label else capture_dir.with_name("capture_black_floor")
        ls = Capture.load(scene_of).load_scene()
        relighter = Relighter(ls, albedo=albedo, roughness=roughness, transport=LightTransport(bounces=bounces))
        for name, entry in zip(HELD_OUT_LIGHTINGS, tests, strict=True):
            for camera in (HELD_OUT, capture.train_cameras[0]):
                photo = read_exr(capture.image_path(camera, entry.frame))
                error, bias = image_error(relighter.render(entry.mesh_frame, camera, capture.lighting(ls.stage, entry)).image, photo)
                held_out.append((name, camera, label, f"{100 * error:.1f} %", f"{100 * bias:+.1f} %"))
                if label == "1 bounce":  # the photograph again (another seed), scored on the subject's pixels
                    again = read_exr(work / "again" / "images" / camera / f"{entry.frame:06d}.exr")
                    again[..., 3] = photo[..., 3]
                    error, bias = image_error(again, photo)
                    held_out.append((name, camera, "the photograph again (its own noise)", f"{100 * error:.1f} %", f"{100 * bias:+.1f} %"))
    return maps, sorted(held_out, key=lambda r: (r[0], r[1]))


def fit_section(work: Path) -> list[str]:
    maps, held_out = fit_rows(work)
    lines = [
        "",
        "## Photographs on a white floor, imported and fitted",
        "",
        "The shipped user stage (scenes/user_stage: the tiny body, 40 LEDs) on a white floor (0.8) 1 cm under its feet, "
        "photographed as benchmarks/from_scene.py photographs it (Mitsuba's `path`, max_depth 3: the floor's light is in "
        "the photographs; all LEDs, each LED alone; a key and a rim light and the camera `between` held out), imported "
        "with `gra-mi import mitsuba` (the floor comes in as the capture's set) and fitted with `gra-mi fit` (default "
        "steps) at one and two bounces, and at two with the capture's floor made black (what gra-mi modelled before "
        "the set reflected light). Maps on the texels the training cameras see; held-out relights with each fit's own "
        "bounces, over the subject's pixels (image_error).",
        "",
    ]
    lines += markdown_table(("fit", "albedo median relative error", "albedo bias", "roughness MAE"), maps)
    lines += [""] + markdown_table(("lighting", "camera", "maps", "mean relative error", "bias of the mean"), held_out)
    return lines


def glossy_rows(folder: Path) -> list[dict]:
    """Floors of other BSDFs under the walk, two bounces with each way of finding the set's light, against ``path``
    (max_depth 3) on the same floor, and ``path`` again with another seed: per floor, lighting and camera, the biases,
    the floor's hits and what the floor's light costs per lighting."""
    from unittest import mock

    from gra_mi.apps.harness import side_by_side
    from gra_mi.render import bounce
    from gra_mi.render.path_reference import bounce_errors, path_reference
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    scenes, rows = stages(folder, 2, GLOSSY_FLOORS), []
    for floor, bsdf in GLOSSY_FLOORS.items():
        ls = scenes[floor]
        one = Relighter(ls, 256)
        for lighting, (leds, near) in lightings(ls).items():
            for cam in CAMERAS:
                refs = [
                    path_reference(one, 2, cam, leds, near, 3, GLOSSY_SPP, folder / "path", seed=s, set_xml=floor_xml(bsdf)) for s in (0, 1)
                ]
                image_one = one.render(2, cam, leds, near).image
                row = {
                    "floor": floor,
                    "lighting": lighting,
                    "camera": cam,
                    "one": (bounce_errors(image_one, image_one, *refs[:1] * 2)["bias_one"],),
                }
                row["noise"] = (bounce_errors(image_one, refs[1], *refs[:1] * 2)["bias_more"],)
                for name, (reflectance, glossy) in set_models().items():
                    with mock.patch.object(bounce, "albedo", reflectance), mock.patch.object(bounce, "has_glossy_lobe", glossy):
                        two = Relighter(ls, 256, transport=LightTransport(bounces=2))
                        e = bounce_errors(image_one, two.render(2, cam, leds, near).image, *refs[:1] * 2)
                        hits = two.bounce_operator(2).set_hits
                        ms = None  # (timed once per floor: under `interior`, for the first camera's job)
                        if lighting == "interior (LEDs)" and cam == CAMERAS[0]:
                            ms = (
                                1e3
                                * side_by_side({"set": lambda t=two, h=hits, lit=leds: t.set_light(2, h, lit, [], t.far_field)}, 3)["set"]
                            )
                    row[name] = (e["bias_more"], hits.count, int(hits.glossy.sum()), ms)
                rows.append(row)
    return rows


def _pct(x: float) -> str:
    return f"{100 * x:+.1f} %"


def _span(rows: list[dict], key: str) -> str:
    """The range of ``key``'s bias over ``rows``."""
    values = [r[key][0] for r in rows]
    return f"{_pct(min(values))} … {_pct(max(values))}"


def glossy_page(run: BenchmarkRun) -> str:
    models = list(set_models())
    stamp = run.stamp("walk on a floor + small rig")  # (before the measurement: the tree as it ran)
    rows = glossy_rows(run.work)
    lines = [
        "# The light a glossy set reflects onto the subject",
        "",
        f"Generated by `benchmarks/set_light.py --glossy` ({stamp}).",
        "",
        "The walk of set-light.md (frame 2, the default 331-LED rig, UV 256², K = 32, the default smoothing) on a floor of "
        f"three BSDFs, two bounces against Mitsuba's `path` (max_depth 3, {GLOSSY_SPP} spp) on the same floor: the bias "
        "of Σ render / Σ `path` − 1 over the pixels all renders cover. *noise*: `path` with another seed against the first. "
        "The columns are ways of finding the floor's light at a hit: *diffuse albedo + glossy lobes* (gra-mi: a "
        "Lambertian surface of its diffuse lobes' directional albedo toward the ray, plus Mitsuba's own BSDF evaluated "
        "at the hit with only its glossy lobes, toward each LED and near light), *diffuse albedo only* (the glossy light "
        "left out), *every lobe's albedo, spread evenly* (a Lambertian surface of the whole albedo: exact under even "
        "light), *eval_diffuse_reflectance* (Mitsuba's, which gra-mi used before: π f(ω, n) for a BSDF without a "
        "diffuse lobe, unbounded: 100 for a polished metal seen along its normal).",
        "",
        "The range of the bias over the two lightings and two cameras:",
        "",
    ]
    summary = []
    for floor in GLOSSY_FLOORS:
        mine = [r for r in rows if r["floor"] == floor]
        summary.append((floor, *(_span(mine, key) for key in ("one", *models, "noise"))))
    lines += markdown_table(("floor", "1 bounce", *models, "noise"), summary)
    first = [r for r in rows if r["lighting"] == "interior (LEDs)" and r["camera"] == CAMERAS[0]]
    lines += [
        "",
        f"The floor's hits in the bounce operator (those on a glossy BSDF) and its light per lighting (`interior`, "
        f"{CAMERAS[0]}'s job; the floor's LED visibility cached; median of 3):",
        "",
    ]
    lines += markdown_table(
        ("floor", *models), [(r["floor"], *(f"{r[m][1]:,} ({r[m][2]:,}), {r[m][3]:.0f} ms" for m in models)) for r in first]
    )
    lines += [""]
    table = [(r["floor"], r["lighting"], r["camera"], *(_pct(r[key][0]) for key in ("one", *models, "noise"))) for r in rows]
    lines += markdown_table(("floor", "lighting", "camera", "1 bounce", *(f"2 bounces: {m}" for m in models), "noise"), table)
    return "\n".join(lines) + "\n"


def measure(run: BenchmarkRun) -> str:
    if run.args.glossy:
        return glossy_page(run)
    quick = run.args.quick
    scenes = stages(run.work, 2 if quick else 3)
    accuracy = accuracy_rows(scenes, run.work, [32] if quick else [8, 32, 128], frame=2)
    cost = cost_rows(scenes, [256] if quick else [256, 512], 1 if quick else 3, 2 if quick else 5)
    page = markdown(accuracy, cost, run.stamp("walk on a floor + small rig; scenes/user_stage on a floor"))
    return page + "\n".join(fit_section(run.work / "user")) + "\n"


def arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true", help="K = 32 only, UV 256², one frame, 2 repeats.")
    parser.add_argument("--glossy", action="store_true", help="Only floors of glossy BSDFs, each way of finding the set's "
                        "light against `path`, and its cost (its own page: docs/results/set-light-glossy.md).")  # fmt: skip


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
