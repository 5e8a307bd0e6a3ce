"""A plain Mitsuba scene under an environment emitter: gra_onebounce's dome of lights against Mitsuba's `direct`,
speed against error.

The scene: the tiny subject (a gra_microfacet material, roughness 0.35; arms that shadow the torso) at 96×128, lit by
an `envmap` emitter holding one of the reference maps (`envmap_library.reference_map`: a sharp sun, a studio's soft
boxes). The truth: Mitsuba's `direct` with both of its strategies (4 emitter and 4 BSDF samples per pass, MIS) at
TRUTH_SPP passes. Each row renders the same scene: gra_onebounce with a dome of N lights (deterministic but for where
in a pixel its 1 or 4 samples fall), or `direct` at S passes. Error: mean relative error over the covered pixels (the
metric of Mitsuba's own tests: |ours − truth| / max(truth, 5 % of its 95th percentile)) and the bias of the mean;
time: the median of 3 renders after one that compiles.

    .venv/bin/python benchmarks/environment_dome.py [--truth-spp 2048] [--write docs/results/environment-dome.md]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.apps.harness import RENDER_COLUMNS, BenchmarkRun, direct_integrator, integrator_rows, run_benchmark, table_page

TINY_BODY = Path(__file__).resolve().parents[1] / "scenes" / "subjects" / "tiny" / "frames" / "frame_0000.ply"
DOMES = ((256, 4), (1024, 1), (1024, 4), (1024, 64), (4096, 4))  # (lights, samples per pixel: anti-aliasing only)
DIRECT_SPP = (4, 16, 64)  # passes of 4 emitter + 4 BSDF samples
MAPS = ("sun", "studio")


def scene_under(name: str):
    import mitsuba as mi

    from gra_mi.render.near_field_cases import body_scene
    from gra_mi.stage.envmap_library import reference_map

    sky = {"type": "envmap", "bitmap": mi.Bitmap(reference_map(name, 128).astype(np.float32))}
    return body_scene({"sky": sky}, TINY_BODY)


def measure(run: BenchmarkRun) -> str:
    import mitsuba as mi

    domes = [(f"gra_onebounce, dome of {n}, {spp} spp", mi.load_dict({"type": "gra_onebounce", "dome_lights": n}), spp) for n, spp in DOMES]
    passes = [(f"direct, {spp} × (4 + 4) samples", direct_integrator(4, 4), spp) for spp in DIRECT_SPP]
    rows = integrator_rows({name: scene_under(name) for name in MAPS}, direct_integrator(4, 4), run.args.truth_spp, domes + passes)
    notes = [
        f"The truth: `direct` at {run.args.truth_spp} passes of 4 emitter + 4 BSDF samples (its own noise is in the "
        "error of every row, a few tenths of a per cent). gra_onebounce's samples per pixel only anti-alias; its error "
        "is the dome's: each cell's light from one direction (the mean of the cell's light) with one hard shadow, a "
        "highlight narrower than a cell blurred; its flux exact.",
    ]
    return table_page("An environment emitter: a dome of lights against Mitsuba's direct", "environment_dome.py",
                      run.stamp("tiny subject, 96×128"), rows, notes, ("map", *RENDER_COLUMNS))  # fmt: skip


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=lambda p: p.add_argument("--truth-spp", type=int, default=2048, help="Passes of the truth."))
