"""Pretrain the tiny refiner's prior (gra_mi/data/tiny_refiner_prior.safetensors): a conditional flow model that has
already learnt "coarse render → path-traced frame", so that the demo's few hundred CPU steps fine-tune it (the paper's
few-shot adaptation of WAN2.1-VACE) instead of starting from noise.

Data: refiner sequences of a subject unlike the demo's. By default the ``tiny`` capture preset's subject, made in
``--work``: a Mitsuba path-traced capture (`gra-mi capture --preset tiny --renderer path`), its one-bounce fit
(`gra-mi fit`) and the fit's microfacet renders as the coarse input, cut around the subject (`gra-mi refiner-data
--zoom`). Or ``--data``: a refiner data folder of your own.

Training: `gra-mi train-refiner`'s flow matching (without error recycling, which the fine-tuning adds), from random
weights (RefinerConfig.prior off), with every DiT weight trainable (RefinerTrainConfig.train_base) and no LoRA. It resumes from its checkpoint in
``--work/model``. Then the DiT (with VACE), envmap layers and prompt embedding go to ``--out``.

    .venv/bin/python pipelines/pretrain_tiny_refiner.py --steps 3800

The shipped file was made in two runs: 3,000 steps of flow on the latents (before the tiny size's residual flow
existed), then 800 steps of residual flow with ``--init`` on that run's folder (17 + 4.5 minutes on 2 cores). One run
of 3,800 steps follows the same recipe on residual flow throughout; it is not the same file bit for bit.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_OUT = Path(__file__).resolve().parent.parent / "gra_mi" / "data" / "tiny_refiner_prior.safetensors"


def _gra_mi(*args: str) -> None:
    print("$ gra-mi " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "gra_mi.cli", *args], check=True)


def make_data(work: Path, scale: float, zoom: float) -> Path:
    """The tiny preset's capture → fit → refiner data (each step resumes or is skipped when done)."""
    capture, fit, data = work / "capture", work / "fit", work / "data"
    if not (capture / "capture.json").is_file():
        _gra_mi("capture", "--preset", "tiny", "--renderer", "path", "--out", str(capture))
    if not (fit / "albedo.exr").is_file():
        _gra_mi("fit", str(capture), "--out", str(fit))
    if not (data / "dataset.json").is_file():
        _gra_mi("refiner-data", str(capture), "--fit", str(fit), "--out", str(data), "--scale", str(scale), "--zoom", str(zoom))
    return data


def export_prior(model_dir: Path, out: Path) -> dict[str, int]:
    """The trained refiner's DiT, envmap layers and prompt embedding (not the VAE, which ships apart) → ``out``."""
    from safetensors.torch import load_file, save_file

    from gra_mi.core.io import atomic_path

    state = load_file(str(model_dir / "refiner.safetensors"))
    keep = ("transformer.", "env_attention.", "env_mlp.", "prompt_embeds")
    # float16 halves the wheel (weights this small lose nothing that shows: the refiner computes in float32)
    prior = {k: v.half().contiguous() for k, v in state.items() if k.startswith(keep) and "lora_" not in k}
    with atomic_path(out) as tmp:
        save_file(prior, str(tmp), metadata={"source": str(model_dir)})
    return {"tensors": len(prior), "parameters": int(sum(v.numel() for v in prior.values()))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--work", type=Path, default=Path("outputs/pretrain_refiner"), help="Working folder (data, training run).")
    parser.add_argument("--data", type=Path, default=None, help="A refiner data folder to train on. Default: made from the tiny preset.")
    parser.add_argument(
        "--scale",
        type=float,
        default=0.25,
        help="Delivered frame scale of the made data (the tiny preset's subject then spans as "
        "many pixels as the demo's at 0.5). Default: 0.25.",
    )
    parser.add_argument("--zoom", type=float, default=4.0, help="Subject crop magnification of the made data, as the demo's. Default: 4.")
    parser.add_argument("--steps", type=int, default=600, help="Training steps. Default: 600.")
    parser.add_argument("--lr", type=float, default=1e-3, help="AdamW learning rate. Default: 1e-3.")
    parser.add_argument("--seed", type=int, default=0, help="Random seed. Default: 0.")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"The prior's file. Default: {DEFAULT_OUT}.")
    parser.add_argument(
        "--init", type=Path, default=None, help="Continue from this training folder (a refiner folder) instead of random weights."
    )
    args = parser.parse_args()
    from gra_mi.refiner.config import RefinerConfig
    from gra_mi.refiner.train import RefinerTrainConfig, train_refiner

    t0 = time.perf_counter()
    data = args.data or make_data(args.work, args.scale, args.zoom)
    made = time.perf_counter() - t0
    model_dir = args.work / "model"
    # Plain flow matching, as a base model is pretrained: error recycling feeds the model its own errors, which
    # from random weights swamp what it must first learn (copy the control through); the fine-tuning recycles.
    # a prior is fine-tuned before anything is delivered: the mix is chosen then, not here
    config = RefinerTrainConfig(steps=args.steps, lr=args.lr, seed=args.seed, train_base=True, error_recycling=False, choose_mix=False)
    train_refiner(data, model_dir, config, RefinerConfig(prior=False, lora_rank=0, seed=args.seed), init=args.init)
    trained = time.perf_counter() - t0 - made
    counts = export_prior(model_dir, args.out)
    summary = {"data": str(data), "steps": args.steps, "data_seconds": made, "train_seconds": trained, **counts}
    (args.work / "prior.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(
        f"wrote {args.out}: {counts['parameters']:,} parameters, {args.steps} steps in {trained / 60:.1f} min (data: {made / 60:.1f} min)"
    )


if __name__ == "__main__":
    main()
