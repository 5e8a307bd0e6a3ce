"""An independent reference for gra-mi's UV-space renders: the same frame, maps and lights as a Mitsuba scene with the
``gra_microfacet`` BSDF, rendered by Mitsuba's own ``path`` integrator (``max_depth`` 2: one bounce, 3: one
interreflection, -1: all). Tests and benchmarks compare :class:`~gra_mi.render.relighter.Relighter` renders with it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from gra_mi.core.io import write_exr
from gra_mi.stage.scene import camera_xml, render_mean
from gra_mi.subject.sequence import write_ply


@dataclass(frozen=True)
class HardCase:
    """A view where the body lights itself: a frame of the anny body's ``arm_raise`` clip at 4 frames per loop (0: rest,
    1: arms out, 2: arms above the head), a camera on the spot and a point light near it."""

    name: str
    frame: int
    eye: tuple
    target: tuple
    light: tuple

    def camera(self, size: int = 128):
        from gra_mi.stage.lightstage import Camera, look_at_opencv

        to_world = look_at_opencv(np.array(self.eye, float), np.array(self.target, float))
        return Camera(self.name, size, size, 1.3 * size, 1.3 * size, size / 2, size / 2, to_world)

    def point_light(self, intensity: float = 0.3):
        from gra_mi.render.point_light import PointLight

        return PointLight(np.array(self.light, float), np.full(3, intensity), radius=0.0)


HARD_CASES = (
    HardCase("armpit", 1, (0.9, 1.0, 0.7), (0.2, 1.3, 0.0), (0.6, 0.95, 0.45)),
    HardCase("face under raised arms", 2, (0.1, 1.5, 0.9), (0.0, 1.55, 0.05), (0.3, 1.25, 0.5)),
    HardCase("inner thighs", 0, (0.0, 0.55, 0.9), (0.0, 0.65, 0.0), (0.0, 0.35, 0.45)),
    HardCase("hand by the hip", 0, (1.0, 0.95, 0.5), (0.45, 0.85, 0.05), (0.85, 0.6, 0.35)),
)
HARD_CASE_CLIP, HARD_CASE_FRAMES = "arm_raise", 4


def _emitter(position, intensity) -> str:
    p = ", ".join(f"{x:.9g}" for x in position)
    i = ", ".join(f"{x:.9g}" for x in intensity)
    return f'<emitter type="point"><point name="position" value="{p}"/><rgb name="intensity" value="{i}"/></emitter>'


def path_reference(
    relighter, frame: int, camera, led_intensities: np.ndarray, near_lights=(), max_depth: int = 3, spp: int = 256, folder: Path | str = ".",
    seed: int = 0, set_xml: str = "",
) -> np.ndarray:  # fmt: skip
    """(H, W, 4) Mitsuba ``path`` render of ``relighter``'s frame, maps and LEDs (near field) plus point ``near_lights``
    (radius 0), from ``camera`` (a :class:`~gra_mi.stage.lightstage.Camera` or the rig's name/index). Writes its
    scene's files (the frame's PLY, the maps) into ``folder``. ``set_xml``: the set's shapes, as Mitsuba XML."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    ls, seq = relighter.ls, relighter.ls.sequence
    cam = ls.stage.camera(camera)
    write_ply(folder / "frame.ply", seq.vertices[frame], seq.normals[frame], seq.uvs, seq.faces)
    write_exr(folder / "albedo.exr", relighter.albedo_tex)
    write_exr(folder / "roughness.exr", relighter.roughness_tex)
    on = np.max(led_intensities, axis=1) > 0
    emitters = [_emitter(p, i) for p, i in zip(ls.stage.led_positions[on], np.asarray(led_intensities)[on], strict=True)]
    for light in near_lights:
        if light.radius > 0 or light.is_spot:
            raise ValueError("the path reference takes point lights of radius 0 only")
        emitters.append(_emitter(light.position, light.intensity))
    xml = (
        f'<scene version="3.0.0">{camera_xml(cam, str(spp))}{"".join(emitters)}'
        f'<shape type="ply"><string name="filename" value="{folder / "frame.ply"}"/><boolean name="face_normals" value="false"/>'
        f'<bsdf type="gra_microfacet"><texture type="bitmap" name="albedo"><string name="filename" value="{folder / "albedo.exr"}"/></texture>'
        f'<texture type="bitmap" name="roughness"><string name="filename" value="{folder / "roughness.exr"}"/>'
        f'<boolean name="raw" value="true"/></texture></bsdf></shape>{set_xml}</scene>'
    )
    scene = mi.load_string(xml)
    return render_mean(scene, 0, mi.load_dict({"type": "path", "max_depth": max_depth}), spp, seed)


def bounce_errors(one: np.ndarray, more: np.ndarray, path_one: np.ndarray, path_more: np.ndarray, block: int = 8) -> dict:
    """How a render with more bounces (``more``) and its one-bounce render (``one``) compare with Mitsuba's ``path`` at the
    same depths (``path_one``: max_depth 2, ``path_more``): over the pixels all four cover fully, the relative bias of
    the totals; and in the ``block``² blocks where Mitsuba's one bounce is ≥ 10 % darker than its deeper render
    (where the light after the first bounce matters), the largest relative error of ``more`` and of its added light."""
    covered = np.all([im[..., 3] > 0.999 for im in (one, more, path_one, path_more)], axis=0)
    total = {k: float(im[..., :3][covered].sum()) for k, im in (("one", one), ("more", more), ("p1", path_one), ("p", path_more))}
    h, w = (covered.shape[0] // block) * block, (covered.shape[1] // block) * block

    def blocks(image):
        return image[:h, :w, :3].sum(-1).reshape(h // block, block, w // block, block).sum((1, 3))

    full = covered[:h, :w].reshape(h // block, block, w // block, block).all((1, 3))
    o1, o2, p1, p2 = blocks(one), blocks(more), blocks(path_one), blocks(path_more)
    dark = full & (p1 <= 0.9 * p2)
    out = {
        "covered": float(covered.mean()),
        "bias_one": total["one"] / total["p"] - 1.0,
        "bias_more": total["more"] / total["p"] - 1.0,
        "bias_one_vs_path_one": total["one"] / total["p1"] - 1.0,
        "dark_blocks": int(dark.sum()),
        "dark_block_error_one": float(np.max(np.abs(o1[dark] / p2[dark] - 1.0))) if dark.any() else float("nan"),
        "dark_block_error_more": float(np.max(np.abs(o2[dark] / p2[dark] - 1.0))) if dark.any() else float("nan"),
        "added_light_error": float(np.max(np.abs((o2 - o1)[dark] - (p2 - p1)[dark]) / p2[dark])) if dark.any() else float("nan"),
    }
    return out
