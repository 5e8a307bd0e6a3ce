"""RelightNet's held-out gain against the number of training lightings synthesized from a capture's OLATs.

On a static OLAT capture and its fit, RelightNet is trained with the capture's own training frames plus N procedural
maps on the LEDs (targets: the OLAT sums; `train-relightnet --synthesized-lightings N`), N = 4, 48, 256, 1024 by
default, each with the same steps, and scored by `gra-mi eval` on the held-out cameras: the capture's held-out
envmap frames and held-out OLATs (truth: the capture's images) and library maps no run trains on (truth: the OLAT
sum). The gain is RelightNet's metric minus the microfacet render's (its input); with `--seeds`, the largest N is
trained with several seeds and their spread reported. Prints a Markdown page.

    .venv/bin/python benchmarks/relightnet_lightings.py --capture CAP --fit FIT [--counts 4,48,256,1024] [--steps 1000]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark

GROUPS = ("held-out envmaps", "held-out OLATs", "library maps (Σ OLAT truth)")


def group_of(name: str, about: dict) -> str:
    if name.startswith("field_"):
        return "library maps (Σ OLAT truth)"
    return "held-out OLATs" if about["lighting"] == "OLATs" else "held-out envmaps"


def train_and_score(capture: Path, fit: Path, work: Path, count: int, steps: int, seed: int, library: int) -> dict:
    from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate
    from gra_mi.relightnet.train import TrainConfig, train_relightnet

    out = work / f"n{count}_seed{seed}"
    start = time.perf_counter()
    train_relightnet(capture, fit, out / "relightnet", TrainConfig(steps=steps, synthesized_lightings=count, seed=seed), overwrite=True)
    seconds = time.perf_counter() - start
    report = evaluate(EvalInputs(capture, fit, out / "relightnet"), out / "eval", EvalConfig(library_envmaps=library))
    gains: dict[str, dict[str, list]] = {}
    for split, about in report["protocol"]["splits"].items():
        a, b = report["stages"]["microfacet"]["splits"][split], report["stages"]["RelightNet"]["splits"][split]
        entry = gains.setdefault(group_of(split, about), {"psnr": [], "ssim": [], "flip": [], "base": []})
        entry["psnr"].append(b["psnr"] - a["psnr"])
        entry["ssim"].append(b["ssim"] - a["ssim"])
        entry["flip"].append(b["flip"] - a["flip"])
        entry["base"].append(a["psnr"])
    return {
        "count": count,
        "seed": seed,
        "seconds": seconds,
        "gains": {g: {k: float(np.mean(v)) for k, v in e.items()} for g, e in gains.items()},
    }


def markdown(runs: list[dict], steps: int, stamp: str) -> list[str]:
    lines = [
        "# Results: RelightNet against the number of training lightings",
        "",
        f"> `benchmarks/relightnet_lightings.py`, {stamp}; {steps} steps per run.",
        "",
        "Gain = RelightNet − microfacet render (its input) on the held-out cameras, per lighting group, by `gra-mi eval`",
        "(PSNR in dB, SSIM, ꟻLIP: negative is better). Several seeds: mean ± spread (max − min) / 2.",
        "",
        "| training lightings | seeds | group | microfacet PSNR | PSNR gain | SSIM gain | ꟻLIP change | training (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for count in dict.fromkeys(r["count"] for r in runs):
        mine = [r for r in runs if r["count"] == count]
        for group in GROUPS:
            values = {k: [r["gains"][group][k] for r in mine if group in r["gains"]] for k in ("psnr", "ssim", "flip", "base")}
            if not values["psnr"]:
                continue
            said = {k: _spread(v, 2 if k == "psnr" else 3) for k, v in values.items()}
            seconds = np.mean([r["seconds"] for r in mine])
            lines.append(
                f"| {count} | {len(mine)} | {group} | {np.mean(values['base']):.2f} | {said['psnr']} | {said['ssim']} | {said['flip']} | {seconds:.0f} |"
            )
    return lines


def _spread(values: list[float], digits: int) -> str:
    mean = float(np.mean(values))
    if len(values) == 1:
        return f"{mean:+.{digits}f}"
    return f"{mean:+.{digits}f} ± {(max(values) - min(values)) / 2:.{digits}f}"


def measure(run: BenchmarkRun) -> str:
    args = run.args
    counts = [int(c) for c in args.counts.split(",")]
    runs = []
    for count in counts:
        for seed in range(args.seeds if count == counts[-1] else 1):
            runs.append(train_and_score(args.capture, args.fit, run.work, count, args.steps, seed, args.library))
            print(json.dumps(runs[-1]), file=sys.stderr)
    return "\n".join(markdown(runs, args.steps, run.stamp("olat")))


def arguments(parser) -> None:
    parser.add_argument("--capture", type=Path, required=True, help="A static OLAT capture.")
    parser.add_argument("--fit", type=Path, required=True, help="Its fit (gra-mi fit).")
    parser.add_argument("--counts", default="4,48,256,1024", help="Numbers of synthesized lightings. Default: 4,48,256,1024.")
    parser.add_argument("--steps", type=int, default=1000, help="Training steps per run. Default: 1000.")
    parser.add_argument("--seeds", type=int, default=1, help="Seeds for the largest count (the spread). Default: 1.")
    parser.add_argument("--library", type=int, default=8, help="Held-out library maps scored. Default: 8.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, torch=True)
