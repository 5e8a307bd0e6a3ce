"""Video refiner speed: tiny-config training step and rollout frames/s on CPU; memory against rollout length;
and, where a GPU exists, the real 1.3B (or 14B) configuration (random weights) at 1024×544 stage by stage against
the paper's runtime table (H100), with each inference mode's distance from the same weights run in float32.

    .venv/bin/python benchmarks/refiner.py [--quick] [--real-1.3b-cpu] [--skip-tiny] [--real-size 14B]
                                           [--real-steps N] [--real-frames N]

Its page: one table; every row of a comparison is measured in this one run (medians).
"""

from __future__ import annotations

import math
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, table_page, timed
from gra_mi.refiner.config import RefinerConfig
from gra_mi.refiner.dataset import RefinerDataset
from gra_mi.refiner.model import VideoRefiner, parameter_counts
from gra_mi.refiner.synthetic import synthetic_dataset
from gra_mi.refiner.train import ErrorBank, RefinerTrainConfig, encode_window, flow_matching_loss


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
        "import json,sys,torch; torch.set_num_threads(2); from gra_mi.refiner.infer import refine_to_folder;"
        f"s=refine_to_folder('{model_dir}','{data_dir}','{sequence}','{data_dir.parent}/rollout_{frames}',steps={steps},frames={frames},write_exr_frames=False);"
        "s.pop('per_frame'); print(json.dumps(s))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env={**os.environ, "GRA_MI_QUIET": "1"})
    if out.returncode != 0:
        raise RuntimeError(f"the rollout of {frames} frames failed:\n{out.stderr[-3000:]}")
    import json

    return json.loads(out.stdout.strip().splitlines()[-1])


PAPER_MS_PER_FRAME = {"VAE env.": 140.2, "Video model": 840.3, "VAE dec.": 145.6}
"""GRA Supp. Tab. "Runtime": H100, averaged over 17-frame generations (model size and step count not stated)."""


def real_window(
    size: str, device: str, height: int, width: int, steps: int, frames: int, folder: Path, float32_reference: bool = True
) -> dict:
    """The real configuration with random weights (DiT bfloat16, VAE float32) through gra-mi's own inference code:
    one 17-frame window stage by stage (the stages of the paper's runtime table), then a rollout of ``frames`` frames."""
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel
    from safetensors.torch import save_file

    from gra_mi.refiner.conditioning import conditioning, seed_mask
    from gra_mi.refiner.config import TRANSFORMER_CONFIGS
    from gra_mi.refiner.flow import euler_sample
    from gra_mi.refiner.infer import rollout
    from gra_mi.refiner.loading import cast_transformer, default_dtype

    cuda = device == "cuda"
    torch.manual_seed(0)
    t0 = time.perf_counter()
    with torch.device(device):
        with default_dtype(torch.bfloat16 if size != "1.3B" else torch.float32):  # the 14B in float32 would not fit
            transformer = cast_transformer(WanVACETransformer3DModel(**TRANSFORMER_CONFIGS[size]), torch.bfloat16)
        backbone = (transformer, AutoencoderKLWan())
    prompt = folder / "prompt.safetensors"
    save_file({"prompt_embeds": torch.randn(1, 512, 4096)}, str(prompt))  # umT5's 512 tokens, as diffusers pads them
    model = VideoRefiner(RefinerConfig(size=size, dtype="bfloat16", prompt_embeds=str(prompt)), backbone=backbone).to(device).eval()
    build = time.perf_counter() - t0
    data = synthetic_dataset(folder / "data", {0: (0, 1)}, frames=17, height=height, width=width, env_height=32, test_frames=frames)
    name = data.names("test")[0]
    win = {k: v.to(device) for k, v in data.window(name, 0, 17).items()}
    mask = seed_mask(17, height, width, 0).to(device)

    def encode():
        return conditioning(model, win["coarse"], mask, win["reference"], win["env"], win["reference_env"])

    timed(encode)  # warm-up (cuDNN autotuning)
    t_encode, (control, env_latents) = timed(encode, 2)
    env = model.env_tokens(env_latents)
    shape = (1, 16, *control.shape[2:])
    x, sigma = torch.randn(shape, device=device), torch.tensor([0.5], device=device)
    with torch.no_grad():
        # Stand-ins for trained layers: nonzero LoRA B (zero at init) and envmap output projections (zero at init).
        for pname, param in model.named_parameters():
            if "lora_B" in pname or (pname.startswith("env_attention.") and pname.endswith("to_out.weight")):
                param.normal_(0.0, 1e-2)
        repeats = 3 if cuda else 1
        timed(lambda: model(x, sigma, control, env))
        t_full, v_trained = timed(lambda: model(x, sigma, control, env), repeats)
        t_no_env = timed(lambda: model(x, sigma, control, None), repeats)[0]
        model.transformer.disable_adapters()
        t_stock = timed(lambda: model(x, sigma, control, None), repeats)[0]
        v_no_lora = model(x, sigma, control, env)
        model.transformer.enable_adapters()
        # The reference: the same weights run in float32 (bf16 → float32 → bf16 round-trips exactly). 14B: no room.
        v_float32 = None
        if float32_reference:
            dtypes = {n: p.dtype for n, p in model.transformer.named_parameters()}
            for param in model.transformer.parameters():
                param.data = param.data.float()
            v_float32 = model(x, sigma, control, env)
            for n, param in model.transformer.named_parameters():
                param.data = param.data.to(dtypes[n])
        change = lambda v: float("nan") if v_float32 is None else float((v - v_float32).norm() / v_float32.norm())  # noqa: E731
        trained_error = change(v_trained)
        model.prepare_for_inference(fuse_lora=False)  # `gra-mi refine --no-fuse-lora`
        env = model.env_tokens(env_latents)
        timed(lambda: model(x, sigma, control, env))
        t_prepared, v_prepared = timed(lambda: model(x, sigma, control, env), repeats)
        model.transformer.fuse_lora()  # = prepare_for_inference(): what `gra-mi refine` samples with, below too
        timed(lambda: model(x, sigma, control, env))
        t_fused, v_fused = timed(lambda: model(x, sigma, control, env), repeats)
        prepared_error, fused_error = change(v_prepared), change(v_fused)
        lora_effect = float((v_no_lora - v_trained).norm() / v_trained.norm())
    t_sample, latents = timed(lambda: euler_sample(model, shape, control, env, steps, 3.0, torch.Generator().manual_seed(0)))
    t_decode, _ = timed(lambda: model.decode(latents[:, :, 1:]))
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    t_rollout, count = timed(lambda: sum(1 for _ in rollout(model, data, name, steps=steps, frames=frames)))
    return {
        "build_s": build,
        "tokens": int(shape[2] * shape[3] * shape[4] // 4),
        "encode_s": t_encode,
        "size": size,
        "forward_s": t_full,
        "forward_no_env_s": t_no_env,
        "forward_stock_s": t_stock,
        "forward_prepared_s": t_prepared,
        "forward_fused_s": t_fused,
        "prepared_error": prepared_error,
        "trained_error": trained_error,
        "fused_error": fused_error,
        "lora_effect": lora_effect,
        "sample_s": t_sample,
        "decode_s": t_decode,
        "rollout_s": t_rollout,
        "rollout_frames": count,
        "peak_gib": torch.cuda.max_memory_allocated() / 2**30 if cuda else float("nan"),
    }


def real_rows(r: dict, where: str, height: int, width: int, steps: int) -> list[tuple[str, str, str]]:
    def off(key: str) -> str:  # distance of a mode's velocity from the float32 network's
        return "float32 reference not run" if math.isnan(r[key]) else f"{100 * r[key]:.2f} % from the float32 network"

    per_frame = {"VAE env.": r["encode_s"] / 17, "Video model": r["sample_s"] / 17, "VAE dec.": r["decode_s"] / 17}
    rows = [
        (
            f"{r['size']} DiT forward, 17×{height}×{width} + reference ({where}, bf16, random weights)",
            f"{1000 * r['forward_s']:.0f} ms",
            f"{r['tokens']} tokens; LoRA r32, envmap attention (float32) after every block; "
            f"{off('trained_error')} (rel. L2 of the velocity)",
        ),
        (
            "  same, without the envmap attention",
            f"{1000 * r['forward_no_env_s']:.0f} ms",
            f"envmap attention costs {100 * (r['forward_s'] / r['forward_no_env_s'] - 1):.1f} %",
        ),
        (
            "  same, without LoRA (stock WAN)",
            f"{1000 * r['forward_stock_s']:.0f} ms",
            f"unmerged LoRA costs {100 * (r['forward_no_env_s'] / r['forward_stock_s'] - 1):.1f} %",
        ),
        (
            "  envmap attention in bf16, LoRA kept apart (`refine --no-fuse-lora`)",
            f"{1000 * r['forward_prepared_s']:.0f} ms",
            f"{r['forward_s'] / r['forward_prepared_s']:.2f}× faster; {off('prepared_error')}",
        ),
        (
            "  + LoRA folded into the bf16 weights: what `refine` runs",
            f"{1000 * r['forward_fused_s']:.0f} ms",
            f"{r['forward_s'] / r['forward_fused_s']:.2f}× faster; {off('fused_error')} "
            f"(the stand-in LoRA itself changes the velocity by {100 * r['lora_effect']:.1f} %)",
        ),
    ]
    for stage, seconds in per_frame.items():
        what = {
            "VAE env.": "VAE encoding (control video ×2, reference, envmaps)",
            "Video model": f"{steps} Euler steps",
            "VAE dec.": "VAE decoding",
        }
        paper = f"paper ({stage}, H100): {PAPER_MS_PER_FRAME[stage]} ms" if where == "GPU" else ""
        rows.append((f"one window, {what[stage]}, per frame (/17)", f"{1000 * seconds:.0f} ms", paper))
    total = sum(per_frame.values())
    paper = f"paper: {sum(PAPER_MS_PER_FRAME.values()):.1f} ms" if where == "GPU" else ""
    rows.append(("one window, all three, per frame (/17)", f"{1000 * total:.0f} ms", paper))
    memory = f"; peak GPU memory {r['peak_gib']:.1f} GiB" if where == "GPU" else ""
    rows.append(
        (
            f"rollout of {r['rollout_frames']} frames (hand-off of 5 per window)",
            f"{1000 * r['rollout_s'] / r['rollout_frames']:.0f} ms/frame",
            f"{r['rollout_s']:.1f} s in all{memory}",
        )
    )
    return rows


def tiny_rows(tmp: Path, quick: bool, euler_steps: int) -> tuple[list[tuple[str, str, str]], dict[str, int]]:
    """The tiny configuration on the CPU: training steps, rollouts, memory against rollout length; its parameter counts."""
    rows = []
    lengths = [17, 41] if quick else [41, 161]
    for res in (64,) if quick else (64, 128):
        data = synthetic_dataset(tmp / f"data{res}", {0: (2, 0)}, frames=17, height=res, width=res)
        model = VideoRefiner(RefinerConfig())
        t = train_step_times(model, data, 3 if quick else 8)
        rows.append(
            (
                f"tiny training step, 17×{res}×{res} (+ reference frame)",
                f"{1000 * t['step']:.0f} ms",
                f"VAE encoding of the window: {1000 * t['encode']:.0f} ms (cached for un-augmented windows)",
            )
        )
    model.save(tmp / "model")
    long = synthetic_dataset(tmp / "long", {0: (0, 1)}, frames=17, height=64, width=64, test_frames=max(lengths))
    results = {n: rollout_in_subprocess(tmp / "model", long.folder, "s0_test00", n, euler_steps) for n in lengths}
    for n, r in results.items():
        rows.append(
            (
                f"tiny rollout, {n} frames at 64×64, {euler_steps} Euler steps",
                f"{r['frames_per_second']:.2f} frames/s",
                f"{r['windows']} windows, peak RSS {r['peak_rss_mib']:.0f} MiB",
            )
        )
    a, b = (results[n]["peak_rss_mib"] for n in lengths)
    rows.append(("peak memory, longest / shortest rollout", f"{b / a:.3f}×", f"{lengths[-1]} vs {lengths[0]} frames: flat with length"))
    return rows, parameter_counts(model)


def measure(run: BenchmarkRun) -> str:
    args = run.args
    if not torch.cuda.is_available():
        torch.set_num_threads(2)  # the CPU rows are comparable across machines of the project's CI size
    rows = []
    counts = None
    for part in ("tiny", "gpu", "cpu"):
        (run.work / part).mkdir(exist_ok=True)
    if not args.skip_tiny:
        tiny, counts = tiny_rows(run.work / "tiny", args.quick, args.euler_steps)
        rows += tiny
    if torch.cuda.is_available():
        size = args.real_size
        r = real_window(size, "cuda", 544, 1024, args.real_steps, args.real_frames, run.work / "gpu", float32_reference=size == "1.3B")
        rows += real_rows(r, "GPU", 544, 1024, args.real_steps)
    else:
        rows.append((f"{args.real_size} per window at 1024×544 (GPU)", "not measured", "no CUDA GPU on this machine"))
    if args.real_cpu:
        r = real_window("1.3B", "cpu", 64, 128, 2, 17, run.work / "cpu")
        rows += real_rows(r, "CPU", 64, 128, 2)
    notes = []
    if counts:
        notes.append(
            f"tiny config: {counts['total']:,} parameters, {counts['trainable']:,} trainable (LoRA {counts['lora']:,}, VACE {counts['vace']:,}, env attention {counts['env_attention']:,})"
        )
    notes.append(f"max RSS of this process: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")
    return table_page(
        "Video refiner speed", "refiner.py", run.stamp("tiny + real configurations"), rows, notes, ("measurement", "value", "notes")
    )


def arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true", help="Fewer repeats and shorter rollouts (a CI smoke run).")
    parser.add_argument(
        "--real-1.3b-cpu", dest="real_cpu", action="store_true", help="Also run one 1.3B forward on the CPU (about 5 GB of RAM, minutes)."
    )
    parser.add_argument("--euler-steps", type=int, default=10, help="Euler steps per window for the tiny rollouts. Default: 10.")
    parser.add_argument("--real-steps", type=int, default=20, help="Euler steps per window for the 1.3B timings. Default: 20.")
    parser.add_argument("--real-size", choices=["1.3B", "14B"], default="1.3B", help="Real configuration timed on a GPU. Default: 1.3B.")
    parser.add_argument("--real-frames", type=int, default=41, help="Frames of the real-size rollout (17 per window). Default: 41.")
    parser.add_argument("--skip-tiny", action="store_true", help="Only the 1.3B rows (on a GPU machine: skips the CPU measurements).")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, mitsuba=False)
