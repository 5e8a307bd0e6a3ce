"""Video refiner speed: tiny-config training step and rollout frames/s on CPU; memory against rollout length;
and, where a GPU exists, the real 1.3B configuration (random weights) per window at 1024×544 against the paper's
840 ms of video-model time per frame on an H100.

    .venv/bin/python benchmarks/refiner.py [--quick] [--real-1.3b-cpu]

Prints a markdown table; every row of a comparison is measured in this one run.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from gra_mi.refiner_data import RefinerDataset, synthetic_dataset  # noqa: E402
from gra_mi.refiner_model import RefinerConfig, VideoRefiner, parameter_counts  # noqa: E402
from gra_mi.refiner_train import ErrorBank, RefinerTrainConfig, encode_window, flow_matching_loss  # noqa: E402


def train_step_times(model: VideoRefiner, dataset: RefinerDataset, repeats: int) -> dict[str, float]:
    config = RefinerTrainConfig()
    optimizer = torch.optim.AdamW(model.trainable_parameters(), lr=1e-4)
    banks = (ErrorBank(50, 32), ErrorBank(50, 32))
    name = dataset.names("train")[0]
    enc_t, step_t = [], []
    for i in range(repeats):
        rng = np.random.default_rng(i)
        t0 = time.perf_counter()
        enc = encode_window(model, dataset.window(name, 0, 17), seeded=5 if i % 2 else 0)
        t1 = time.perf_counter()
        result = flow_matching_loss(model, enc, config, rng, torch.Generator().manual_seed(i), banks)
        optimizer.zero_grad()
        result.loss.backward()
        optimizer.step()
        t2 = time.perf_counter()
        enc_t.append(t1 - t0)
        step_t.append(t2 - t1)
    return {"encode": statistics.median(enc_t), "step": statistics.median(step_t)}


def rollout_in_subprocess(model_dir: Path, data_dir: Path, sequence: str, frames: int, steps: int) -> dict:
    """Each length in a fresh process, so peak memory (max RSS) is that rollout's own."""
    code = (
        "import json,sys,torch; torch.set_num_threads(2); from gra_mi.refiner_infer import refine_to_folder;"
        f"s=refine_to_folder('{model_dir}','{data_dir}','{sequence}','{data_dir}/out_{frames}',steps={steps},frames={frames},write_exr_frames=False);"
        "s.pop('per_frame'); print(json.dumps(s))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env={**os.environ, "GRA_MI_QUIET": "1"})
    import json

    return json.loads(out.stdout.strip().splitlines()[-1])


def real_forward(size: str, frames: int, height: int, width: int, device: str, dtype=torch.bfloat16) -> dict:
    """One forward of the real transformer (random weights) on a window + reference frame."""
    from diffusers import WanVACETransformer3DModel

    from gra_mi.refiner_model import TRANSFORMER_CONFIGS, latent_frames

    t0 = time.perf_counter()
    with torch.device(device):
        model = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS[size]).to(dtype).eval()
    build = time.perf_counter() - t0
    f = latent_frames(frames) + 1
    shape = (1, 16, f, height // 8, width // 8)
    x = torch.randn(shape, device=device, dtype=dtype)
    control = torch.randn(1, 96, *shape[2:], device=device, dtype=dtype)
    text = torch.randn(1, 512, 4096, device=device, dtype=dtype)
    times = []
    with torch.no_grad():
        for _ in range(3 if device == "cuda" else 1):
            if device == "cuda":
                torch.cuda.synchronize()
            t = time.perf_counter()
            model(x, torch.tensor([500.0], device=device), text, control_hidden_states=control, return_dict=False)
            if device == "cuda":
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t)
    tokens = f * (height // 16) * (width // 16)
    return {"build_s": build, "forward_s": min(times), "tokens": tokens}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="Fewer repeats and shorter rollouts (a CI smoke run).")
    parser.add_argument(
        "--real-1.3b-cpu", dest="real_cpu", action="store_true", help="Also run one 1.3B forward on the CPU (about 5 GB of RAM, minutes)."
    )
    parser.add_argument("--euler-steps", type=int, default=10, help="Euler steps per window for the rollouts. Default: 10.")
    args = parser.parse_args()
    torch.set_num_threads(2)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        lengths = [17, 41] if args.quick else [41, 161]
        for res in (64,) if args.quick else (64, 128):
            data = synthetic_dataset(tmp / f"data{res}", {0: (2, 0)}, frames=17, height=res, width=res)
            model = VideoRefiner(RefinerConfig())
            t = train_step_times(model, data, 3 if args.quick else 8)
            rows.append(
                (
                    f"tiny training step, 17×{res}×{res} (+ reference frame)",
                    f"{1000 * t['step']:.0f} ms",
                    f"VAE encoding of the window: {1000 * t['encode']:.0f} ms (cached for un-augmented windows)",
                )
            )
        counts = parameter_counts(model)
        model.save(tmp / "model")
        long = synthetic_dataset(tmp / "long", {0: (0, 1)}, frames=17, height=64, width=64, test_frames=max(lengths))
        results = {n: rollout_in_subprocess(tmp / "model", long.folder, "s0_test00", n, args.euler_steps) for n in lengths}
        for n, r in results.items():
            rows.append(
                (
                    f"tiny rollout, {n} frames at 64×64, {args.euler_steps} Euler steps",
                    f"{r['frames_per_second']:.2f} frames/s",
                    f"{r['windows']} windows, peak RSS {r['peak_rss_mib']:.0f} MiB",
                )
            )
        a, b = (results[n]["peak_rss_mib"] for n in lengths)
        rows.append(("peak memory, longest / shortest rollout", f"{b / a:.3f}×", f"{lengths[-1]} vs {lengths[0]} frames: flat with length"))
    if torch.cuda.is_available():
        r = real_forward("1.3B", 17, 544, 1024, "cuda")
        per_window = r["forward_s"] * 20  # 20 Euler steps, one forward each (no CFG: the refiner runs without a negative prompt)
        rows.append(
            (
                "1.3B forward, 17×544×1024 + reference (GPU, bf16, random weights)",
                f"{1000 * r['forward_s']:.0f} ms",
                f"{r['tokens']} tokens",
            )
        )
        rows.append(
            (
                "1.3B window, 20 Euler steps",
                f"{per_window:.1f} s",
                f"{1000 * per_window / 12:.0f} ms per new frame (12 per window); paper: 840 ms/frame (H100)",
            )
        )
    else:
        rows.append(("1.3B per window at 1024×544 (GPU)", "not measured", "no CUDA GPU on this machine"))
    if args.real_cpu:
        r = real_forward("1.3B", 17, 64, 128, "cpu", torch.float32)
        rows.append(
            (
                "1.3B forward on CPU, 17×64×128 + reference (random weights)",
                f"{r['forward_s']:.1f} s",
                f"{r['tokens']} tokens; built in {r['build_s']:.0f} s",
            )
        )
    print(
        f"tiny config: {counts['total']:,} parameters, {counts['trainable']:,} trainable (LoRA {counts['lora']:,}, VACE {counts['vace']:,}, env attention {counts['env_attention']:,})"
    )
    print(f"max RSS of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB\n")
    print("| measurement | value | notes |\n|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
