"""Pretrain the tiny AutoencoderKLWan that stands in for Wan2.1's VAE on CPU (gra_mi/data/tiny_vae.safetensors).

The refiner's tiny configuration needs a VAE that actually reconstructs (a random one decodes noise), as the real
sizes have Wan2.1's pretrained VAE. This script trains the tiny config (70 k parameters) as a plain autoencoder
(MSE on the posterior mean, which is what the refiner encodes with) on 5-frame clips (two latent frames: the causal first frame and one 4-frame group) of:
procedural textured balls under changing light (gra_mi.refiner_data.synthetic_sequence), smooth random colour
fields with moving edges, log-encoded envmaps, and, when given, the frames of a capture (``--capture``).

    .venv/bin/python pipelines/pretrain_tiny_vae.py --minutes 12 --capture outputs/demo/capture
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F


def procedural_clip(rng: np.random.Generator, size: int, frames: int) -> torch.Tensor:
    from gra_mi.refiner.data import env_to_video, image_to_video, synthetic_sequence

    kind = rng.choice(3, p=[0.6, 0.25, 0.15])
    if kind == 0:
        seq = synthetic_sequence(frames, size, size, 16, int(rng.integers(1000)), int(rng.integers(1 << 30)))
        key = "target" if rng.random() < 0.6 else "coarse"
        return image_to_video(torch.from_numpy(seq[key]) * float(rng.uniform(0.7, 1.5)), 1.0).permute(3, 0, 1, 2)
    if kind == 1:
        seq = synthetic_sequence(frames, 16, 16, size // 2, int(rng.integers(1000)), int(rng.integers(1 << 30)))
        env = torch.from_numpy(seq["env"])  # (T, size/2, size, 3)
        return (
            env_to_video(env, float(rng.uniform(0.5, 4))).permute(3, 0, 1, 2)[:, :, :, : size // 2].repeat(1, 1, 2, 2)[:, :, :size, :size]
        )
    # smooth colour field with a moving edge
    y, x = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    out = []
    c = torch.from_numpy(rng.uniform(-1, 1, (4, 3))).float()
    a, b, speed = rng.uniform(0, 2 * math.pi), rng.uniform(2, 8), rng.uniform(-0.05, 0.05)
    for t in range(frames):
        edge = torch.sigmoid((x * math.cos(a) + y * math.sin(a) - 0.5 - speed * t) * 30)
        wave = 0.5 + 0.5 * torch.sin(b * (x + y) + t * speed * 10)
        img = c[0][:, None, None] * edge + c[1][:, None, None] * (1 - edge) + 0.4 * (wave - 0.5) * c[2][:, None, None]
        out.append(img.clamp(-1, 1))
    return torch.stack(out, 1)


def capture_clips(folder: Path, size: int, frames: int):
    from gra_mi.core.io import read_exr
    from gra_mi.refiner.data import image_to_video

    clips = []
    for cam in sorted((folder / "images").iterdir()):
        files = sorted(cam.glob("frame_*.exr"))
        imgs = [torch.from_numpy(read_exr(f)[..., :3]) for f in files]
        if len(imgs) < frames:
            continue
        video = torch.stack(imgs).permute(3, 0, 1, 2)  # (3, N, H, W)
        video = F.interpolate(video, scale_factor=0.5, mode="area")
        exposure = 0.8 / max(float(torch.quantile(video.mean(0).flatten(), 0.99)), 1e-6)
        clips.append(image_to_video(video, exposure))
    return clips


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=12.0, help="Training time budget. Default: 12.")
    parser.add_argument("--capture", type=Path, default=None, help="A capture folder whose frames join the training data.")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "gra_mi" / "data" / "tiny_vae.safetensors")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    from diffusers import AutoencoderKLWan
    from safetensors.torch import save_file

    from gra_mi.refiner.model import VAE_CONFIGS

    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    vae = AutoencoderKLWan(**VAE_CONFIGS["tiny"])
    opt = torch.optim.Adam(vae.parameters(), lr=1e-3)
    size, frames = 64, 5
    captured = capture_clips(args.capture, size, frames) if args.capture else []
    t0, step = time.perf_counter(), 0
    budget = args.minutes * 60
    while time.perf_counter() - t0 < budget:
        batch = []
        for _ in range(2):
            if captured and rng.random() < 0.4:
                v = captured[int(rng.integers(len(captured)))]
                s = int(rng.integers(v.shape[1] - frames + 1))
                i, j = int(rng.integers(v.shape[2] - size + 1)), int(rng.integers(v.shape[3] - size + 1))
                batch.append(v[:, s : s + frames, i : i + size, j : j + size])
            else:
                batch.append(procedural_clip(rng, size, frames))
        x = torch.stack(batch)
        for group in opt.param_groups:  # cosine decay over the time budget
            group["lr"] = 1e-3 * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min((time.perf_counter() - t0) / budget, 1))))
        recon = vae.decode(vae.encode(x).latent_dist.mode()).sample
        loss = F.mse_loss(recon, x)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(vae.parameters(), 1.0)
        opt.step()
        step += 1
        if step % 50 == 0:
            psnr = 10 * math.log10(4 / max(F.mse_loss(recon, x).item(), 1e-12))
            print(f"step {step}  {time.perf_counter() - t0:.0f} s  mse {loss.item():.5f}  psnr {psnr:.1f} dB", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in vae.state_dict().items()}, str(args.out))
    print(f"wrote {args.out} after {step} steps")


if __name__ == "__main__":
    main()
