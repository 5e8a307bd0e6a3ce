"""A plain Mitsuba scene under an area light: gra_onebounce's lattice of points on the light against Mitsuba's
`direct`, speed against error.

The scenes (`near_field_cases.area_cases`): the tiny subject (a gra_microfacet material, roughness 0.35) at 96×128
under a small softbox beside the head, a textured disk 30 cm from the chest, or a 1 m² window at the side, and the
window again on a glossy body. The truth: Mitsuba's `direct` (one emitter and one BSDF sample per pass) at TRUTH_SPP
passes. Each row renders the same scene: gra_onebounce with S points on the light and B directions from the BSDF per
pixel sample (rank-1 lattices shifted at random per sample), or `direct` with E emitter and B BSDF samples per pass. Error: mean relative error over the covered pixels (the metric of
Mitsuba's own tests) and the bias of the mean; time: the median of 3 renders after one that compiles.

    .venv/bin/python benchmarks/area_lights.py [--truth-spp 16384] [--write docs/results/area-lights.md]
"""

from __future__ import annotations

from pathlib import Path

from gra_mi.apps.harness import RENDER_COLUMNS, BenchmarkRun, integrator_rows, run_benchmark, table_page
from gra_mi.render.near_field_cases import area_cases, body_scene

TINY_BODY = Path(__file__).resolve().parents[1] / "scenes" / "subjects" / "tiny" / "frames" / "frame_0000.ply"
OURS = ((1, 0, 16), (4, 0, 16), (16, 0, 16), (16, 4, 16), (16, 16, 16), (64, 16, 16), (16, 16, 64))  # (points, BSDF directions, spp)
DIRECT = ((1, 0, 64), (1, 0, 256), (1, 0, 1024), (16, 0, 16), (1, 1, 256), (16, 16, 16))  # (emitter, BSDF samples, passes)
GLOSSY = 0.08  # the glossy body's roughness: a highlight narrower than the window seen in it


def direct(emitter_samples: int = 1, bsdf_samples: int = 0):
    import mitsuba as mi

    return mi.load_dict({"type": "direct", "emitter_samples": emitter_samples, "bsdf_samples": bsdf_samples})


def measure(run: BenchmarkRun) -> str:
    import mitsuba as mi

    ours = [
        (f"gra_onebounce, {s} points + {b} BSDF directions × {spp} spp", mi.load_dict({"type": "gra_onebounce", "area_samples": s, "bsdf_samples": b}), spp)
        for s, b, spp in OURS
    ]  # fmt: skip
    theirs = [(f"direct, {s} emitter + {b} BSDF samples × {spp} spp", direct(s, b), spp) for s, b, spp in DIRECT]
    scenes = {name: body_scene({"light": light}, TINY_BODY) for name, light in area_cases().items()}
    scenes["window, glossy body"] = body_scene({"light": area_cases()["window"]}, TINY_BODY, roughness=GLOSSY)
    rows = integrator_rows(scenes, direct(1, 1), run.args.truth_spp, ours + theirs)
    notes = [
        f"The truth: `direct` at {run.args.truth_spp} passes of one emitter and one BSDF sample (its own noise is in "
        "the error of every row). Both integrators trace one shadow ray per point on the light and one ray per BSDF "
        "direction, weighted against each other by the power heuristic; a row's error holds the light's noise and the "
        "anti-aliasing noise of its pixel samples (which more samples of the light do not reduce). gra_onebounce's "
        "points and directions are lattices shifted at random per pixel sample, `direct`'s are independent. The glossy "
        f"body (roughness {GLOSSY}) shows the window as a highlight the light's points rarely land in: the BSDF's "
        "directions carry it.",
    ]
    return table_page("An area light: points on its surface against Mitsuba's direct", "area_lights.py",
                      run.stamp("tiny subject, 96×128"), rows, notes, ("light", *RENDER_COLUMNS))  # fmt: skip


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=lambda p: p.add_argument("--truth-spp", type=int, default=16384, help="Passes of the truth."))
