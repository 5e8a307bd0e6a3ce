"""The reflectance field against direct renders: accuracy and cost of relighting a capture as Σ wᵢ · OLATᵢ.

On a synthetic `olat` capture (331 LEDs; white, 2 gradient and 10 environment-mapped frames rendered directly), for
each held-out camera and each of those 13 lightings:

- **Σ OLAT vs direct**: the sum of the capture's OLAT images against the capture's own render under the same LED
  drive (relative RMSE over the subject, and total brightness);
- **render noise**: the direct render against a second render of the same view with another seed — two renders that
  should be equal disagree by this much, the floor any comparison with a render can reach;
- **Σ OLAT vs far field** (envmaps only): against the same map path-traced at infinity (`gra-mi eval-lighting`'s
  truth): what a stage's 331 LEDs at 1.7 m are not — the near-field and discretisation difference, not an error of
  the sum.

Then the cost of a sum per lighting at the capture's size (its real stack) and at HumanOLAT's (810×1440, and half of
it; a random stack with the capture's subject fraction), held as float32 or float16, one lighting or 32 at a time.

    .venv/bin/python benchmarks/reflectance_field.py [--capture DIR] [--write docs/results/reflectance-field.md]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, timed


def relative_rmse(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a[mask, :3] - b[mask, :3]) ** 2)) / np.sqrt(np.mean(b[mask, :3] ** 2)))


def agreement(capture, cameras: list[str]) -> list[dict]:
    """Per combined lighting (every non-OLAT frame) and camera: Σ OLAT vs direct, direct vs a re-render, Σ vs far field."""
    from gra_mi.capture.dataset import load_observation
    from gra_mi.capture.reflectance import OlatIndex, ReflectanceField
    from gra_mi.capture.truth import GroundTruthRenderer, render_envmap_truth
    from gra_mi.capture.wrinkles import pose_capture_wrinkles
    from gra_mi.stage.envmap import envmap_to_leds, load_envmap
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.stage.scene import LightstageScene

    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    index = OlatIndex.of(capture, stage)
    fields = {c: ReflectanceField.load(capture, c, index) for c in cameras}
    gt = capture.ground_truth
    renderer = GroundTruthRenderer(spp=gt["spp"], indirect_spp=gt["indirect_spp"], max_depth=gt["max_depth"])
    source = LightstageScene.load(capture.folder / "scene_gt.xml")
    source.set_frame(0)
    pose_capture_wrinkles(source.params, capture, 0)  # the static pose: as its images have them
    rows = []
    for entry in [e for e in capture.frames if e.frame not in index.frames]:
        lighting = capture.lighting(stage, entry)
        source.set_led_intensities(lighting)
        far = None
        if entry.envmap:
            env = load_envmap(capture.folder / entry.envmap)
            far = render_envmap_truth(capture, env * envmap_to_leds(env, stage).scale, 0, cameras, spp=256)
        for cam in cameras:
            direct = load_observation(capture, cam, entry.frame)
            mask = direct[..., 3] > 0.5
            seed = 7919 + entry.frame
            seconds, again = timed(lambda cam=cam, seed=seed: renderer.render(source.scene, source.sensor_index(cam), seed=seed))
            summed = fields[cam].relight(index.weights(lighting, entry.pattern or entry.envmap))[0]
            row = {"lighting": Path(entry.pattern or entry.envmap).stem, "camera": cam, "render_s": seconds}
            row |= {"sum_vs_direct": relative_rmse(summed, direct, mask), "render_noise": relative_rmse(again, direct, mask)}
            row |= {"brightness": float(summed[mask, :3].sum() / direct[mask, :3].sum() - 1)}
            if far is not None:
                row |= {
                    "sum_vs_far": relative_rmse(summed, far[cam], mask),
                    "far_brightness": float(summed[mask, :3].sum() / far[cam][mask, :3].sum() - 1),
                }
            rows.append(row)
    return rows


def speed(capture, camera: str) -> tuple[list[dict], float, int]:
    """ms per lighting of the sum, held as float32 / float16, one lighting or 32, at three camera sizes; and the
    subject's share of the pixels and the OLAT count they were measured with."""
    from gra_mi.capture.reflectance import OlatIndex, ReflectanceField
    from gra_mi.stage.lightstage import load_calibration

    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    index = OlatIndex.of(capture, stage)
    real = ReflectanceField.load(capture, camera, index, progress_bar=False)
    fraction = real.pixels.size / (real.shape[0] * real.shape[1])
    rng = np.random.default_rng(0)
    rows = []
    for label, (w, h) in (
        ("capture camera", real.shape[::-1]),
        ("HumanOLAT ½ (405×720)", (405, 720)),
        ("HumanOLAT (810×1440)", (810, 1440)),
    ):
        for dtype in (np.float32, np.float16):
            rf = real if label == "capture camera" and dtype == np.float32 else _stand_in(real, (h, w), fraction, dtype, rng)
            for batch in (1, 32):
                weights = rng.uniform(0, 1, (batch, len(index.frames), 3))
                seconds, _ = timed(lambda rf=rf, weights=weights: rf.relight(weights), max(1, int(8 / batch)), warmup=True)
                ms = 1000 * seconds / batch
                rows.append(
                    {"size": label, "w": w, "h": h, "dtype": np.dtype(dtype).name, "batch": batch, "ms": ms, "mib": rf.stack.nbytes / 2**20}
                )
            del rf
    return rows, fraction, len(index.frames)


def _stand_in(real, shape: tuple[int, int], fraction: float, dtype, rng):
    """A field of ``shape`` whose stack is random, with the real capture's share of subject pixels."""
    from gra_mi.capture.reflectance import ReflectanceField

    pixels = np.sort(rng.choice(shape[0] * shape[1], int(fraction * shape[0] * shape[1]), replace=False))
    k = len(real.index.frames)
    stack = np.empty((3, k, pixels.size), dtype)
    for c in range(3):
        for j in range(k):
            stack[c, j] = rng.random(pixels.size, np.float32)
    return ReflectanceField(real.capture, real.camera, real.index, shape, pixels, np.ones(shape, np.float32), stack, np.ones(k))


def markdown(capture, rows: list[dict], speeds: tuple, stamp: str) -> str:
    speeds, fraction, olats = speeds
    lines = [
        "# Results: relighting from the reflectance field",
        "",
        f"> `benchmarks/reflectance_field.py`, {stamp}. Capture: `gra-mi capture --preset olat` ({len(capture.frames)} frames,",
        f"> {capture.ground_truth['spp']} spp path-traced, {capture.ground_truth['indirect_spp']} indirect), its held-out cameras.",
        "",
        "Relative RMSE over the subject's pixels. *Σ OLAT vs direct*: the sum of the capture's OLAT images against its",
        "own render under the same LED drive. *Render noise*: that render against a second one with another seed (the",
        "floor: two renders that should be equal differ by this much). *vs far field*: the same envmap path-traced at",
        "infinity (`eval-lighting`'s truth) — the stage's near field and 331-LED discretisation, not an error of the sum.",
        "",
        "| lighting | Σ OLAT vs direct | render noise | brightness Σ / direct − 1 | Σ OLAT vs far field | brightness Σ / far − 1 |",
        "|---|---|---|---|---|---|",
    ]
    for name in dict.fromkeys(r["lighting"] for r in rows):
        group = [r for r in rows if r["lighting"] == name]
        mean = lambda key, group=group: float(np.mean([r[key] for r in group])) if key in group[0] else None  # noqa: E731
        far = f"{100 * mean('sum_vs_far'):.1f} %" if mean("sum_vs_far") is not None else "—"
        far_b = f"{100 * mean('far_brightness'):+.1f} %" if mean("far_brightness") is not None else "—"
        lines.append(
            f"| {name} | {100 * mean('sum_vs_direct'):.2f} % | {100 * mean('render_noise'):.2f} % | {100 * mean('brightness'):+.2f} % | {far} | {far_b} |"
        )
    render_s = np.mean([r["render_s"] for r in rows])
    lines += [
        "",
        f"A direct path-traced render costs {render_s:.2f} s per image at the capture's size; the sum, the table below.",
        "The sum of 331 OLAT renders carries 331× their samples, so it agrees with the direct render better than a",
        "second direct render does: its error against the direct render is that render's own noise.",
        "",
        "## Cost of a sum per lighting",
        "",
        "The capture's own stack at its size; at HumanOLAT's sizes a random stack with the capture's share of subject",
        f"pixels ({100 * fraction:.0f} %) and its {olats} OLATs. Batch: lightings summed together.",
        "",
        "| camera | held as | batch | ms per lighting | stack in memory |",
        "|---|---|---|---|---|",
    ]
    lines += [f"| {r['size']} | {r['dtype']} | {r['batch']} | {r['ms']:.1f} | {r['mib']:.0f} MiB |" for r in speeds]
    return "\n".join(lines) + "\n"


def measure(run: BenchmarkRun) -> str:
    from gra_mi.capture import synthetic
    from gra_mi.capture.dataset import Capture

    folder = run.args.capture or run.work / "olat"
    if run.args.capture is None:
        synthetic.generate_capture(folder, synthetic.CaptureConfig(preset="olat", measure_noise=False))
    capture = Capture.load(folder)
    rows = agreement(capture, capture.eval_cameras)
    speeds = speed(capture, capture.eval_cameras[0])
    return markdown(capture, rows, speeds, run.stamp("olat"))


def arguments(parser) -> None:
    parser.add_argument("--capture", type=Path, default=None, help="An `olat` capture (default: generate one, ~20 min).")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
