"""Render one frame and camera of a lightstage scene under every envmap in a folder (and their plates).

    .venv/bin/python pipelines/envmap_sweep.py scenes/tiny_lightstage.xml outputs/envmaps/test --out outputs/sweep

Writes one EXR + PNG per envmap and a contact sheet (render over background plate | envmap preview).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import write_exr, write_png
from gra_mi.core.progress import progress
from gra_mi.core.runtime import choose_variant
from gra_mi.stage.envmap import background_plate, load_envmap
from gra_mi.stage.scene import LightstageScene, composite_over, render


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="Lightstage scene XML.")
    parser.add_argument("envmaps", type=Path, help="Folder of lat-long EXR envmaps.")
    parser.add_argument("--frame", type=int, default=0, help="Subject frame. Default: 0.")
    parser.add_argument("--camera", default="0", help="Camera index or name. Default: 0.")
    parser.add_argument("--spp", type=int, default=64, help="Samples per pixel (Mitsuba direct). Default: 64.")
    parser.add_argument("--out", type=Path, default=Path("outputs/sweep"), help="Output folder. Default: outputs/sweep.")
    parser.add_argument("--variant", default=None, help="Mitsuba variant (default: automatic).")
    args = parser.parse_args(argv)
    try:
        paths = sorted(args.envmaps.glob("*.exr"))
        if not paths:
            raise GraMiInputError(args.envmaps, "no .exr envmaps found")
        choose_variant(args.variant)
        ls = LightstageScene.load(args.scene, frame=args.frame)
        camera = ls.stage.camera(args.camera)
        rows = []
        for path in progress(paths, description="envmaps"):
            env = load_envmap(path)
            lighting = ls.set_envmap(env)
            image = render(ls, camera.name, "direct", args.spp)
            write_exr(args.out / f"{path.stem}.exr", image)
            shown = composite_over(image, background_plate(env, camera) * lighting.scale)
            write_png(args.out / f"{path.stem}.png", shown, exposure=0.9)
            # The envmap beside the render, resampled to the render's height, at the same exposure.
            h = shown.shape[0] - shown.shape[0] % 2
            thumb = _fit(env, h // 2)
            rows.append(np.concatenate([shown[:h], np.pad(thumb * lighting.scale, ((0, h - thumb.shape[0]), (0, 0), (0, 0)))], axis=1))
        width = max(r.shape[1] for r in rows)
        sheet = np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], axis=0)
        write_png(args.out / "contact_sheet.png", sheet, exposure=0.9)
        print(f"wrote {len(paths)} renders and {args.out / 'contact_sheet.png'}")
    except GraMiInputError as exc:
        print(f"envmap_sweep: error: {exc}", file=sys.stderr)
        return 2
    return 0


def _fit(env: np.ndarray, height: int) -> np.ndarray:
    """Nearest-pixel resize of a lat-long map to the given height (preview only)."""
    rows = np.minimum((np.arange(height) * env.shape[0]) // height, env.shape[0] - 1)
    cols = np.minimum((np.arange(2 * height) * env.shape[1]) // (2 * height), env.shape[1] - 1)
    return env[rows][:, cols]


if __name__ == "__main__":
    sys.exit(main())
