"""RelightNet speed: forward pass at 512² UV and one training step (forward, rasterise, L1, backward, Adam), for
each space-to-depth factor side by side (patch 1: every UNet level at full texel resolution, the layout before
issue 15; the default puts the top level at 128², i.e. patch 4 at 512²).

    .venv/bin/python benchmarks/relightnet.py [--resolution 512] [--repeats 5] [--patches 1,2,4]

Prints a markdown table (medians, interleaved repeats so that a noisy machine slows every row alike). The paper
reports 25.4 ms for the forward pass on an H100. Goal (issue 15): ≤ 200 ms on 2 CPU cores, ≤ 25 ms on a GPU.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=512, help="UV resolution. Default: 512.")
    parser.add_argument("--repeats", type=int, default=5, help="Timed repeats (after one warm-up). Default: 5.")
    parser.add_argument("--image", default="1024x540", help="Camera image size WxH for the training step. Default: 1024x540.")
    parser.add_argument("--patches", default="1,2,4", help="Space-to-depth factors to compare. Default: 1,2,4.")
    parser.add_argument("--no-train-step", action="store_true", help="Time the forward pass only.")
    args = parser.parse_args(argv)

    from gra_mi.relightnet.model import RelightNet, RelightNetConfig
    from gra_mi.render.bridge import IN_CHANNELS, sample_texture

    device = "cuda" if torch.cuda.is_available() else "cpu"
    w, h = (int(v) for v in args.image.split("x"))
    r = args.resolution
    default_patch = RelightNetConfig(resolution=r).patch
    patches = [int(p) for p in args.patches.split(",")]
    models = {p: RelightNet(RelightNetConfig(resolution=r, patch=p)).to(device).eval() for p in patches}
    x = torch.rand(1, IN_CHANNELS, r, r, device=device)
    mask = torch.ones(1, 1, r, r, device=device)
    env = torch.rand(1, 3, 16, 32, device=device)
    grid = torch.rand(1, h, w, 2, device=device) * 2 - 1
    target = torch.rand(1, 3, h, w, device=device)

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    def timed_side_by_side(fns: dict) -> dict:
        for fn in fns.values():
            fn()  # warm-up
        sync()
        times = {k: [] for k in fns}
        for _ in range(args.repeats):
            for k, fn in fns.items():
                t = time.perf_counter()
                fn()
                sync()
                times[k].append(time.perf_counter() - t)
        return {k: statistics.median(v) for k, v in times.items()}

    def forward(model):
        def run():
            with torch.inference_mode():
                model(x, env, mask)

        return run

    def train_step(model):
        optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)

        def run():
            model.train()
            optimizer.zero_grad(set_to_none=True)
            loss = (sample_texture(model(x, env, mask), grid) - target).abs().mean()
            loss.backward()
            optimizer.step()
            model.eval()

        return run

    t_forward = timed_side_by_side({p: forward(m) for p, m in models.items()})
    t_step = {} if args.no_train_step else timed_side_by_side({p: train_step(m) for p, m in models.items()})
    where = torch.cuda.get_device_name() if device == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    print(f"\n# RelightNet at {r}² UV — {where}\n")
    print(f"| patch (UNet top level) | parameters | forward | vs patch {patches[0]} | training step (rasterise into {w}×{h}) |")
    print("|---|---|---|---|---|")
    for p, m in models.items():
        params = sum(q.numel() for q in m.parameters())
        step = f"{1e3 * t_step[p]:.0f} ms" if p in t_step else "—"
        tag = " (default)" if p == default_patch else ""
        print(
            f"| {p} ({r // p}²){tag} | {params / 1e6:.2f} M | {1e3 * t_forward[p]:.0f} ms | {t_forward[patches[0]] / t_forward[p]:.1f}× | {step} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
