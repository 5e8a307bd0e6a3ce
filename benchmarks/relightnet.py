"""RelightNet speed: forward pass at 512² UV and one training step (forward, rasterise, L1, backward, Adam).

    .venv/bin/python benchmarks/relightnet.py [--resolution 512] [--repeats 5]

Prints a markdown table (medians). The paper reports 25.4 ms for the forward pass on an H100.
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
    args = parser.parse_args(argv)

    from gra_mi.relightnet.model import RelightNet, RelightNetConfig
    from gra_mi.render.bridge import IN_CHANNELS, sample_texture

    device = "cuda" if torch.cuda.is_available() else "cpu"
    w, h = (int(v) for v in args.image.split("x"))
    model = RelightNet(RelightNetConfig(resolution=args.resolution)).to(device)
    params = sum(p.numel() for p in model.parameters())
    x = torch.randn(1, IN_CHANNELS, args.resolution, args.resolution, device=device)
    env = torch.rand(1, 3, 16, 32, device=device)
    grid = torch.rand(1, h, w, 2, device=device) * 2 - 1
    target = torch.rand(1, 3, h, w, device=device)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    def timed(fn):
        fn()
        sync()
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            fn()
            sync()
            times.append(time.perf_counter() - t)
        return statistics.median(times)

    with torch.no_grad():
        t_forward = timed(lambda: model(x, env))

    def step():
        optimizer.zero_grad(set_to_none=True)
        loss = (sample_texture(model(x, env), grid) - target).abs().mean()
        loss.backward()
        optimizer.step()

    t_step = timed(step)
    where = torch.cuda.get_device_name() if device == "cuda" else f"CPU, {torch.get_num_threads()} threads"
    print(f"\n# RelightNet — {where}, {params / 1e6:.2f} M parameters\n")
    print("| measurement | value |")
    print("|---|---|")
    print(f"| forward at {args.resolution}² UV | {1e3 * t_forward:.0f} ms |")
    print(f"| training step (forward, rasterise into {w}×{h}, L1, backward, Adam) | {1e3 * t_step:.0f} ms |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
