"""The demo's headline numbers over several RelightNet training seeds: is RelightNet's gain larger than its spread?

`gra-mi demo` trains RelightNet once (seed 0). This trains it with seeds 1 … N−1 on the same capture and fit (the
demo's own steps; seed 0 is the demo's own RelightNet where its options match), scores each with `gra-mi eval`
(held-out cameras under the held-out lighting sequence, the microfacet render beside it) and with `gra-mi
eval-lighting` (the reference maps against their path-traced truth, RelightNet beside far field), and writes a page
with the mean and the spread (max − min) / 2 of every number, and where the demo's own RelightNet moves ꟻLIP (the
silhouette band against the interior).

    .venv/bin/python benchmarks/demo_seeds.py --run outputs/demo [--seeds 3] [--more-steps 2000] [--lightings 4,16]
        [--write docs/results/demo-seeds.md]

Each run keeps its numbers in its folder under --work (default RUN/seeds/…/result.json): a rerun reads them back.
"""

from __future__ import annotations

import csv
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark

METRICS = (("psnr", "PSNR", 2), ("ssim", "SSIM", 3), ("flip", "ꟻLIP", 3))


def run_transport(run: Path):
    """The bounces of light the demo run was made with (its RelightNet's input; the same for every seed here)."""
    from gra_mi.render.transport import LightTransport

    return LightTransport(**json.loads((run / "demo.json").read_text()).get("transport", {}))


def train_and_score(run: Path, out: Path, seed: int, steps: int, lighting_spp: int, lightings: int | None = None) -> dict:
    """One seed: RelightNet trained (on ``lightings`` of the capture's training lightings: None, all), then both
    evaluations; the numbers the page needs (kept in ``out/result.json``, which a rerun reads instead of training
    again). Every render has the run's bounces of light."""
    from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy
    from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate
    from gra_mi.relightnet.train import TrainConfig, train_relightnet

    transport = run_transport(run)
    config = TrainConfig(steps=steps, seed=seed, training_lightings=lightings, transport=transport)
    model = demos_own(run, config) or out / "relightnet"
    if (out / "result.json").is_file():
        return json.loads((out / "result.json").read_text()) | dict(zip(("seconds", "resumed"), training_seconds(model), strict=True))
    capture, fit = run / "capture", run / "fit"
    if model == out / "relightnet":
        train_relightnet(capture, fit, model, config)
    seconds, resumed = training_seconds(model)
    # The demo's own protocol (its refined sequences set the held-out sequences' frames and scale; only the microfacet
    # and RelightNet rows are read here, the refined rows being the demo's own RelightNet's).
    inputs = replace(EvalInputs.from_run(run), relightnet=model)
    report = evaluate(inputs, out / "eval", EvalConfig(transport=transport))
    splits = {
        name: {stage: {k: report["stages"][stage]["splits"][name][k] for k, _, _ in METRICS} for stage in ("microfacet", "RelightNet")}
        for name in report["protocol"]["splits"]
    }
    lighting_config = EnvmapAccuracyConfig(spp=lighting_spp, transport=transport)
    rows = envmap_accuracy(capture, fit, out.parent / "lighting", relightnet_dir=model, config=lighting_config)
    lighting = {f"{r['map']}|{r['method']}": r["psnr"] for r in rows}
    result = {
        "seed": seed,
        "steps": steps,
        "lightings": lightings,
        "seconds": seconds,
        "resumed": resumed,
        "splits": splits,
        "lighting": lighting,
    }
    (out / "result.json").write_text(json.dumps(result, indent=1) + "\n")
    return result


def demos_own(run: Path, config) -> Path | None:
    """The demo's own RelightNet where it was trained with these options (seed 0 at the demo's steps): not trained again."""
    own = run / "relightnet"
    if not (own / "relightnet.json").is_file():
        return None
    said, defaults = json.loads((own / "provenance.json").read_text()).get("config"), asdict(type(config)())
    # An option added since the demo ran counts at its default.
    return own if said is not None and all(said.get(k, defaults[k]) == v for k, v in asdict(config).items()) else None


def training_seconds(model: Path) -> tuple[float, bool]:
    """The training loop's seconds (its log's last row) and whether the run was resumed from a checkpoint: the log's
    clock restarts at a resume, so a resumed run's seconds count only the part after it."""
    seconds = [float(row["seconds"]) for row in csv.DictReader((model / "train_log.csv").open())]
    return seconds[-1], any(b < a for a, b in zip(seconds[:-1], seconds[1:], strict=True))


def flip_regions(run: Path, model: Path, band: int = 3) -> dict:
    """Where RelightNet's ꟻLIP moves: per held-out camera, the mean over the capture's test frames of the microfacet
    render's and RelightNet's ꟻLIP on the silhouette band (the subject's pixels within ``band`` of its edge) and on
    the interior, at the truth's exposure (as `gra-mi eval` shows them)."""
    from scipy.ndimage import binary_erosion

    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.core.color import display_exposure
    from gra_mi.core.metrics import flip_map, subject_mask
    from gra_mi.fit.fitted import fitted_relighter
    from gra_mi.relightnet.infer import render_view
    from gra_mi.relightnet.model import RelightNet

    capture = Capture.load(run / "capture")
    _, relighter = fitted_relighter(capture.folder, run / "fit", run / "cache" / "seeds", run_transport(run))
    net = RelightNet.load(model, "cpu")
    out: dict = {}
    for cam in capture.eval_cameras:
        sums: dict = {}
        for entry in (f for f in capture.frames if f.split == "test"):
            truth = load_observation(capture, cam, entry.frame)
            mask = subject_mask(truth)
            inner = binary_erosion(mask, iterations=band)
            exposure, lighting = display_exposure(truth, mask), capture.lighting(relighter.ls.stage, entry)
            for stage, stage_net in (("microfacet", None), ("RelightNet", net)):
                error = flip_map(render_view(relighter, stage_net, entry.mesh_frame, cam, lighting).image, truth, exposure)
                for region, where in (("band", mask & ~inner), ("interior", inner)):
                    sums.setdefault((stage, region), []).append(float(error[where].mean()))
        out[cam] = {f"{stage}|{region}": float(np.mean(v)) for (stage, region), v in sums.items()}
    return out


def regions_table(regions: dict) -> list[str]:
    lines = ["| camera | region | microfacet | + RelightNet | change |", "|---|---|---|---|---|"]
    for cam, cells in regions.items():
        for region in ("band", "interior"):
            base, ours = cells[f"microfacet|{region}"], cells[f"RelightNet|{region}"]
            lines.append(f"| {cam} | {region} | {base:.4f} | {ours:.4f} | {ours - base:+.4f} |")
    return lines


def _spread(values: list[float], digits: int) -> str:
    mean = float(np.mean(values))
    return f"{mean:.{digits}f}" if len(values) == 1 else f"{mean:.{digits}f} ± {(max(values) - min(values)) / 2:.{digits}f}"


def headline(runs: list[dict]) -> list[str]:
    """Per held-out camera: the microfacet render, RelightNet (mean ± spread) and the gain, with the goal's verdict."""
    lines = [
        "| split | metric | microfacet | + RelightNet | gain | goal | met |",
        "|---|---|---|---|---|---|---|",
    ]
    goals = {"psnr": (0.5, "≥ +0.5 dB"), "ssim": (0.0, "> 0"), "flip": (0.0, "< 0")}
    for split in runs[0]["splits"]:
        for key, label, digits in METRICS:
            base = [r["splits"][split]["microfacet"][key] for r in runs]
            ours = [r["splits"][split]["RelightNet"][key] for r in runs]
            gains = [o - b for o, b in zip(ours, base, strict=True)]
            bound, said = goals[key]
            mean, spread = float(np.mean(gains)), (max(gains) - min(gains)) / 2
            met = mean < bound if key == "flip" else mean >= bound if key == "psnr" else mean > bound
            verdict = "no" if not met else "yes" if abs(mean) > spread else "by the mean, within the spread"
            lines.append(
                f"| {split} | {label} | {_spread(base, digits)} | {_spread(ours, digits)} | {_spread(gains, digits)} | {said} | {verdict} |"
            )
    return lines


def lighting_table(runs: list[dict]) -> list[str]:
    """Per reference map: far field (the fitted maps) against RelightNet, PSNR against the path-traced truth."""
    methods = sorted({key.split("|")[1] for key in runs[0]["lighting"]})
    maps = list(dict.fromkeys(key.split("|")[0] for key in runs[0]["lighting"]))
    lines = ["| map | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for name in maps:
        cells = [_spread([r["lighting"][f"{name}|{m}"] for r in runs], 2) for m in methods]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def steps_curve(runs: list[dict], all_lightings: int) -> list[str]:
    """RelightNet's gain over its input against its training steps and training lightings (one seed each): what more
    training, or more lightings, buys."""
    splits = list(runs[0]["splits"])
    head = "| training lightings | steps | seed | " + " | ".join(f"{s} PSNR / SSIM / ꟻLIP gain" for s in splits)
    lines = [head + " | training (s) |", "|---|---|---|" + "---|" * len(splits) + "---|"]
    for r in sorted(runs, key=lambda r: (r.get("lightings") or all_lightings, r["steps"], r["seed"])):
        cells = []
        for split in splits:
            base, ours = r["splits"][split]["microfacet"], r["splits"][split]["RelightNet"]
            cells.append(" / ".join(f"{ours[k] - base[k]:+.{d}f}" for k, _, d in METRICS))
        said = f"{r['seconds']:.0f}" + (" (after a resume)" if r.get("resumed") else "")
        count = r.get("lightings") or all_lightings
        lines.append(f"| {count} | {r['steps']} | {r['seed']} | " + " | ".join(cells) + f" | {said} |")
    return lines


def training_lightings(run: Path) -> int:
    """How many distinct lightings lit the capture's training frames (uniform light aside)."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.relightnet.train import lighting_of

    frames = [f for f in Capture.load(run / "capture").frames if f.split == "train"]
    return len({lighting_of(f) for f in frames} - {None})


def markdown(runs: list[dict], run: Path, stamp: str, regions: dict) -> list[str]:
    demo = json.loads((run / "demo.json").read_text())
    lightings = training_lightings(run)
    seeds = [r for r in runs if r["steps"] == demo["preset"]["relightnet_steps"] and not r.get("lightings")]
    said = demo["eval"]["protocol"]
    tall = [s.get("subject_pixels", [0, 0]) for s in said["splits"].values()]
    return [
        "# Results: the demo's RelightNet over training seeds",
        "",
        f"> `benchmarks/demo_seeds.py`, {stamp}; the demo run's capture and fit, RelightNet retrained with each seed ({len(seeds)} seeds); "
        f"every render with {run_transport(run).label}.",
        "",
        f"Held-out cameras under the held-out lighting sequence (`gra-mi eval`), at {said['resolution'][0]}×{said['resolution'][1]}, "
        f"the subject {min(t[0] for t in tall)}–{max(t[1] for t in tall)} pixels tall. Mean ± spread (max − min) / 2 over the seeds; "
        "the microfacet render (RelightNet's input) does not depend on the seed. *met*: the mean meets the goal, and the gain is "
        "larger than its spread (a gain within the run-to-run spread is not one).",
        "",
        *headline(seeds),
        "",
        "Under the reference maps (`gra-mi eval-lighting`, PSNR in dB against the true materials path-traced under each map):",
        "",
        *lighting_table(seeds),
        "",
        "Where the ꟻLIP moves (seed 0; every test frame of each held-out camera): the silhouette band is the subject's "
        "pixels within 3 pixels of its edge, the interior the rest.",
        "",
        *regions_table(regions),
        "",
        "Each run (with `--more-steps`, also longer ones: the demo trains "
        f"{demo['preset']['relightnet_steps']} steps; the learning-rate schedule spans each run's steps; with `--lightings`, "
        f"also on the lit frames of fewer of the capture's {lightings} training lightings, every uniformly lit frame kept). "
        "Training: seconds in the training loop since it last started (noisy: other work may have shared the cores):",
        "",
        *steps_curve(runs, lightings),
        "",
    ]


def measure(run: BenchmarkRun) -> str:
    from gra_mi.relightnet.train import TrainConfig

    args = run.args
    demo = json.loads((args.run / "demo.json").read_text())
    preset = demo["preset"]
    work = args.work or args.run / "seeds"  # kept: a rerun reads each seed's result back
    steps = preset["relightnet_steps"]
    jobs = [(work / f"seed{seed}", seed, steps, None) for seed in range(args.seeds)]
    jobs += [(work / f"steps{more}_seed0", 0, int(more), None) for more in args.more_steps.split(",") if more]
    jobs += [(work / f"lightings{count}_seed0", 0, steps, int(count)) for count in args.lightings.split(",") if count]
    runs = []
    for out, seed, run_steps, lightings in jobs:
        runs.append(train_and_score(args.run, out, seed, run_steps, preset["lighting_spp"], lightings))
        print(json.dumps(runs[-1]), file=sys.stderr)
    own = demos_own(args.run, TrainConfig(steps=preset["relightnet_steps"], transport=run_transport(args.run)))
    regions = flip_regions(args.run, own or work / "seed0" / "relightnet")
    return "\n".join(markdown(runs, args.run, run.stamp(preset["name"]), regions))


def arguments(parser) -> None:
    parser.add_argument("--run", type=Path, required=True, help="A `gra-mi demo` output folder (its capture/ and fit/ are used).")
    parser.add_argument("--seeds", type=int, default=3, help="RelightNet training seeds 0 … N−1. Default: 3.")
    parser.add_argument("--more-steps", default="", help="Also train seed 0 this many steps, comma-separated (the steps curve).")
    parser.add_argument(
        "--lightings", default="", help="Also train seed 0 on this many of the training lightings, comma-separated (the lightings curve)."
    )


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, torch=True)
