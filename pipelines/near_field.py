"""Near-field relighting (paper "Near-field relighting"): a point light circling the subject while it moves.

    .venv/bin/python pipelines/near_field.py scenes/tiny_lightstage.xml --out outputs/near_field

Writes the light's path as a light path file (``lights.json``: one keyframe per frame on a circle around the subject
at chest height), relights the sequence with it through ``gra-mi relight --lights`` (LEDs off, soft shadows from the
light's sphere, e.g. the arm shadowing the torso, the paper's envmap conditioning of every frame), and writes a contact
sheet of evenly spaced frames: render | conditioning envmap. The same file can be edited and passed to
``gra-mi relight SCENE --lights lights.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from gra_mi.apps.relight import RelightConfig, collect_lights, relight_batch, select
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_write_text, read_exr, write_png
from gra_mi.core.runtime import choose_variant
from gra_mi.render.light_path import LightPath
from gra_mi.render.plugins import register_plugins
from gra_mi.stage.scene import LightstageScene


def circle_path(frames: list[int], distance: float, height: float, intensity: float, radius: float) -> dict:
    """One keyframe per frame: the light goes once around the subject's vertical axis over ``frames``."""
    keyframes = []
    for k, frame in enumerate(frames):
        a = 2 * math.pi * k / len(frames)
        keyframes.append({"frame": frame, "position": [distance * math.sin(a), height, distance * math.cos(a)]})
    return {"lights": [{"name": "circling", "type": "point", "radius": radius, "intensity": intensity, "keyframes": keyframes}]}


def contact_sheet(out: Path, frames: list[int], camera: str, rows: int = 6) -> Path:
    """Render | conditioning for up to ``rows`` evenly spaced frames."""
    shown = [frames[round(i)] for i in np.linspace(0, len(frames) - 1, min(rows, len(frames)))]
    images = [read_exr(out / "lights" / camera / f"frame_{frame:04d}.exr")[..., :3] for frame in shown]
    bright = max(float(np.percentile(np.stack(images), 99.5)), 1e-6)  # one exposure for the sheet: frames stay comparable
    lines = []
    for frame, image in zip(shown, images, strict=True):
        env = read_exr(out / "lights" / "conditioning" / f"frame_{frame:04d}.exr")[..., :3]
        env = env / max(float(env.max()), 1e-9) * bright
        scale = max(1, image.shape[0] // env.shape[0])
        env = np.repeat(np.repeat(env, scale, axis=0), scale, axis=1)[: image.shape[0]]
        lines.append(np.concatenate([image, np.pad(env, ((0, image.shape[0] - env.shape[0]), (0, 0), (0, 0)))], axis=1))
    width = max(line.shape[1] for line in lines)
    sheet = np.concatenate([np.pad(line, ((0, 0), (0, width - line.shape[1]), (0, 0))) for line in lines], axis=0)
    write_png(out / "contact_sheet.png", sheet, exposure=None)
    return out / "contact_sheet.png"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scene", type=Path, help="Lightstage scene XML.")
    parser.add_argument("--frames", default="all", help="Frames the light circles over: 'all', 'A:B' or a comma list. Default: all.")
    parser.add_argument("--camera", default="0", help="Camera index or name. Default: 0.")
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
        ls = LightstageScene.load(args.scene)
        frames = select(args.frames, ls.sequence.num_frames, "frames", integers=True)
        camera = ls.stage.camera(args.camera).name
        atomic_write_text(
            args.out / "lights.json", json.dumps(circle_path(frames, args.distance, args.height, args.intensity, args.radius), indent=1)
        )
        lights = collect_lights(ls.stage, {}, [], {}, paths=[LightPath.load(args.out / "lights.json")])
        relight_batch(ls, args.out, lights, frames=frames, cameras=[camera], config=RelightConfig(uv_resolution=args.uv_resolution))
        print(f"wrote {len(frames)} near-field renders, {args.out / 'lights.json'} and {contact_sheet(args.out, frames, camera)}")
    except GraMiInputError as exc:
        print(f"near_field: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
