"""Synthetic lightstage captures standing in for the RHC data (paper Supp. "Details about the Dataset").

``gra-mi capture`` writes the layout of docs/data-format.md: the rig, the tracked subject, procedural envmaps,
interleaved uniformly lit and envmap-lit training frames (a different training envmap on each relit frame), test
sequences under held-out envmaps (one envmap per sequence), per-camera linear HDR images with their masks (alpha),
and the true material maps for evaluation.

Ground truth comes from one of two renderers:
- ``path`` (default): Mitsuba's ``path`` integrator with more than the one-bounce model can explain — three
  bounces, Mitsuba's ``principled`` BSDF with sheen on cloth, spatially varying albedo and roughness, and
  pose-dependent wrinkle normal maps;
- ``onebounce``: gra-mi's own one-bounce model from the true maps (for recovery tests: the fit must find them).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture, FrameLighting
from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_write_text, write_exr, write_png

logger = logging.getLogger(__name__)


@dataclass
class CapturePreset:
    name: str
    subject: str  # "tiny" or "anny"
    train_clips: list[str]
    test_clips: list[str]  # one test sequence per clip, each under its own held-out envmap
    frames_per_clip: int
    num_leds: int
    num_cameras: int
    eval_cameras: int  # the last cameras are held out for novel-view evaluation
    width: int
    height: int
    camera_distance: float
    uv_resolution: int
    envmap_height: int
    spp: int  # path tracer samples per pixel
    max_depth: int = 4  # path length: three bounces


PRESETS = {
    "tiny": CapturePreset("tiny", "tiny", ["tiny"], ["tiny"], 6, 64, 8, 1, 320, 240, 1.2, 32, 32, 128),
    "small": CapturePreset("small", "anny", ["walk"], ["squat"], 8, 331, 8, 2, 256, 135, 1.8, 256, 64, 32),
    "full": CapturePreset("full", "anny", ["walk", "arm_raise", "turn"], ["squat"], 24, 331, 40, 3, 1024, 540, 1.8, 512, 128, 256),
}


# --------------------------------------------------------------------------------------------------------------
# Ground-truth material
# --------------------------------------------------------------------------------------------------------------


def _smooth_noise(resolution: int, seed: int) -> np.ndarray:
    """A smooth field in [0, 1] over UV: a few random low-frequency waves."""
    rng = np.random.default_rng(seed)
    c = (np.arange(resolution) + 0.5) / resolution
    u, v = np.meshgrid(c, c, indexing="xy")
    field = np.zeros_like(u)
    for _ in range(4):
        fu, fv = rng.uniform(1.0, 4.0, 2)
        phase = rng.uniform(0, 2 * math.pi)
        field += np.sin(2 * math.pi * (fu * u + fv * v) + phase)
    return 0.5 + 0.5 * field / 4.0


def ground_truth_maps(atlas, vertex_colors: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """Spatially varying albedo, roughness and a cloth (sheen) mask as (R, R, C) UV textures."""
    r = atlas.resolution
    base = atlas.bake_vertex_attribute(vertex_colors, fill=0.5)
    albedo = np.clip(base * (0.8 + 0.4 * _smooth_noise(r, seed))[..., None], 0.03, 0.95)
    roughness = np.clip(0.3 + 0.5 * _smooth_noise(r, seed + 1), 0.05, 1.0)[..., None]
    skin = (base[..., 0] > base[..., 2] + 0.1)[..., None]  # skin tones are redder than blue
    cloth = (~skin) & atlas.mask[..., None]
    return {"albedo": albedo.astype(np.float32), "roughness": roughness.astype(np.float32), "cloth": cloth.astype(np.float32)}


def wrinkle_normal_map(cloth: np.ndarray, amplitude: float, seed: int = 0) -> np.ndarray:
    """A tangent-space normal map (values in [0, 1]) of wrinkle bands on cloth, of the given slope amplitude."""
    r = cloth.shape[0]
    rng = np.random.default_rng(seed)
    c = (np.arange(r) + 0.5) / r
    u, v = np.meshgrid(c, c, indexing="xy")
    angle, freq = rng.uniform(0, math.pi), 24.0
    phase = 2 * math.pi * freq * (u * math.cos(angle) + v * math.sin(angle))
    slope = amplitude * np.cos(phase) * cloth[..., 0]
    n = np.stack([-slope * math.cos(angle), -slope * math.sin(angle), np.ones_like(slope)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return (0.5 + 0.5 * n).astype(np.float32)


def wrinkle_amplitude(frame: int, num_frames: int) -> float:
    """Pose-dependent: wrinkles deepen and relax with the motion's phase."""
    return 0.1 + 0.5 * abs(math.sin(2 * math.pi * frame / max(num_frames, 1)))


ONEBOUNCE_BSDF = """<bsdf type="gra_microfacet" id="gt_material">
            <texture type="bitmap" name="albedo"><string name="filename" value="gt/albedo.exr"/></texture>
            <texture type="bitmap" name="roughness"><string name="filename" value="gt/roughness.exr"/><boolean name="raw" value="true"/></texture>
        </bsdf>"""

GT_BSDF = """<bsdf type="normalmap" id="gt_material">
            <texture type="bitmap" name="normalmap"><string name="filename" value="gt/normal_map.exr"/><boolean name="raw" value="true"/></texture>
            <bsdf type="principled">
                <texture type="bitmap" name="base_color"><string name="filename" value="gt/albedo.exr"/></texture>
                <texture type="bitmap" name="roughness"><string name="filename" value="gt/roughness.exr"/><boolean name="raw" value="true"/></texture>
                <texture type="bitmap" name="sheen"><string name="filename" value="gt/sheen.exr"/><boolean name="raw" value="true"/></texture>
                <float name="specular" value="0.5"/>
            </bsdf>
        </bsdf>"""


def _schedule(preset: CapturePreset, train_envmaps: list[str], test_envmaps: list[str]) -> list[FrameLighting]:
    frames, t, relit = [], 0, 0
    for _ in preset.train_clips:
        for k in range(preset.frames_per_clip):
            if k % 2 == 0:
                frames.append(FrameLighting(t, "train", 0, "uniform", None))
            else:
                frames.append(FrameLighting(t, "train", 0, "envmap", train_envmaps[relit % len(train_envmaps)]))
                relit += 1
            t += 1
    for s, _ in enumerate(preset.test_clips):
        for _ in range(preset.frames_per_clip):
            frames.append(FrameLighting(t, "test", s, "envmap", test_envmaps[s % len(test_envmaps)]))
            t += 1
    return frames


def generate_capture(out: str | Path, preset_name: str = "small", renderer: str = "path") -> Capture:
    """Write a synthetic capture; rerunning resumes (existing images are kept)."""
    from gra_mi.core.progress import progress
    from gra_mi.core.runtime import ensure_mitsuba
    from gra_mi.render.atlas import UVAtlas
    from gra_mi.stage.envmap_library import write_envmap_set
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, subject_scene_xml, write_rig
    from gra_mi.subject.sequence import save_sequence, tiny_subject

    if preset_name not in PRESETS:
        raise GraMiParameterError("preset", f"unknown preset '{preset_name}', expected one of {sorted(PRESETS)}")
    if renderer not in ("path", "onebounce"):
        raise GraMiParameterError("renderer", f"expected 'path' or 'onebounce', got '{renderer}'")
    preset = PRESETS[preset_name]
    out = Path(out)
    ensure_mitsuba()

    # 1. Rig, subject, envmaps ---------------------------------------------------------------------------
    stage = default_lightstage(
        preset.num_leds, num_cameras=preset.num_cameras, camera_distance=preset.camera_distance, width=preset.width, height=preset.height
    )
    write_rig(stage, out / "rig")
    if not (out / "subject" / "sequence.npz").is_file():
        if preset.subject == "tiny":
            seq = tiny_subject(preset.frames_per_clip * (len(preset.train_clips) + len(preset.test_clips)))
        else:
            from gra_mi.subject.anny_body import anny_sequence

            seq = anny_sequence(preset.train_clips + preset.test_clips, preset.frames_per_clip)
        save_sequence(seq, out / "subject")
    n_relit = len(preset.train_clips) * (preset.frames_per_clip // 2)
    train_env = [str(p.relative_to(out)) for p in write_envmap_set(out / "envmaps", "train", max(n_relit, 1), preset.envmap_height)]
    test_env = [str(p.relative_to(out)) for p in write_envmap_set(out / "envmaps", "test", len(preset.test_clips), preset.envmap_height)]
    atomic_write_text(out / "scene.xml", subject_scene_xml("rig", "subject"))

    # 2. Ground-truth material ---------------------------------------------------------------------------
    ls = LightstageScene.load(out / "scene.xml")
    atlas = UVAtlas.build(ls.sequence.faces, ls.sequence.uvs, preset.uv_resolution)
    colors = ls.sequence.vertex_colors if ls.sequence.vertex_colors is not None else np.full((ls.sequence.num_vertices, 3), 0.5, np.float32)
    maps = ground_truth_maps(atlas, colors)
    write_exr(out / "gt" / "albedo.exr", maps["albedo"])
    write_exr(out / "gt" / "roughness.exr", maps["roughness"])
    write_exr(out / "gt" / "sheen.exr", maps["cloth"] * 0.8)
    write_png(out / "gt" / "albedo.png", maps["albedo"])
    write_exr(out / "gt" / "normal_map.exr", wrinkle_normal_map(maps["cloth"], 0.0))

    capture = Capture(
        out,
        preset.name,
        renderer,
        preset.uv_resolution,
        [c.name for c in stage.cameras[: len(stage.cameras) - preset.eval_cameras]],
        [c.name for c in stage.cameras[len(stage.cameras) - preset.eval_cameras :]],
        _schedule(preset, train_env, test_env),
    )
    capture.save()

    # 3. Render (image space: the fit works in UV space, so the ground truth takes another code path) ------
    import mitsuba as mi

    if renderer == "onebounce":
        atomic_write_text(out / "scene_gt.xml", subject_scene_xml("rig", "subject", spp=preset.spp, bsdf_xml=ONEBOUNCE_BSDF))
        integrator = mi.load_dict({"type": "gra_onebounce"})
        spp = 16  # deterministic lighting: samples only anti-alias
    else:
        atomic_write_text(out / "scene_gt.xml", subject_scene_xml("rig", "subject", spp=preset.spp, bsdf_xml=GT_BSDF))
        integrator = mi.load_dict({"type": "path", "max_depth": preset.max_depth})
        spp = preset.spp
    source = LightstageScene.load(out / "scene_gt.xml")
    normal_key = next((k for k in source.params.keys() if k.endswith("normalmap.data")), None)
    jobs = [(entry, cam) for entry in capture.frames for cam in stage.cameras]
    for entry, cam in progress(jobs, description=f"capture ({renderer})"):
        path = capture.image_path(cam.name, entry.frame)
        if path.is_file():
            continue
        if source.set_frame(entry.frame):
            if normal_key is not None:  # wrinkles follow the pose
                amplitude = wrinkle_amplitude(entry.frame, ls.sequence.num_frames)
                source.params[normal_key] = mi.TensorXf(wrinkle_normal_map(maps["cloth"], amplitude))
                source.params.update()
        source.set_led_intensities(capture.lighting(stage, entry))
        sensor = source.sensor_index(cam.name)
        image = np.array(mi.render(source.scene, sensor=sensor, integrator=integrator, spp=spp, seed=entry.frame), dtype=np.float32)
        write_exr(path, image)
    return capture
