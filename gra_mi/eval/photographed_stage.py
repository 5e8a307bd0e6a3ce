"""A user's stage written as a Mitsuba scene (the shipped ``scenes/user_stage``), photographed as a capture on it would
be: its films at twice the size, a held-out sensor between its two, path-traced under all LEDs at once, each LED alone
and two held-out patterns (a key light, a rim light). The benchmarks that import and fit photographs share it
(benchmarks/from_scene.py, benchmarks/set_light.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

PHOTO_SPP = 128
HELD_OUT = "between"
HELD_OUT_LIGHTINGS = ("key", "rim")
HELD_OUT_SENSOR = f"""
    <sensor type="perspective" id="{HELD_OUT}">
        <float name="fov" value="30"/>
        <transform name="to_world"><lookat origin="1.6, 1.2, 2.0" target="0, 1, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="320"/><integer name="height" value="240"/>
            <string name="pixel_format" value="rgba"/></film>
    </sensor>
"""


def photographed_stage(scene: Path, folder: Path, shapes: str = "") -> Path:
    """The user's stage ``scene`` (its ``body.obj`` and ``albedo.png`` beside it) as a capture photographs it: its films
    at twice the size, a held-out sensor between the two, and ``shapes`` (Mitsuba XML: a set) added."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("body.obj", "albedo.png"):
        shutil.copyfile(scene.parent / name, folder / name)
    text = scene.read_text()
    for size, doubled in (("160", "320"), ("120", "240")):
        text = text.replace(f'value="{size}"/>', f'value="{doubled}"/>')
    text = text.replace("\n    <emitter", HELD_OUT_SENSOR + "\n    <emitter", 1).replace("</scene>", f"{shapes}</scene>")
    (folder / "scene.xml").write_text(text)
    return folder / "scene.xml"


def stage_lightings(folder: Path, stage, intensities: np.ndarray) -> tuple[Path, list[tuple[int, np.ndarray]]]:
    """``folder/lighting.json`` (EasyMocap's) and each frame's emitted intensities: all LEDs, each LED alone (training);
    a key light (3 LEDs, the rest at 5 %) and a rim light (the LEDs behind), held out, as patterns in W/sr: emitted =
    value × gain, the gains the scene's intensities over their mean (as `import mitsuba` states them)."""
    mean, count = float(intensities.mean()), len(intensities)
    toward = stage.led_positions - stage.center
    key = np.full(count, 0.05 * mean)
    key[np.argsort(-toward @ np.array([1.0, 0.3, 1.0]))[:3]] = mean
    rim = np.where(toward[:, 2] < -0.3, mean, 0.0)
    entries = [{"frame": 0, "uniform": 1.0}] + [{"frame": 1 + k, "led": k} for k in range(count)]
    emitted = [intensities] + [np.eye(count)[k][:, None] * intensities for k in range(count)]
    for name, values in zip(HELD_OUT_LIGHTINGS, (key, rim), strict=True):
        (folder / f"{name}.json").write_text(json.dumps({"intensities": values.tolist()}))
        entries.append({"frame": len(entries), "split": "test", "pattern": f"{name}.json"})
        emitted.append(values[:, None] / mean * intensities)
    (folder / "lighting.json").write_text(json.dumps({"frames": entries}))
    return folder / "lighting.json", list(enumerate(emitted))


def photograph(path: Path, frames: list[tuple[int, np.ndarray]], folder: Path | None = None, seed: int = 0, spp: int = PHOTO_SPP) -> None:
    """Each frame's photographs (Mitsuba's ``path``, max_depth 3: the light reflected once more, glossy and diffuse)
    into ``folder`` (None: beside the scene ``path``), seeded by ``seed`` + the frame's number (another ``seed``: the
    same photographs taken again, their own noise)."""
    import mitsuba as mi

    from gra_mi.capture.mitsuba_capture import write_photographs

    scene, path_tracer = mi.load_file(str(path), parallel=False), mi.load_dict({"type": "path", "max_depth": 3})
    for n, emitted in frames:
        write_photographs(scene, path.parent if folder is None else folder, n, emitted, path_tracer, spp, seed=seed + n)
