"""Materials with a delta lobe under a sky and a softbox: gra_onebounce's one ray per lobe against Mitsuba's `direct`,
speed against error.

The scenes (`near_field_cases.ball_scene`, 64×64): a ball of each of `near_field_cases.DELTA_MATERIALS` (a perfect
mirror, gold, a plastic with a smooth coat, glass) under a turned, scaled envmap sky and a small softbox. The truth:
Mitsuba's `direct` (one emitter and one BSDF sample per pass) at TRUTH_SPP passes. gra_onebounce follows each delta
lobe with one ray (a glass's reflection and transmission both), its smooth lobes lit by the dome and the softbox's
points; `direct` draws one BSDF sample per pass (a glass's lobe picked at random). Error: mean relative error over
the ball's pixels and the bias of the mean; time: the median of 3 renders after one that compiles.

    .venv/bin/python benchmarks/delta_lobes.py [--truth-spp 32768] [--write docs/results/delta-lobes.md]
"""

from __future__ import annotations

from gra_mi.apps.harness import RENDER_COLUMNS, BenchmarkRun, direct_integrator, integrator_rows, run_benchmark, table_page
from gra_mi.render.near_field_cases import DELTA_MATERIALS, ball_scene

OURS = (4, 16, 64)  # spp
DIRECT = (16, 64, 256)  # passes of one emitter and one BSDF sample


def measure(run: BenchmarkRun) -> str:
    import mitsuba as mi

    candidates = [(f"gra_onebounce × {spp} spp", mi.load_dict({"type": "gra_onebounce"}), spp) for spp in OURS]
    candidates += [(f"direct, 1 emitter + 1 BSDF sample × {spp} spp", direct_integrator(1, 1), spp) for spp in DIRECT]
    scenes = {name: ball_scene(material) for name, material in DELTA_MATERIALS.items()}
    rows = integrator_rows(scenes, direct_integrator(1, 1), run.args.truth_spp, candidates)
    notes = [
        f"The truth: `direct` at {run.args.truth_spp} passes (its own noise is in the error of every row; a glass's "
        "is the largest, as `direct` picks its reflection or its transmission at random). gra_onebounce's rows "
        "hold the pixels' anti-aliasing noise and, on the plastic, the softbox's points and the dome's cells on its "
        "diffuse base; a mirror's and gold's reflections are exact at every pixel sample.",
    ]
    return table_page("Delta lobes: a mirror, gold, a plastic's coat and glass against Mitsuba's direct", "delta_lobes.py",
                      run.stamp("a ball, 64×64"), rows, notes, ("material", *RENDER_COLUMNS))  # fmt: skip


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=lambda p: p.add_argument("--truth-spp", type=int, default=32768, help="Passes of the truth."))
