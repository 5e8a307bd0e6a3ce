"""Near-field relighting (paper "Near-field relighting"): a point light moving around the subject.

    .venv/bin/python pipelines/near_field.py scenes/tiny_lightstage.xml --out outputs/near_field

For each light position on a circle around the subject at chest height, renders the one-bounce image (LEDs off,
soft shadows from the light's sphere, e.g. the arm shadowing the torso) and the envmap conditioning the paper
derives for it, and writes a contact sheet: render | conditioning envmap.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import write_exr, write_png
from gra_mi.core.progress import progress
from gra_mi.core.runtime import choose_variant
from gra_mi.render.plugins import register_plugins
from gra_mi.render.point_light import PointLight, conditioning_envmap, conditioning_pattern
from gra_mi.render.relighter import Relighter
from gra_mi.stage.scene import LightstageScene


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="Lightstage scene XML.")
    parser.add_argument("--frame", type=int, default=0, help="Subject frame. Default: 0.")
    parser.add_argument("--camera", default="0", help="Camera index or name. Default: 0.")
    parser.add_argument("--positions", type=int, default=6, help="Light positions on the circle. Default: 6.")
    parser.add_argument("--distance", type=float, default=0.6, help="Circle radius around the subject's axis (m). Default: 0.6.")
    parser.add_argument("--height", type=float, default=1.25, help="Height of the circle (m). Default: 1.25.")
    parser.add_argument("--intensity", type=float, default=1.5, help="Radiant intensity (W/sr). Default: 1.5.")
    parser.add_argument("--radius", type=float, default=0.03, help="Light sphere radius (m). Default: 0.03.")
    parser.add_argument("--uv-resolution", type=int, default=256, help="UV resolution. Default: 256.")
    parser.add_argument("--out", type=Path, default=Path("outputs/near_field"), help="Output folder. Default: outputs/near_field.")
    parser.add_argument("--variant", default=None, help="Mitsuba variant (default: automatic).")
    args = parser.parse_args(argv)
    try:
        choose_variant(args.variant)
        register_plugins()
        ls = LightstageScene.load(args.scene, frame=args.frame)
        relighter = Relighter(ls, args.uv_resolution)
        cam = ls.stage.camera(args.camera)
        off = np.zeros((ls.stage.num_leds, 3))
        rows = []
        for k in progress(range(args.positions), description="light positions"):
            a = 2 * math.pi * k / args.positions
            light = PointLight([args.distance * math.sin(a), args.height, args.distance * math.cos(a)], args.intensity, args.radius)
            image = relighter.render(args.frame, cam.name, off, light).image
            env = conditioning_envmap(ls.stage, conditioning_pattern(ls.stage, ls.scene, light), height=image.shape[0] // 2)
            write_exr(args.out / f"light_{k:02d}.exr", image)
            write_exr(args.out / f"light_{k:02d}_conditioning.exr", env)
            env_shown = env / max(float(env.max()), 1e-9) * float(np.percentile(image[..., :3], 99.5))
            env_shown = np.pad(env_shown, ((0, image.shape[0] - env_shown.shape[0]), (0, 0), (0, 0)))
            rows.append(np.concatenate([image[..., :3], env_shown], axis=1))
        width = max(r.shape[1] for r in rows)
        sheet = np.concatenate([np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows], axis=0)
        write_png(args.out / "contact_sheet.png", sheet, exposure=None)
        print(f"wrote {args.positions} near-field renders and {args.out / 'contact_sheet.png'}")
    except GraMiInputError as exc:
        print(f"near_field: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
