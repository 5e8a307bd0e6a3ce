"""Every stage's speed as users run it, in one process on one device: the numbers the GPU check
(scripts/gpu_check.sh) puts beside the CPU's, and the paper's H100 runtime table where it has the stage.

The walking anny body in the default 331-LED rig at UV 512², one camera at the paper's 1024×540:

- one bounce: a new frame (mesh update, texel geometry, visibility of every texel × LED), then the view of that
  cached frame under a new envmap (texel shading, rasterisation): the paper's "microfacet" row;
- two bounces: the texel-to-texel operator traced for a new frame, and a cached view;
- the material fit per view: the LED loop of the texels a camera sees built, then a step's shading of them, and the
  closed form's 11 roughness candidates in one walk over the LEDs beside one walk per candidate;
- RelightNet's forward pass at 512² and one training step (rasterised into 1024×540);
- the reflectance-field sum per lighting at HumanOLAT's half size (405×720, 331 OLATs, a random stack);
- the viewer's server render of a lighting change (512×288).

A stage that fails is recorded with its error and the others still run (the GPU check has one try).

    .venv/bin/python benchmarks/stages.py [--variant cuda_ad_rgb] [--json FILE] [--write PAGE]
"""

from __future__ import annotations

import json
import logging
import traceback
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, envmap_drives, relightnet_calls, run_benchmark, side_by_side, table_page, timed

UV = 512
IMAGE = (1024, 540)
FRAMES = 6


logger = logging.getLogger(__name__)


def walk_scene(folder: Path):
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, rig_scene
    from gra_mi.subject.anny_body import anny_sequence

    stage = default_lightstage(width=IMAGE[0], height=IMAGE[1])
    return LightstageScene.load(rig_scene(folder, anny_sequence(["walk"], frames_per_clip=FRAMES), stage), spp=1)


def one_bounce(ls, repeats: int) -> list[dict]:
    from gra_mi.render.relighter import Relighter

    relighter, drives = Relighter(ls, UV), envmap_drives(ls.stage)
    frames = iter(range(FRAMES))
    t_frame, frame = timed(lambda: (f := next(frames), relighter.visibility(f))[0], min(repeats, FRAMES - 1), warmup=True)
    calls = iter(range(10**6))
    t_view, _ = timed(lambda: relighter.render(frame, 0, drives[next(calls) % len(drives)]), repeats, warmup=True)
    texels = relighter.atlas.num_texels
    return [
        {"stage": "one bounce: new frame (mesh, texel geometry, visibility)", "ms": 1e3 * t_frame, "note": f"{texels} texels × {ls.stage.num_leds} LEDs"},
        {"stage": "one bounce: cached frame, new envmap (shading + rasterisation)", "ms": 1e3 * t_view, "note": f"{IMAGE[0]}×{IMAGE[1]}"},
        {"stage": "microfacet per frame (the two above)", "ms": 1e3 * (t_frame + t_view), "paper": "microfacet"},
    ]  # fmt: skip


def two_bounces(ls, repeats: int) -> list[dict]:
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    two, drive = Relighter(ls, UV, transport=LightTransport(bounces=2)), envmap_drives(ls.stage, 1)[0]
    frame = 0
    two.render(frame, 0, drive)  # visibility and operator traced, kernels compiled
    t_op, op = timed(lambda: (two._operators.clear(), two.bounce_operator(frame))[1], repeats)
    change = iter(range(1, 10**9))  # a new lighting per call: nothing after the first bounce is reused
    t_view, _ = timed(lambda: two.render(frame, 0, drive * (1 + 1e-6 * next(change))), repeats, warmup=True)
    return [
        {"stage": "two bounces: operator traced for a new frame", "ms": 1e3 * t_op, "note": f"K = {two.transport.bounce_rays}, {op.nbytes / 2**20:.0f} MB"},
        {"stage": "two bounces: cached frame, new envmap", "ms": 1e3 * t_view, "note": "default smoothing"},
    ]  # fmt: skip


def fit_per_view(ls, repeats: int) -> list[dict]:
    """The material fit's work per view (MaterialFitter.parts): the LED loop of the texels camera 0 sees built and
    run (a view's first step), then each later step's shading of them for new roughness values."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.fit.materials import FitConfig
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.shading import TexelLedLoop
    from gra_mi.render.visibility import texels_seen_by

    relighter, lighting, frame = Relighter(ls, UV), envmap_drives(ls.stage, 1)[0], 1
    geom, camera = relighter.geometry(frame), ls.stage.cameras[0]
    visibility, texels = relighter.visibility(frame), texels_seen_by(relighter.geometry(frame), [camera])

    values = iter(np.linspace(0.2, 0.8, 8 * repeats + 8))

    def step(loop):
        dr.eval(loop.run(mi.Float(np.full(texels.size, next(values), np.float32))))  # Dr.Jit is lazy: evaluate it
        return loop

    t_build, loop = timed(
        lambda: step(TexelLedLoop.build(geom, visibility, texels, relighter.leds(), lighting, camera.position)), repeats, warmup=True
    )
    t_step, _ = timed(lambda: step(loop), repeats, warmup=True)
    # The closed form's roughness grid (FitConfig's candidates): one walk over the LEDs for all, or one per value.
    grid = np.linspace(0.0, 1.0, FitConfig().roughness_candidates)
    together = tuple(dr.opaque(mi.Float, float(r)) for r in grid)
    each = [mi.Float(np.full(texels.size, r, np.float32)) for r in grid]
    grid_ms = side_by_side({"one walk": lambda: dr.eval(loop.run(together)), "each": lambda: [dr.eval(loop.run(r)) for r in each]}, repeats)
    note = f"{texels.size} texels seen by one camera"
    return [
        {"stage": "material fit, per view: first step (its LED loop built)", "ms": 1e3 * t_build, "note": note},
        {"stage": "material fit, per view: a step's shading (new roughness)", "ms": 1e3 * t_step, "note": note},
        {
            "stage": f"closed-form fit, per view: {grid.size} roughness candidates in one walk",
            "ms": 1e3 * grid_ms["one walk"],
            "note": note,
        },
        {"stage": "closed-form fit, per view: the same, one walk per candidate", "ms": 1e3 * grid_ms["each"], "note": "side by side"},
    ]


def relightnet(repeats: int) -> list[dict]:
    import torch

    from gra_mi.relightnet.model import RelightNet, RelightNetConfig

    device = "cuda" if torch.cuda.is_available() else "cpu"
    model = RelightNet(RelightNetConfig(resolution=UV)).to(device).eval()
    forward, step = relightnet_calls(model, UV, IMAGE, device)
    t_forward, _ = timed(forward, repeats, warmup=True)
    t_step, _ = timed(step, repeats, warmup=True)
    note = f"torch {device}, {sum(p.numel() for p in model.parameters()) / 1e6:.2f} M parameters"
    return [
        {"stage": f"RelightNet forward, {UV}² UV", "ms": 1e3 * t_forward, "note": note, "paper": "relightnet"},
        {"stage": f"RelightNet training step (rasterised into {IMAGE[0]}×{IMAGE[1]})", "ms": 1e3 * t_step, "note": note},
    ]


def reflectance_field(repeats: int) -> list[dict]:
    from gra_mi.capture.reflectance import ReflectanceField

    rng = np.random.default_rng(0)
    shape, olats, fraction = (720, 405), 331, 0.3
    pixels = np.sort(rng.choice(shape[0] * shape[1], int(fraction * shape[0] * shape[1]), replace=False))
    stack = rng.random((3, olats, pixels.size), np.float32)
    field = ReflectanceField(None, "cam", None, shape, pixels, np.ones(shape, np.float32), stack, np.ones(olats))
    weights = rng.uniform(0, 1, (1, olats, 3))
    t, _ = timed(lambda: field.relight(weights), repeats, warmup=True)
    return [{"stage": "reflectance field: one lighting, 405×720, 331 OLATs", "ms": 1e3 * t, "note": f"summed on {field.summed_on}"}]


def viewer(work: Path, repeats: int) -> list[dict]:
    from gra_mi.apps.harness import walking_scene
    from gra_mi.apps.viewer import ViewerSession, ViewSources, camera_pose, viewer_camera, with_lighting

    session = ViewerSession(ViewSources(scene=walking_scene(work / "viewer", 2), uv_resolution=UV))
    position, wxyz, fov = camera_pose(session.ls.stage.cameras[0])
    camera = viewer_camera(position, wxyz, fov, 512, 288)
    session.render(camera)  # the frame's visibility and the kernels: once
    turns = iter(range(1, 10**6))
    t, _ = timed(lambda: (with_lighting(session, mode="envmap", rotation=15.0 * next(turns)), session.render(camera)), repeats)
    return [{"stage": "viewer: a lighting change rendered (server, 512×288)", "ms": 1e3 * t, "note": "envmap rotated, cached frame"}]


def guarded(name: str, measure) -> list[dict]:
    """The stage's rows, or one row holding its error: on a one-try GPU run the other stages still count."""
    try:
        return measure()
    except Exception as error:  # noqa: BLE001 — recorded on the page, and printed
        traceback.print_exc()
        return [{"stage": name, "error": f"{type(error).__name__}: {error}"}]


def measure(run: BenchmarkRun) -> str:
    from gra_mi.core.errors import require_positive

    args, work = run.args, run.work
    require_positive({"repeats": args.repeats})
    ls = walk_scene(work / "walk")
    stages = {
        "one bounce": lambda: one_bounce(ls, args.repeats),
        "two bounces": lambda: two_bounces(ls, args.repeats),
        "material fit": lambda: fit_per_view(ls, args.repeats),
        "RelightNet": lambda: relightnet(args.repeats),
        "reflectance field": lambda: reflectance_field(args.repeats),
        "viewer": lambda: viewer(work, args.repeats),
    }
    record = {"stamp": run.stamp(f"anny walk, UV {UV}², {IMAGE[0]}×{IMAGE[1]}"), "device": device_said(run.variant), "stages": []}
    for name, stage in stages.items():
        record["stages"] += guarded(name, stage)
        if args.json is not None:  # after each stage: a run stopped at its time limit keeps what it measured
            args.json.write_text(json.dumps(record, indent=1))
    rows = record["stages"]
    table = [(r["stage"], cell(r), r.get("note", "")) for r in rows]
    return table_page(f"Stage speed — {record['device']}", "stages.py", record["stamp"], table, columns=("stage", "ms", "note"))


def cell(row: dict) -> str:
    if "ms" in row:
        return f"{row['ms']:.1f}"
    return f"failed: {row['error']}" if "error" in row else f"skipped: {row['skipped']}"


def device_said(variant: str | None) -> str:
    """The Mitsuba variant and torch device, with the GPU's name where one is used."""
    import os

    import torch

    if torch.cuda.is_available():
        return f"{variant}, torch cuda ({torch.cuda.get_device_name()})"
    return f"{variant}, torch cpu ({os.cpu_count()} cores, {torch.get_num_threads()} threads)"


def arguments(parser) -> None:
    parser.add_argument("--repeats", type=int, default=5, help="Timed repeats per stage (medians; after one warm-up). Default: 5.")
    parser.add_argument("--json", type=Path, default=None, help="Also write the rows as JSON here (the GPU check's page reads it).")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, variant=None, torch=True)
