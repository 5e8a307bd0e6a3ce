"""Light after the first bounce (``--bounces 2``): accuracy against Mitsuba's own ``path`` integrator where the body
lights itself, and its cost on the demo's body, side by side in one run.

1. Accuracy: the anny body in the hard cases' poses (gra_mi.render.path_reference.HARD_CASES: an armpit, the face
   under raised arms, the inner thighs, a hand by the hip), lit by a point light near the body, at UV 256² and 512²
   with K rays per texel; against ``path`` at max_depth 2 (one bounce), 3 (one interreflection) and unlimited, with
   the same mesh, ``gra_microfacet`` and maps. Reference noise: the same path render with another seed.
2. Cost: the walking body in the default 331-LED rig (the `small` preset's rig; the `olat` preset's pose is the
   walk's first frame): per new frame the visibility trace against the bounce operator's trace, the texels that
   trace, the operator's memory; per view of a cached frame under a new envmap, one against two bounces.

    .venv/bin/python benchmarks/interreflection.py [--quick] [--write docs/results/interreflection.md]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, side_by_side

SPP = 1024


def accuracy_rows(folder: Path, resolutions, rays_list) -> list[dict]:
    from gra_mi.render.path_reference import HARD_CASE_CLIP, HARD_CASE_FRAMES, HARD_CASES, bounce_errors, path_reference
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, rig_scene
    from gra_mi.subject.anny_body import anny_sequence

    scene = rig_scene(folder / "hard", anny_sequence([HARD_CASE_CLIP], HARD_CASE_FRAMES), default_lightstage())
    ls = LightstageScene.load(scene, spp=1)
    off = np.zeros((ls.stage.num_leds, 3))
    rows = []
    for resolution in resolutions:
        one = Relighter(ls, resolution)
        for case in HARD_CASES:
            camera, light = case.camera(), case.point_light()
            paths = {d: path_reference(one, case.frame, camera, off, [light], d, SPP, folder / "path") for d in (2, 3, -1)}
            again = path_reference(one, case.frame, camera, off, [light], 3, SPP, folder / "path", seed=1)
            noise = bounce_errors(paths[2], again, paths[2], paths[3])["bias_more"]
            image_one = one.render(case.frame, camera, off, [light]).image
            for rays in rays_list:
                more = Relighter(ls, resolution, transport=LightTransport(bounces=2, bounce_rays=rays))
                image = more.render(case.frame, camera, off, [light]).image
                e = bounce_errors(image_one, image, paths[2], paths[3])
                e["unlimited_vs_one_extra"] = bounce_errors(image_one, paths[3], paths[2], paths[-1])["bias_more"]
                e["two_vs_unlimited"] = bounce_errors(image_one, image, paths[2], paths[-1])["bias_more"]
                rows.append({"case": case.name, "resolution": resolution, "rays": rays, "noise": noise, **e})
    return rows


def _frame_costs(ls, one, two, raw, frame: int, leds: np.ndarray, repeats: int) -> dict:
    """``two`` with the default smoothing, ``raw`` without (what the smoothing costs)."""
    from gra_mi.render.visibility import compute_visibility

    ls.set_frame(frame)
    geom, change = one.geometry(frame), iter(range(1, 10**9))
    trace = side_by_side(
        {
            "vis": lambda: compute_visibility(ls.scene, geom, one.leds()),
            "op": lambda: (two._operators.clear(), two.bounce_operator(frame)),
        },
        repeats,
    )
    op, used = two.bounce_operator(frame), two.job_operator(frame)
    # a new lighting per call: nothing after the first bounce is reused
    views = side_by_side(
        {
            name: lambda rel=rel: rel.render(frame, 0, leds * (1 + 1e-6 * next(change)))
            for name, rel in (("one", one), ("two", two), ("raw", raw))
        },
        repeats,
    )
    return {
        "frame": frame, "texels": op.num_texels, "traced": op.traced / op.num_texels, "entries": op.entries, "used": used.entries,
        "mb": op.nbytes / 2**20,
        "vis_ms": 1e3 * trace["vis"], "op_ms": 1e3 * trace["op"], "view_one_ms": 1e3 * views["one"], "view_two_ms": 1e3 * views["two"],
        "view_raw_ms": 1e3 * views["raw"],
    }  # fmt: skip


def cost_rows(folder: Path, resolutions, frames: int, repeats: int) -> list[dict]:
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport
    from gra_mi.stage.envmap import envmap_to_leds
    from gra_mi.stage.envmap_library import reference_map
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, rig_scene
    from gra_mi.subject.anny_body import anny_sequence

    stage = default_lightstage(width=216, height=312)
    ls = LightstageScene.load(rig_scene(folder / "walk", anny_sequence(["walk"], frames_per_clip=2 * frames), stage), spp=1)
    leds = envmap_to_leds(reference_map("interior", 64), ls.stage).radiant_intensity(ls.stage)
    rows = []
    for resolution in resolutions:
        one = Relighter(ls, resolution)
        two = Relighter(ls, resolution, transport=LightTransport(bounces=2))
        raw = Relighter(ls, resolution, transport=LightTransport(bounces=2, bounce_smoothing=0))
        for rel in (one, two, raw):
            rel.only_for([ls.stage.cameras[0].name])  # as `gra-mi relight` renders: the light its camera can see
        rows += [{"resolution": resolution} | _frame_costs(ls, one, two, raw, f, leds, repeats) for f in range(0, 2 * frames, 2)]
    return rows


def markdown(accuracy: list[dict], cost: list[dict], stamp: str) -> str:
    lines = [
        "# Light after the first bounce: accuracy and cost",
        "",
        f"Generated by `benchmarks/interreflection.py` ({stamp}).",
        "",
        "## Against Mitsuba's `path` where the body lights itself",
        "",
        f"Each hard case (gra_mi.render.path_reference.HARD_CASES) at 128×128, a 0.3 W/sr point light near the body, "
        f"the body's own colours, roughness 0.5; `path` at {SPP} spp with `gra_microfacet` and the same maps; two bounces with K rays per texel and the "
        "default smoothing (radius 2). *bias*: Σ "
        "render / Σ `path` (max_depth 3) − 1 over the pixels all renders cover; *own*: gra-mi's one bounce against "
        "`path` max_depth 2 (UV resampling, no interreflection involved); *blocks*: 8×8 blocks where Mitsuba's one "
        "bounce is ≥ 10 % darker than max_depth 3, the largest error there of one and two bounces, and of the light "
        "two bounces add against the light `path` adds; *noise*: the bias of a second `path` render (another seed); "
        "*unlimited*: max_depth 3 against unlimited depth, and two bounces against unlimited.",
        "",
        "| case | UV | K | own | bias 1 bounce | bias 2 bounces | blocks | block error 1 / 2 | added light error | noise | max_depth 3 vs ∞ | 2 bounces vs ∞ |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    pct = lambda x: "–" if not np.isfinite(x) else f"{100 * x:+.2f} %"  # noqa: E731
    size = lambda x: "–" if not np.isfinite(x) else f"{100 * x:.2f} %"  # noqa: E731
    for r in accuracy:
        blocks = f"{size(r['dark_block_error_one'])} / {size(r['dark_block_error_more'])}" if r["dark_blocks"] else "–"
        added = size(r["added_light_error"]) if r["dark_blocks"] else "–"
        lines.append(
            f"| {r['case']} | {r['resolution']}² | {r['rays']} | {pct(r['bias_one_vs_path_one'])} | {pct(r['bias_one'])} | "
            f"{pct(r['bias_more'])} | {r['dark_blocks']} | {blocks} | {added} | {pct(r['noise'])} | "
            f"{pct(r['unlimited_vs_one_extra'])} | {pct(r['two_vs_unlimited'])} |"
        )
    lines += [
        "",
        "## Cost on the demo's body",
        "",
        "The anny body walking, the default 331-LED rig, near field, K = 32 rays per texel (the default), median over "
        "repeats, measured side by side in one run. *new frame*: the per-LED visibility trace (every texel) and the bounce "
        "operator's trace; *cached frame*: one view under a new envmap (`interior`), every LED on, one and two bounces, "
        "rendered as `gra-mi relight` renders one camera (*rays used*: those whose light can reach what it sees), two",
        "bounces with the default smoothing (radius 2) and without it (*unsmoothed*: what the smoothing costs).",
        "",
        "| UV | frame | texels | trace (hull test) | operator entries | rays used | MB / frame | visibility ms | operator ms | × visibility | view ms, 1 bounce | 2 bounces | × | 2 bounces, unsmoothed |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in cost:
        lines.append(
            f"| {r['resolution']}² | {r['frame']} | {r['texels']:,} | {100 * r['traced']:.0f} % | {r['entries']:,} | {r['used']:,} | {r['mb']:.1f} | "
            f"{r['vis_ms']:.0f} | {r['op_ms']:.0f} | {r['op_ms'] / r['vis_ms']:.2f} | {r['view_one_ms']:.0f} | {r['view_two_ms']:.0f} | "
            f"{r['view_two_ms'] / r['view_one_ms']:.2f} | {r['view_raw_ms']:.0f} |"
        )
    lines += [
        "",
        "What a perfect fit scores with one and two bounces, and the material fit with each: "
        "[olat-fit-effects.md](olat-fit-effects.md) (`benchmarks/olat_fit.py --effects`).",
    ]
    return "\n".join(lines) + "\n"


def measure(run: BenchmarkRun) -> str:
    args = run.args
    resolutions = [256] if args.quick else [256, 512]
    rays = [8, 32] if args.quick else [8, 16, 32, 64]
    accuracy = accuracy_rows(run.work, resolutions, rays)
    cost = cost_rows(run.work, resolutions, 2 if args.quick else 3, 2 if args.quick else 5)
    return markdown(accuracy, cost, run.stamp("hard cases + small rig"))


def arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true", help="UV 256² only, K = 8 and 32, 2 frames, 2 repeats.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
