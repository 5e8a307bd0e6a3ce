"""Pretrain the tiny AutoencoderKLWan that stands in for Wan2.1's VAE on CPU (gra_mi/data/tiny_vae.safetensors).

The refiner's tiny configuration needs a VAE that actually reconstructs (a random one decodes noise), as the real
sizes have Wan2.1's pretrained VAE. This script trains the tiny config (70 k parameters) as a plain autoencoder
(MSE on the posterior mean, which is what the refiner encodes with) on 5-frame clips (two latent frames: the causal first frame and one 4-frame group) of:
procedural textured balls under changing light (gra_mi.refiner_data.synthetic_sequence), smooth random colour
fields with moving edges, log-encoded envmaps, and, when given, the frames of a capture (``--capture``).

    .venv/bin/python pipelines/pretrain_tiny_vae.py --minutes 12 --capture outputs/demo/capture

With ``--capture``, only its training cameras' frames are trained on, and every ``--eval-every`` minutes the round
trip (encode + decode) of its held-out cameras' test frames is scored as the refiner sees them (half resolution,
display PSNR over the subject, and the temporal error of ``gra-mi eval``): the curve (CSV + PNG beside ``--out``)
says what a model size and a training time buy. ``--minutes 0 --init FILE`` only scores FILE.
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
    """Half-resolution videos of the capture's training cameras (its held-out cameras are kept for scoring)."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.io import read_exr
    from gra_mi.refiner.data import image_to_video

    clips = []
    for name in Capture.load(folder).train_cameras:
        cam = folder / "images" / name
        files = sorted(cam.glob("frame_*.exr"))
        imgs = [torch.from_numpy(read_exr(f)[..., :3]) for f in files]
        if len(imgs) < frames:
            continue
        video = torch.stack(imgs).permute(3, 0, 1, 2)  # (3, N, H, W)
        video = F.interpolate(video, scale_factor=0.5, mode="area")
        exposure = 0.8 / max(float(torch.quantile(video.mean(0).flatten(), 0.99)), 1e-6)
        clips.append(image_to_video(video, exposure))
    return clips


def held_out_frames(folder: Path, frames: int = 5) -> list[tuple[torch.Tensor, float]]:
    """(linear video (3, T, H, W) at half resolution, padded to multiples of 16; its display exposure) of the first
    ``frames`` test frames of each held-out camera."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.core.metrics import display_exposure

    capture = Capture.load(folder)
    test = [f.frame for f in capture.frames if f.split == "test"][:frames]
    videos = []
    for cam in capture.eval_cameras:
        imgs = torch.stack([torch.from_numpy(load_observation(capture, cam, f)) for f in test]).permute(3, 0, 1, 2)
        imgs = F.interpolate(imgs, scale_factor=0.5, mode="area")  # (4, T, H/2, W/2): what the refiner data holds
        h, w = imgs.shape[-2:]
        imgs = F.pad(imgs, (0, (-w) % 16, 0, (-h) % 16))
        rgb, alpha = imgs[:3], imgs[3]
        exposure = display_exposure(rgb[:, 0].permute(1, 2, 0).numpy(), alpha[0].numpy() > 0.5)
        videos.append((rgb, alpha, exposure))
    return videos


@torch.no_grad()
def round_trip_scores(vae, videos) -> tuple[float, float]:
    """Mean display PSNR over the subject and mean temporal error of encode + decode on the held-out videos."""
    from gra_mi.core.metrics import compare, temporal_error
    from gra_mi.refiner.data import image_to_video, video_to_image

    psnrs, temporals = [], []
    for rgb, alpha, exposure in videos:
        x = image_to_video(rgb, exposure)[None]  # as the refiner data shows frames: the 99th percentile at 0.8
        recon = video_to_image(vae.decode(vae.encode(x).latent_dist.mode()).sample[0], exposure)
        frames = [recon[:, t].permute(1, 2, 0).numpy() for t in range(rgb.shape[1])]
        truths = [rgb[:, t].permute(1, 2, 0).numpy() for t in range(rgb.shape[1])]
        masks = [alpha[t].numpy() > 0.5 for t in range(rgb.shape[1])]
        psnrs += [compare(f, t, m)["psnr"] for f, t, m in zip(frames, truths, masks, strict=True)]
        temporals.append(temporal_error(frames, truths, masks, exposure))
    return float(np.mean(psnrs)), float(np.mean(temporals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--minutes", type=float, default=12.0, help="Training time budget. Default: 12.")
    parser.add_argument("--capture", type=Path, default=None, help="A capture folder whose frames join the training data.")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "gra_mi" / "data" / "tiny_vae.safetensors")
    parser.add_argument("--seed", type=int, default=0, help="Random seed. Default: 0.")
    parser.add_argument("--base-dim", type=int, default=None, help="Channels of the first stage. Default: the shipped config's.")
    parser.add_argument("--dim-mult", default=None, help="Channel multipliers per stage, e.g. 1,2,2,2. Default: the shipped config's.")
    parser.add_argument("--lr", type=float, default=1e-3, help="Peak learning rate (cosine decay over the budget). Default: 1e-3.")
    parser.add_argument("--init", type=Path, default=None, help="Start from these weights (with --minutes 0: only score them).")
    parser.add_argument("--eval-every", type=float, default=2.0, help="Minutes between held-out scores (with --capture). Default: 2.")
    args = parser.parse_args()
    from diffusers import AutoencoderKLWan
    from safetensors.torch import load_file, save_file

    from gra_mi.refiner.model import VAE_CONFIGS

    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    config = dict(VAE_CONFIGS["tiny"])
    if args.base_dim is not None:
        config["base_dim"] = args.base_dim
    if args.dim_mult is not None:
        config["dim_mult"] = [int(m) for m in args.dim_mult.split(",")]
    vae = AutoencoderKLWan(**config)
    if args.init is not None:
        vae.load_state_dict(load_file(str(args.init)))
    parameters = sum(p.numel() for p in vae.parameters())
    print(f"VAE {config}: {parameters / 1e3:.0f} k parameters", flush=True)
    opt = torch.optim.Adam(vae.parameters(), lr=args.lr)
    size, frames = 64, 5
    captured = capture_clips(args.capture, size, frames) if args.capture else []
    held_out = held_out_frames(args.capture) if args.capture else []
    curve: list[tuple[float, int, float, float]] = []

    def score(elapsed: float) -> None:
        if held_out:
            vae.eval()
            curve.append((elapsed, step, *round_trip_scores(vae, held_out)))
            vae.train()
            print(f"held out: {elapsed:.0f} s, step {step}: PSNR {curve[-1][2]:.2f} dB, temporal {curve[-1][3]:.2f}", flush=True)

    t0, step = time.perf_counter(), 0
    budget = args.minutes * 60
    next_score = 0.0
    while time.perf_counter() - t0 < budget:
        if time.perf_counter() - t0 >= next_score:
            score(time.perf_counter() - t0)
            next_score += args.eval_every * 60
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
            group["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min((time.perf_counter() - t0) / budget, 1))))
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
    score(time.perf_counter() - t0)
    if curve:
        from gra_mi.core.io import atomic_write_text, pyplot, save_figure

        rows = ["seconds,steps,held_out_psnr_db,held_out_temporal"] + [f"{t:.1f},{s},{p:.3f},{e:.4f}" for t, s, p, e in curve]
        atomic_write_text(args.out.with_suffix(".csv"), "\n".join(rows) + "\n")
        fig, ax = pyplot().subplots(figsize=(5, 3.2))
        ax.plot([t / 60 for t, *_ in curve], [p for _, _, p, _ in curve], "o-")
        ax.axhline(30, color="grey", ls="--", lw=0.8)
        ax.set(
            xlabel="training minutes (2 CPU cores)", ylabel="held-out round trip PSNR (dB)", title=f"{parameters / 1e3:.0f} k parameters"
        )
        save_figure(fig, args.out.with_suffix(".png"))
    if args.minutes > 0:
        from gra_mi.core.io import atomic_path

        with atomic_path(args.out) as tmp:
            save_file({k: v.contiguous() for k, v in vae.state_dict().items()}, str(tmp))
        print(f"wrote {args.out} after {step} steps")


if __name__ == "__main__":
    main()
