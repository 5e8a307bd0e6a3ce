"""Pretrain the tiny AutoencoderKLWan that stands in for Wan2.1's VAE on CPU (gra_mi/data/tiny_vae.safetensors).

The refiner's tiny configuration needs a VAE that actually reconstructs (a random one decodes noise), as the real
sizes have Wan2.1's pretrained VAE. This script trains the tiny config (gra_mi.refiner.config.VAE_CONFIGS: 4× in space, 4× in time, 16 channels) as a
plain autoencoder (MSE on the posterior mean, which is what the refiner encodes with, plus the same error after 4×
area averaging) on 5-frame clips (two latent frames: the causal first frame and one 4-frame group) of: procedural
textured balls under changing light (gra_mi.refiner.synthetic.synthetic_sequence), smooth random colour fields with
moving edges, log-encoded envmaps, and the subject crops of captures' training cameras (``--capture``, repeatable),
cut as `gra-mi refiner-data` cuts them. It then measures the latents' per-channel mean and std, which the file
carries in its metadata (the refiner normalises latents with them).

    .venv/bin/python pipelines/pretrain_tiny_vae.py --steps 3000 --capture CAPTURE_A --capture CAPTURE_B

Every ``--eval-every`` steps the round trip (encode + decode) of the held-out cameras' test frames of ``--score``
(default: the first capture) is scored as `gra-mi refine` delivers it (the crop's change put back into the
half-resolution frames; display PSNR over the subject, and the temporal error of ``gra-mi eval``): the curve (CSV +
PNG beside ``--out``, with the seconds each point took) says what a model size and training buy. The budget is in steps,
so a run is the same run on any machine. ``--steps 0 --init FILE`` only scores FILE
(and, with another ``--out``, writes it there with its latent statistics).
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
    from gra_mi.refiner.dataset import env_to_video, image_to_video
    from gra_mi.refiner.synthetic import synthetic_sequence

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


def _capture_crops(folder: Path, cameras: str, frames: list[int] | None, zoom: float, scale: float = 0.5):
    """Per camera of ``cameras`` ('train' or 'eval'): the subject crops as the refiner data cuts them
    (gra_mi.refiner.data: a fixed box per camera, magnified ``zoom``× over ``scale``), linear (3, T, h, w), with the
    whole frames at ``scale`` (T, fh, fw, 4), the box and the refiner data's exposure."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.refiner.data import subject_boxes
    from gra_mi.refiner.dataset import crop_box

    capture = Capture.load(folder)
    names = capture.train_cameras if cameras == "train" else capture.eval_cameras
    out = []
    for cam in names:
        chosen = frames if frames is not None else [f.frame for f in capture.frames if f.split == "train"]
        full = np.stack([load_observation(capture, cam, f) for f in chosen])
        whole = F.interpolate(torch.from_numpy(full).permute(0, 3, 1, 2), scale_factor=scale, mode="area").permute(0, 2, 3, 1).numpy()
        size, (box,) = subject_boxes([whole[..., 3] > 0.5], zoom)
        crop = torch.from_numpy(crop_box(full[..., :3], box, scale, size)).permute(3, 0, 1, 2)
        lum = crop.mean(0)
        exposure = 0.25 / max(float(lum[lum > 0].median()), 1e-6)  # as the refiner data: the subject's median at 0.25
        out.append((crop, whole, box, exposure))
    return out


def capture_clips(folder: Path, zoom: float) -> list[torch.Tensor]:
    """The training cameras' subject crops as videos in [-1, 1] (the held-out cameras are kept for scoring)."""
    from gra_mi.refiner.dataset import image_to_video

    return [image_to_video(crop, exposure) for crop, _, _, exposure in _capture_crops(folder, "train", None, zoom)]


def held_out_frames(folder: Path, zoom: float, frames: int = 5):
    """The first ``frames`` test frames of each held-out camera, cut as the refiner data cuts them."""
    from gra_mi.capture.dataset import Capture

    test = [f.frame for f in Capture.load(folder).frames if f.split == "test"][:frames]
    return _capture_crops(folder, "eval", test, zoom)


@torch.no_grad()
def round_trip_scores(vae, videos) -> tuple[float, float]:
    """Mean display PSNR over the subject and mean temporal error of encode + decode on the held-out videos, in the
    delivered frames (the crop's change put back, as `gra-mi refine` does)."""
    from gra_mi.core.metrics import compare, temporal_error
    from gra_mi.refiner.dataset import image_to_video, paste_box, video_to_image

    psnrs, temporals = [], []
    for crop, whole, box, exposure in videos:
        x = image_to_video(crop, exposure)[None]
        recon = video_to_image(vae.decode(vae.encode(x).latent_dist.mode()).sample[0], exposure)
        change = (recon - video_to_image(x[0], exposure)).permute(1, 2, 3, 0).numpy()
        truths = [w[..., :3] for w in whole]
        results = [paste_box(t, c, box) for t, c in zip(truths, change, strict=True)]
        masks = [w[..., 3] > 0.5 for w in whole]
        psnrs += [compare(f, t, m)["psnr"] for f, t, m in zip(results, truths, masks, strict=True)]
        temporals.append(temporal_error(results, truths, masks, exposure))
    return float(np.mean(psnrs)), float(np.mean(temporals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000, help="Optimisation steps (about 12 minutes on 2 cores). Default: 3000.")
    parser.add_argument(
        "--capture",
        type=Path,
        action="append",
        default=[],
        help="A capture folder whose training cameras join the training data (repeatable).",
    )
    parser.add_argument(
        "--score",
        type=Path,
        default=None,
        help="A capture whose held-out cameras' test frames score the round trip. Default: the first --capture.",
    )
    parser.add_argument("--zoom", type=float, default=4.0, help="Subject crop magnification, as `gra-mi refiner-data --zoom`. Default: 4.")
    parser.add_argument("--size", type=int, default=96, help="Training patch size in pixels. Default: 96.")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "gra_mi" / "data" / "tiny_vae.safetensors")
    parser.add_argument("--seed", type=int, default=0, help="Random seed. Default: 0.")
    parser.add_argument("--hidden", type=int, default=None, help="Channels of the convolutional branches. Default: the shipped config's.")
    parser.add_argument("--lr", type=float, default=1e-3, help="Peak learning rate (cosine decay over the steps). Default: 1e-3.")
    parser.add_argument("--init", type=Path, default=None, help="Start from these weights (with --steps 0: only score them).")
    parser.add_argument("--eval-every", type=int, default=500, help="Steps between held-out scores (with --capture). Default: 500.")
    args = parser.parse_args()
    if args.steps < 0 or args.eval_every < 1:
        parser.error(f"--steps must be >= 0 and --eval-every >= 1, got {args.steps} and {args.eval_every}")
    from safetensors.torch import load_file, save_file

    from gra_mi.refiner.config import VAE_CONFIGS
    from gra_mi.refiner.tiny_vae import TinyVideoAutoencoder

    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    config = dict(VAE_CONFIGS["tiny"])
    if args.hidden is not None:
        config["hidden"] = args.hidden
    vae = TinyVideoAutoencoder(**config)
    if args.init is not None:
        vae.load_state_dict(load_file(str(args.init)))
    parameters = sum(p.numel() for p in vae.parameters())
    print(f"VAE {config}: {parameters / 1e3:.0f} k parameters", flush=True)
    opt = torch.optim.Adam(vae.parameters(), lr=args.lr)
    size, frames = args.size, 5
    captured = [clip for folder in args.capture for clip in capture_clips(folder, args.zoom)]
    scored = args.score or (args.capture[0] if args.capture else None)
    held_out = held_out_frames(scored, args.zoom) if scored else []
    curve: list[tuple[float, int, float, float]] = []

    def score(elapsed: float) -> None:
        if held_out:
            vae.eval()
            curve.append((elapsed, step, *round_trip_scores(vae, held_out)))
            vae.train()
            print(f"held out: {elapsed:.0f} s, step {step}: PSNR {curve[-1][2]:.2f} dB, temporal {curve[-1][3]:.2f}", flush=True)

    t0, step = time.perf_counter(), 0
    while step < args.steps:
        if step % args.eval_every == 0:
            score(time.perf_counter() - t0)
        batch = []
        for _ in range(2):
            if captured and rng.random() < 0.6:
                v = captured[int(rng.integers(len(captured)))]
                s = int(rng.integers(v.shape[1] - frames + 1))
                i, j = int(rng.integers(max(v.shape[2] - size, 0) + 1)), int(rng.integers(max(v.shape[3] - size, 0) + 1))
                clip = v[:, s : s + frames, i : i + size, j : j + size]
                clip = F.pad(clip, (0, size - clip.shape[3], 0, size - clip.shape[2]), value=-1.0)  # black past the crop
                batch.append(clip)
            else:
                batch.append(procedural_clip(rng, size, frames))
        x = torch.stack(batch)
        for group in opt.param_groups:  # cosine decay over the steps
            group["lr"] = args.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * step / args.steps)))
        recon = vae.decode(vae.encode(x).latent_dist.mode()).sample
        # + the error after 4× area averaging (what survives the crop's way back into the delivered frames; zero at
        # the exact start, and kept there)
        loss = F.mse_loss(recon, x) + 10 * F.mse_loss(F.avg_pool3d(recon, (1, 4, 4)), F.avg_pool3d(x, (1, 4, 4)))
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
    if args.steps > 0 or (args.init is not None and args.out.resolve() != args.init.resolve()):
        import json

        from gra_mi.core.io import atomic_path

        mean, std = latent_statistics(vae, captured, rng)
        meta = {"latents_mean": json.dumps(mean), "latents_std": json.dumps(std)}
        with atomic_path(args.out) as tmp:
            save_file({k: v.contiguous() for k, v in vae.state_dict().items()}, str(tmp), metadata=meta)
        print(f"wrote {args.out} after {step} steps")


@torch.no_grad()
def latent_statistics(vae, clips: list[torch.Tensor], rng: np.random.Generator, count: int = 24) -> tuple[list[float], list[float]]:
    """Per-channel mean and std of the latents (the refiner normalises with them, as diffusers with Wan2.1's): over
    17-frame windows of the capture clips, or procedural clips without any."""
    vae.eval()
    latents = []
    for i in range(count):
        if clips:
            v = clips[i % len(clips)]
            s = int(rng.integers(max(v.shape[1] - 17, 0) + 1))
            x = v[None, :, s : s + 17]
        else:
            x = procedural_clip(rng, 96, 17)[None]
        latents.append(vae.encode(x).latent_dist.mode()[0].flatten(1))
    z = torch.cat(latents, dim=1)
    return [round(float(m), 5) for m in z.mean(1)], [round(max(float(d), 1e-3), 5) for d in z.std(1)]


if __name__ == "__main__":
    main()
