"""A plain Mitsuba scene under an area light: gra_onebounce's lattice of points on the light against Mitsuba's
`direct`, speed against error.

The scenes (`near_field_cases.area_cases`): the tiny subject (a gra_microfacet material, roughness 0.35) at 96×128
under a small softbox beside the head, a textured disk 30 cm from the chest, or a 1 m² window at the side, and the
window again on a glossy body; then stages of 24, 96 and 384 area LEDs (`near_field_cases.area_stage`: disks 3 cm
across, powers two orders of magnitude apart, one in five off), where the lights share the points. The truth:
Mitsuba's `direct` (one emitter and one BSDF sample per pass) at --truth-spp passes; on the stages, 64 emitter samples
per pass at --stage-truth-spp passes. Each row renders the same scene: gra_onebounce with S points on the light and B
directions from the BSDF per pixel sample (rank-1 lattices shifted at random per sample), or `direct` with E emitter
and B BSDF samples per pass. Error: mean relative error over the covered pixels (the metric of Mitsuba's own tests)
and the bias of the mean; time: the median of 3 renders after one that compiles.

    .venv/bin/python benchmarks/area_lights.py [--truth-spp 16384] [--stage-truth-spp 4096] [--write docs/results/area-lights.md]
"""

from __future__ import annotations

import gc
from pathlib import Path

from gra_mi.apps.harness import RENDER_COLUMNS, BenchmarkRun, direct_integrator, integrator_rows, run_benchmark, table_page
from gra_mi.render.near_field_cases import area_cases, area_stage, body_scene

TINY_BODY = Path(__file__).resolve().parents[1] / "scenes" / "subjects" / "tiny" / "frames" / "frame_0000.ply"
OURS = ((1, 0, 16), (4, 0, 16), (16, 0, 16), (16, 4, 16), (16, 16, 16), (64, 16, 16), (16, 16, 64))  # (points, BSDF directions, spp)
DIRECT = ((1, 0, 64), (1, 0, 256), (1, 0, 1024), (16, 0, 16), (1, 1, 256), (16, 16, 16))  # (emitter, BSDF samples, passes)
GLOSSY = 0.08  # the glossy body's roughness: a highlight narrower than the window seen in it
STAGES = (24, 96, 384)  # area LEDs
STAGE_OURS = ((16, 4, 16), (256, 4, 16), (16, 4, 64))
STAGE_DIRECT = ((16, 0, 16), (64, 0, 16))


def candidates(ours: tuple, theirs: tuple) -> list[tuple]:
    """(label, integrator, spp): gra_onebounce with each (points, BSDF directions, spp), then `direct` with each
    (emitter samples, BSDF samples, passes)."""
    import mitsuba as mi

    rows = [
        (f"gra_onebounce, {s} points + {b} BSDF directions × {spp} spp", mi.load_dict({"type": "gra_onebounce", "area_samples": s, "bsdf_samples": b}), spp)
        for s, b, spp in ours
    ]  # fmt: skip
    return rows + [(f"direct, {s} emitter + {b} BSDF samples × {spp} spp", direct_integrator(s, b), spp) for s, b, spp in theirs]


def measure(run: BenchmarkRun) -> str:

    scenes = {name: body_scene({"light": light}, TINY_BODY) for name, light in area_cases().items()}
    scenes["window, glossy body"] = body_scene({"light": area_cases()["window"]}, TINY_BODY, roughness=GLOSSY)
    rows = integrator_rows(scenes, direct_integrator(1, 1), run.args.truth_spp, candidates(OURS, DIRECT))
    for n in STAGES:  # one stage alive at a time: a call on an emitter traces every emitter that exists
        stage = {f"stage of {n} area LEDs": body_scene(area_stage(n), TINY_BODY)}
        rows += integrator_rows(stage, direct_integrator(64, 0), run.args.stage_truth_spp, candidates(STAGE_OURS, STAGE_DIRECT))
        del stage
        gc.collect()
    notes = [
        f"The truth: `direct` at {run.args.truth_spp} passes of one emitter and one BSDF sample (its own noise is in "
        "the error of every row). Both integrators trace one shadow ray per point on the light and one ray per BSDF "
        "direction, weighted against each other by the power heuristic; a row's error holds the light's noise and the "
        "anti-aliasing noise of its pixel samples (which more samples of the light do not reduce). gra_onebounce's "
        "points and directions are lattices shifted at random per pixel sample, `direct`'s are independent. The glossy "
        f"body (roughness {GLOSSY}) shows the window as a highlight the light's points rarely land in: the BSDF's "
        "directions carry it.",
        "On the stages gra_onebounce shares its points among the lights in proportion to their power, at least one "
        "each (so 16 points on a stage of 77 lights that are on are 77, one each), and `direct` picks a light "
        "uniformly for each emitter sample. Their truth: `direct` with 64 emitter samples per pass at "
        f"{run.args.stage_truth_spp} passes. A render's time also grows with the number of emitters by a fixed cost: "
        "Dr.Jit traces each emitter's code at each call on an emitter pointer.",
    ]
    return table_page("Area lights: points on their surface against Mitsuba's direct", "area_lights.py",
                      run.stamp("tiny subject, 96×128"), rows, notes, ("light", *RENDER_COLUMNS))  # fmt: skip


if __name__ == "__main__":

    def arguments(parser):
        parser.add_argument("--truth-spp", type=int, default=16384, help="Passes of the truth (one emitter and one BSDF sample each).")
        parser.add_argument("--stage-truth-spp", type=int, default=4096, help="Passes of the stages' truth (64 emitter samples each).")

    run_benchmark(__doc__, measure, arguments=arguments)
