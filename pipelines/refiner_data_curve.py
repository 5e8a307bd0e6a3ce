"""What it would take for the tiny refiner to earn its place: held-out quality against the amount of training data.

For each training-set size, synthetic refiner data (`gra-mi refiner-data --synthetic`: a textured ball under a new
light each frame; the coarse input lacks the fine texture and the highlight), the tiny refiner trained on it from
the shipped prior (every DiT weight, plain flow matching), then measured on the held-out test sequence:

- ``ratio``: its clean-latent estimate from pure noise (σ = 1: the target's conditional mean as the model sees it)
  against the target, relative to the input's own latents (:func:`gra_mi.refiner.train.mean_estimate_error`).
  Below 1 it predicts part of what the input misses;
- the refined video against its input (`gra-mi refine`; display PSNR, ꟻLIP and the temporal error over the
  subject, as `gra-mi eval`), which is at best level with the input while the ratio is ≥ 1.

Writes ``--work``/curve.csv and curve.png and prints the table (docs/results/limitations.md).

    .venv/bin/python pipelines/refiner_data_curve.py --sequences 8 32 128 --steps 1500
"""

from __future__ import annotations

import argparse
import csv
import json
import time
from pathlib import Path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("outputs/refiner_data_curve"), help="Working folder (data, models, curve).")
    parser.add_argument(
        "--sequences", type=int, nargs="+", default=[8, 32, 128], help="Training-set sizes (17-frame sequences). Default: 8 32 128."
    )
    parser.add_argument("--steps", type=int, default=1500, help="Training steps per size. Default: 1500.")
    parser.add_argument("--lr", type=float, default=1e-3, help="AdamW learning rate. Default: 1e-3.")
    parser.add_argument("--resolution", type=int, default=64, help="Frame height and width (multiple of 16). Default: 64.")
    parser.add_argument("--test-frames", type=int, default=41, help="Frames of the held-out test sequence. Default: 41.")
    parser.add_argument("--sample-steps", type=int, default=10, help="Euler steps per window when refining. Default: 10.")
    args = parser.parse_args()

    from gra_mi.core.errors import require_positive

    require_positive({"steps": args.steps, "lr": args.lr, "test-frames": args.test_frames, "sample-steps": args.sample_steps})
    require_positive({f"sequences[{i}]": n for i, n in enumerate(args.sequences)})
    from gra_mi.core.io import atomic_write_text
    from gra_mi.refiner.config import RefinerConfig
    from gra_mi.refiner.infer import refine_to_folder
    from gra_mi.refiner.model import VideoRefiner
    from gra_mi.refiner.synthetic import synthetic_dataset
    from gra_mi.refiner.train import RefinerTrainConfig, mean_estimate_error, train_refiner

    rows = []
    for n in args.sequences:
        t0 = time.perf_counter()
        size = args.resolution
        data = synthetic_dataset(args.work / f"data_{n}", {0: (n, 1)}, height=size, width=size, test_frames=args.test_frames)
        model_dir = args.work / f"model_{n}"
        if not (model_dir / "refiner.json").is_file():  # a finished size is kept; an interrupted one resumes
            config = RefinerTrainConfig(steps=args.steps, lr=args.lr, train_base=True, error_recycling=False)
            train_refiner(data.folder, model_dir, config, RefinerConfig())
        known = mean_estimate_error(VideoRefiner.load(model_dir), data, "test")
        test = data.names("test")[0]
        folder = args.work / f"refined_{n}"
        refine_to_folder(model_dir, data.folder, test, folder, steps=args.sample_steps, overwrite=True)
        scores = _scores(data, test, folder)
        rows.append({"sequences": n, "ratio": known["ratio"], **scores, "minutes": (time.perf_counter() - t0) / 60})
        print(json.dumps(rows[-1]), flush=True)
    with open(args.work / "curve.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    _plot(rows, args.work / "curve.png")
    table = [
        "| training sequences | estimate / input (σ = 1) | refined − input (dB) | ꟻLIP input → refined | temporal input → refined | minutes |",
        "|---|---|---|---|---|---|",
    ]
    table += [
        f"| {r['sequences']} | {r['ratio']:.3f} | {r['psnr_refined'] - r['psnr_input']:+.2f} | {r['flip_input']:.4f} → "
        f"{r['flip_refined']:.4f} | {r['temporal_input']:.4f} → {r['temporal_refined']:.4f} | {r['minutes']:.1f} |"
        for r in rows
    ]
    atomic_write_text(args.work / "curve.md", "\n".join(table) + "\n")
    print("\n".join(table))


def _scores(data, sequence: str, folder: Path) -> dict:
    """Display PSNR, ꟻLIP and the temporal error of the input and the refined frames against the truth, as
    `gra-mi eval` computes them (gra_mi.core.metrics), over the subject of each frame."""
    import numpy as np

    from gra_mi.core.io import read_exr
    from gra_mi.core.metrics import compare, flip, temporal_error

    n = len(list((folder / "frames").glob("*.exr")))
    truth = [data.delivered(sequence, i, "target") for i in range(n)]
    videos = {
        "input": [data.delivered(sequence, i, "coarse") for i in range(n)],
        "refined": [read_exr(folder / "frames" / f"frame_{i:04d}.exr")[..., :3] for i in range(n)],
    }
    masks = [(c.max(axis=-1) > 0) | (t.max(axis=-1) > 0) for c, t in zip(videos["input"], truth, strict=True)]
    out = {}
    for key, frames in videos.items():
        triples = list(zip(frames, truth, masks, strict=True))
        out[f"psnr_{key}"] = float(np.mean([compare(f, t, m)["psnr"] for f, t, m in triples]))
        out[f"flip_{key}"] = float(np.mean([flip(f, t, m) for f, t, m in triples]))
        out[f"temporal_{key}"] = temporal_error(frames, truth, masks, data.exposure)
    return out


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = [r["sequences"] for r in rows]
    fig, (a, b) = plt.subplots(1, 2, figsize=(9, 3.4))
    a.plot(n, [r["ratio"] for r in rows], "o-")
    a.axhline(1.0, color="grey", ls="--", lw=1)
    a.set(xscale="log", xlabel="training sequences", ylabel="estimate / input error", title="what the refiner knows (held out)")
    b.plot(n, [r["psnr_refined"] - r["psnr_input"] for r in rows], "o-")
    b.axhline(-0.4, color="grey", ls="--", lw=1)
    b.set(xscale="log", xlabel="training sequences", ylabel="refined − input (dB)", title="the refined video (held out)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
