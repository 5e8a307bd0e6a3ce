"""Synthetic lightstage captures standing in for the RHC data (paper Supp. "Details about the Dataset").

``gra-mi capture`` writes the layout of docs/data-format.md: the rig, the tracked subject, procedural envmaps,
interleaved uniformly lit and envmap-lit training frames (a different training envmap on each relit frame), test
sequences under held-out envmaps (one envmap per sequence), per-camera linear HDR images with their masks (alpha),
and the true material maps for evaluation.

Ground truth comes from one of two renderers:
- ``path`` (default): more than the one-bounce model can explain — three bounces, Mitsuba's ``principled`` BSDF
  with sheen on cloth, spatially varying albedo and roughness, and pose-dependent wrinkle normal maps. Rendered as
  direct light summed exactly over every LED that is on (one shadow ray per LED, the principled BSDF evaluated by
  Mitsuba) plus the interreflections of Mitsuba's ``path`` (``max_depth`` 4 minus 2 with the same samples, so the
  difference is exactly the bounces after the first), whose LED choice follows each LED's power (``sampling_weight``);
  see :class:`GroundTruthRenderer` and the noise it leaves, measured by :func:`measure_ground_truth_noise`;
- ``onebounce``: gra-mi's own one-bounce model from the true maps (for recovery tests: the fit must find them).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture, FrameLighting
from gra_mi.capture.truth import NOISE_REFERENCE_FACTOR, ground_truth_renderers, measure_ground_truth_noise
from gra_mi.capture.wrinkles import pose_capture_wrinkles, wrinkle_normal_map
from gra_mi.core.config import name_list, option
from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_write_text, write_exr, write_png
from gra_mi.core.limits import require_memory
from gra_mi.core.progress import progress
from gra_mi.core.provenance import claim_output
from gra_mi.core.shard import Shard
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.envmap import downsample_envmap, led_fidelity, load_envmap
from gra_mi.stage.envmap_library import write_envmap_set
from gra_mi.stage.framing import frame_subject
from gra_mi.stage.lightstage import default_lightstage, olat_pattern
from gra_mi.stage.scene import MAX_SPP, LightstageScene, subject_scene_xml, write_rig
from gra_mi.subject.anny_body import anny_sequence
from gra_mi.subject.sequence import WHOLE_FRAME_BYTES, load_sequence, save_sequence, tiny_subject

logger = logging.getLogger(__name__)


@dataclass(kw_only=True, frozen=True)
class CapturePreset:
    name: str
    subject: str  # "tiny" or "anny"
    train_clips: list[str]
    test_clips: list[str]  # one test sequence per clip, under held-out lighting
    frames_per_clip: int  # training clips: a uniformly lit frame, then relit_per_uniform frames each under its own envmap
    num_leds: int
    num_cameras: int
    eval_cameras: int  # the last cameras are held out for novel-view evaluation
    width: int
    height: int
    camera_distance: float
    uv_resolution: int
    envmap_height: int
    # Sample counts are powers of 4: the rig's low-discrepancy sampler (ldsampler) rounds anything else up.
    spp: int  # camera samples per pixel of the exact direct light (anti-aliasing, texture and highlight detail)
    indirect_spp: int  # path samples per pixel of the interreflections
    max_depth: int = 4  # path length: three bounces
    test_frames_per_clip: int | None = None  # default: frames_per_clip
    test_lighting: list[str] | None = None  # per test clip: "envmap" (held out) or "olat" (default: all envmaps)
    static_olat: bool = False  # a static pose lit as HumanOLAT lights one: white, 2 gradients, envmaps, every OLAT
    envmap_frames: int = 10  # static_olat: the environment-lit frames (the held-out lighting)
    relit_per_uniform: int = 1  # environment-lit training frames after each uniformly lit one (the paper: 1)
    # The environment-lit training frames' own sample counts (default: spp, indirect_spp): training data, whose
    # unbiased noise averages out over many frames, can be cheaper than the test frames that scores are measured on.
    relit_spp: int | None = None
    relit_indirect_spp: int | None = None
    # The held-out frames' own sample counts (default: spp, indirect_spp): the truth every score is measured against,
    # whose noise would otherwise cap each score and shrink each stage's measured gain.
    held_out_spp: int | None = None
    held_out_indirect_spp: int | None = None
    framed: bool = False  # each camera cropped to the subject's box over the whole sequence (stage/framing.py)
    framing_margin: float = 0.04  # of the image, per side, around that box

    def train_kinds(self) -> list[str]:
        """One training clip's lighting per frame: "uniform" or "envmap"."""
        return ["uniform" if k % (self.relit_per_uniform + 1) == 0 else "envmap" for k in range(self.frames_per_clip)]

    def test_lightings(self) -> list[str]:
        return self.test_lighting or ["envmap"] * len(self.test_clips)

    def test_frames(self) -> int:
        return self.test_frames_per_clip or self.frames_per_clip


PRESETS = {
    "tiny": CapturePreset(
        name="tiny", subject="tiny", train_clips=["tiny"], test_clips=["tiny"], frames_per_clip=6, num_leds=64,
        num_cameras=8, eval_cameras=1, width=320, height=240, camera_distance=1.2, uv_resolution=32, envmap_height=32,
        spp=4, indirect_spp=16,
    ),
    # The demo: 64 training envmaps (8 relit frames after each uniform one, at a quarter of the samples), cameras
    # framed on the subject, 216x312 portrait with a 2 % margin. Held out: a march, poses the walk never makes, one
    # leg always standing (a squat's deepest frames stood 164 pixels tall; a turn's arm span narrows the framing).
    # In a camera that looks down, the nearer foot projects lowest: when it is the raised one, the subject spans
    # 12 % fewer rows, so the frame is sized for the subject to stand >= 256 pixels tall on either foot.
    "small": CapturePreset(
        name="small", subject="anny", train_clips=["walk"], test_clips=["march"], frames_per_clip=72, relit_per_uniform=8,
        test_frames_per_clip=8, num_leds=331, num_cameras=8, eval_cameras=2, width=216, height=312, camera_distance=1.8,
        uv_resolution=256, envmap_height=64, spp=16, indirect_spp=64, relit_spp=4, relit_indirect_spp=16, framed=True,
        framing_margin=0.02,
    ),
    # 264 training envmaps over three motions; test: two held-out envmaps and one OLAT (out of distribution).
    "medium": CapturePreset(
        name="medium", subject="anny", train_clips=["walk", "arm_raise", "turn"], test_clips=["squat", "walk", "arm_raise"],
        frames_per_clip=99, relit_per_uniform=8, num_leds=331, num_cameras=8, eval_cameras=2, width=216, height=312,
        camera_distance=1.8, uv_resolution=256, envmap_height=64, spp=16, indirect_spp=64, relit_spp=4, relit_indirect_spp=16,
        test_frames_per_clip=17, test_lighting=["envmap", "envmap", "olat"], framed=True, framing_margin=0.02,
    ),
    # A static pose as HumanOLAT captures one (white, 2 gradients, 10 envmaps, 331 OLATs), cameras in portrait.
    "olat": CapturePreset(
        name="olat", subject="anny", train_clips=["walk"], test_clips=[], frames_per_clip=1, num_leds=331,
        num_cameras=8, eval_cameras=2, width=90, height=160, camera_distance=1.8, uv_resolution=256, envmap_height=64,
        spp=16, indirect_spp=16, static_olat=True,
    ),
    # The olat capture at a size `gra-mi demo --preset olat` renders in minutes (the sum of 331 OLATs averages the noise).
    # The held-out frames are the truth every score is measured against: their interreflections at 16 samples capped
    # the scores of a render that models them (a two-bounce render gained 0.5 dB more against an 8x truth), 256 cost
    # 0.4 s per view.
    "olat_quick": CapturePreset(
        name="olat_quick", subject="anny", train_clips=["walk"], test_clips=[], frames_per_clip=1, num_leds=331,
        num_cameras=8, eval_cameras=2, width=72, height=128, camera_distance=1.8, uv_resolution=128, envmap_height=32,
        spp=4, indirect_spp=4, static_olat=True, envmap_frames=4, held_out_spp=16, held_out_indirect_spp=256,
    ),
    # The paper's protocol: 40 cameras at 1024x540, interleaved full-on / relit frames (a GPU's work).
    "full": CapturePreset(
        name="full", subject="anny", train_clips=["walk", "arm_raise", "turn"], test_clips=["squat"], frames_per_clip=24,
        num_leds=331, num_cameras=40, eval_cameras=3, width=1024, height=540, camera_distance=1.8, uv_resolution=512,
        envmap_height=128, spp=64, indirect_spp=256, framed=True,
    ),
}  # fmt: skip

RENDERERS = ("path", "onebounce")
ONEBOUNCE_SPP = 16  # the one-bounce truth's default samples per pixel (anti-aliasing only: its lighting is exact)
ABLATABLE_EFFECTS = ("sheen", "wrinkles", "interreflection")  # what the one-bounce model does not explain

OLAT_KEY_DIRECTION = np.array([0.5, 0.6, 0.62])  # the test OLAT: a key light front-left and above the subject


# --------------------------------------------------------------------------------------------------------------
# Ground-truth material
# --------------------------------------------------------------------------------------------------------------


def _smooth_noise(points: np.ndarray, scale: float, seed: int) -> np.ndarray:
    """A smooth field in [0, 1] over 3D points: a few random plane waves with wavelengths of 0.25 … 1 × ``scale``.

    Defined on the surface (not in UV), so the maps are continuous across UV seams, like a real subject's.
    """
    rng = np.random.default_rng(seed)
    field = np.zeros(points.shape[0])
    for _ in range(4):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        wavelength = scale * rng.uniform(0.25, 1.0)
        field += np.sin(2 * math.pi * (points @ direction) / wavelength + rng.uniform(0, 2 * math.pi))
    return 0.5 + 0.5 * field / 4.0


def ground_truth_maps(atlas, vertex_colors: np.ndarray, rest_vertices: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """Spatially varying albedo, roughness and a cloth (sheen) mask as (R, R, C) UV textures.

    Albedo and roughness vary smoothly over the body's surface (``rest_vertices``: its first frame), with features
    of about a tenth to half of its height.
    """
    r = atlas.resolution
    base = atlas.bake_vertex_attribute(vertex_colors, fill=0.5)
    points = atlas.bake_vertex_attribute(np.asarray(rest_vertices, np.float64), fill=0.0).reshape(-1, 3)
    height = float(np.ptp(rest_vertices[:, 1])) or 1.0
    variation = _smooth_noise(points, 0.5 * height, seed).reshape(r, r)
    albedo = np.clip(base * (0.8 + 0.4 * variation)[..., None], 0.03, 0.95)
    roughness = np.clip(0.3 + 0.5 * _smooth_noise(points, 0.5 * height, seed + 1).reshape(r, r), 0.05, 1.0)[..., None]
    skin = (base[..., 0] > base[..., 2] + 0.1)[..., None]  # skin tones are redder than blue
    cloth = (~skin) & atlas.mask[..., None]
    return {"albedo": albedo.astype(np.float32), "roughness": roughness.astype(np.float32), "cloth": cloth.astype(np.float32)}


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


def _schedule(preset: CapturePreset, train_envmaps: list[str], test_sources: list[tuple[str, str]]) -> list[FrameLighting]:
    """Training: a uniformly lit frame (tracking), then ``relit_per_uniform`` frames each under the next training
    envmap, and so on. Test: one
    sequence per test clip under one held-out lighting, ``(kind, file)`` with kind "envmap" or "pattern"."""
    frames, t, relit = [], 0, 0
    for _ in preset.train_clips:
        for kind in preset.train_kinds():
            if kind == "uniform":
                frames.append(FrameLighting(t, "train", 0, "uniform", None))
            else:
                frames.append(FrameLighting(t, "train", 0, "envmap", train_envmaps[relit % len(train_envmaps)]))
                relit += 1
            t += 1
    for s, (kind, source) in enumerate(test_sources):
        for _ in range(preset.test_frames()):
            if kind == "envmap":
                frames.append(FrameLighting(t, "test", s, "envmap", source))
            else:
                frames.append(FrameLighting(t, "test", s, "pattern", None, pattern=source))
            t += 1
    return frames


def olat_firing_order(stage) -> np.ndarray:
    """The order a stage fires its OLATs in: bottom to top, each ring by azimuth (a z-spiral, as HumanOLAT's stage)."""
    d = stage.led_directions()
    return np.lexsort((np.arctan2(d[:, 0], d[:, 2]), np.round(d[:, 1], 1)))


HELD_OUT_OLAT_EVERY = 10  # a static OLAT capture holds out every 10th OLAT of the firing order (as the import does)


def _olat_schedule(preset: CapturePreset, stage, out: Path, user_envmaps: dict[str, np.ndarray]) -> list[FrameLighting]:
    """A static pose (mesh frame 0) lit as HumanOLAT lights one: frame 0 white (every LED at the stage maximum),
    1–2 gradients (bright above / below), then the environment-lit frames (held out: the test), then one OLAT per LED
    in firing order (training, with the white and gradient frames; every ``HELD_OUT_OLAT_EVERY``-th held out)."""
    up, top = stage.led_directions()[:, 1], stage.max_led_intensity
    drives = {"white": np.full(stage.num_leds, top), "gradient_up": top * 0.5 * (1 + up), "gradient_down": top * 0.5 * (1 - up)}
    frames = [FrameLighting(i, "train", 0, "pattern", None, _write_drive(out, n, d), pose=0) for i, (n, d) in enumerate(drives.items())]
    user = list(user_envmaps.items())[: preset.envmap_frames]
    paths = []
    for name, image in user:
        paths.append(f"envmaps/test/user_{name}.exr")
        write_exr(out / paths[-1], downsample_envmap(image, preset.envmap_height))
    remaining = preset.envmap_frames - len(user)
    if remaining > 0:
        paths += [str(p.relative_to(out)) for p in write_envmap_set(out / "envmaps", "test", remaining, preset.envmap_height)]
    frames += [FrameLighting(len(frames) + k, "test", 0, "envmap", path, pose=0) for k, path in enumerate(paths)]
    for k, led in enumerate(olat_firing_order(stage)):
        drive, split = olat_pattern(stage, int(led)), "test" if k % HELD_OUT_OLAT_EVERY == HELD_OUT_OLAT_EVERY - 1 else "train"
        pattern = _write_drive(out, f"olat_{led:03d}", drive)
        frames.append(FrameLighting(len(frames), split, int(split == "test"), "pattern", None, pattern, pose=0))
    return frames


def _write_drive(out: Path, name: str, drive: np.ndarray) -> str:
    path = out / "patterns" / f"{name}.json"
    if not path.is_file():
        atomic_write_text(path, json.dumps({"intensities": np.asarray(drive, float).tolist()}) + "\n")
    return str(path.relative_to(out))


def _write_test_olat(stage, out: Path) -> str:
    """The out-of-distribution test lighting: one LED (the one nearest a front-left key light) at the stage maximum."""

    direction = OLAT_KEY_DIRECTION / np.linalg.norm(OLAT_KEY_DIRECTION)
    led = int(np.argmax(stage.led_directions() @ direction))
    path = out / "patterns" / f"test_olat_{led:03d}.json"
    drive = olat_pattern(stage, led)
    atomic_write_text(path, json.dumps({"led": led, "intensities": drive.tolist()}) + "\n")
    return str(path.relative_to(out))


@dataclass(kw_only=True)
class CaptureConfig:
    """A synthetic capture (:func:`generate_capture`)."""

    preset: str = field(default="small", metadata=option(choices=tuple(sorted(PRESETS))))
    """tiny: CI, seconds; small: the demo (64 training envmaps, 8 cameras at 216x312 framed on the subject), minutes;
    medium: 264 training envmaps over three motions, OLAT test, about an hour on 2 cores; full: 40 cameras at
    1024x540, 512² UV (a GPU's work)."""
    renderer: str = field(default="path", metadata=option(choices=RENDERERS))
    """Ground truth: Mitsuba path tracing of a richer material (default), or gra-mi's one-bounce model (recovery tests)."""
    spp: int | None = None
    """Samples per pixel of the exact direct light (a power of 4). Default: the preset's (with --renderer onebounce,
    whose samples only anti-alias: 16). The environment-lit training frames of `small` and `medium` keep their own,
    lower counts (capture.json: relit_spp, relit_indirect_spp); the held-out frames of `olat_quick`, which every
    score is measured against, more (held_out_spp, held_out_indirect_spp)."""
    indirect_spp: int | None = None
    """Path samples per pixel of the interreflections (a power of 4). Default: the preset's."""
    without: list[str] = field(default_factory=list, metadata=option(parse=name_list))
    """Effects to leave out of the path-traced ground truth, comma-separated: sheen, wrinkles, interreflection.
    Fitting such captures shows what each effect costs the one-bounce fit (docs/results/fit.md)."""
    measure_noise: bool = True
    """Measure the ground truth's noise against 4x the samples on a few views (capture.json)."""
    training_lightings: int | None = None
    """Environment-lit training frames, each under its own map (default: the preset's). The training clips get as many
    frames as that takes, keeping the preset's relit frames per uniformly lit one."""
    framing_margin: float | None = None
    """A framed preset's margin around the subject's box, a fraction of the image per side in [0, 0.5) (default: the
    preset's)."""

    def validate(self) -> None:
        if self.preset not in PRESETS:
            raise GraMiParameterError("preset", f"unknown preset '{self.preset}', expected one of {sorted(PRESETS)}")
        if self.renderer not in RENDERERS:
            raise GraMiParameterError("renderer", f"expected 'path' or 'onebounce', got '{self.renderer}'")
        for name in ("spp", "indirect_spp"):
            value = getattr(self, name)
            if value is not None and (value < 1 or value > MAX_SPP or 4 ** round(math.log(value, 4)) != value):
                raise GraMiParameterError(
                    name, f"must be a power of 4 up to {MAX_SPP} (the low-discrepancy sampler's counts: 4, 16, 64, 256, ...), got {value}"
                )
        unknown = sorted(set(self.without) - set(ABLATABLE_EFFECTS))
        if unknown or (self.without and self.renderer != "path"):
            raise GraMiParameterError(
                "without",
                f"expected effects of the path-traced ground truth among {', '.join(ABLATABLE_EFFECTS)}, got {', '.join(self.without)}",
            )

        self._validate_framing(PRESETS[self.preset])

    def _validate_framing(self, preset: CapturePreset) -> None:
        if self.training_lightings is not None:
            if preset.static_olat:
                raise GraMiParameterError(
                    "training_lightings",
                    f"the {preset.name} preset lights one static pose by its OLATs; it has no environment-lit training frames",
                )
            if self.training_lightings < 1:
                raise GraMiParameterError("training_lightings", f"must be >= 1, got {self.training_lightings}")
            run = self.resolved()  # a synthetic capture's subject sequence is made whole in memory
            frames = run.frames_per_clip * len(run.train_clips) + run.test_frames() * len(run.test_clips)
            require_memory("training_lightings", frames * WHOLE_FRAME_BYTES[run.subject], f"a sequence of {frames:,} frames")
        if self.framing_margin is not None:
            if not preset.framed:
                raise GraMiParameterError("framing_margin", f"the {preset.name} preset's cameras are not framed on the subject")
            if not 0 <= self.framing_margin < 0.5:
                raise GraMiParameterError(
                    "framing_margin",
                    f"a fraction of the image per side in [0, 0.5) (0.5 leaves no room for the subject), got {self.framing_margin}",
                )

    def resolved(self) -> CapturePreset:
        """The preset with this run's sample counts, training lightings and framing margin."""
        preset = PRESETS[self.preset]
        preset = replace(preset, spp=self.spp or preset.spp, indirect_spp=self.indirect_spp or preset.indirect_spp)
        if self.framing_margin is not None:
            preset = replace(preset, framing_margin=self.framing_margin)
        if self.training_lightings is not None:  # whole cycles of one uniform frame and its relit ones, per clip
            per_clip = math.ceil(self.training_lightings / len(preset.train_clips))
            cycles = math.ceil(per_clip / preset.relit_per_uniform)
            preset = replace(preset, frames_per_clip=cycles * (preset.relit_per_uniform + 1))
        return preset

    def record(self) -> dict:
        """How the ground truth is rendered (renderer, sample counts, effects left out): part of the run's identity,
        since a resume with other counts would mix two estimators."""
        preset = self.resolved()
        if self.renderer == "onebounce":  # deterministic lighting, samples only anti-alias
            counts = {"spp": self.spp or ONEBOUNCE_SPP, "indirect_spp": 0, "max_depth": 2}
        elif "interreflection" in self.without:
            counts = {"spp": preset.spp, "indirect_spp": 0, "max_depth": 2}
        else:
            counts = {"spp": preset.spp, "indirect_spp": preset.indirect_spp, "max_depth": preset.max_depth}
        for kind in ("relit", "held_out") if self.renderer == "path" else ():
            spp, indirect = getattr(preset, f"{kind}_spp"), getattr(preset, f"{kind}_indirect_spp")
            if not (spp or indirect):
                continue
            spp, indirect = spp or counts["spp"], indirect or counts["indirect_spp"]
            if kind == "held_out":  # never noisier than the training frames (--spp, --indirect-spp)
                spp, indirect = max(spp, counts["spp"]), max(indirect, counts["indirect_spp"])
            counts[f"{kind}_spp"] = spp
            counts[f"{kind}_indirect_spp"] = indirect if counts["indirect_spp"] else 0  # --without interreflection
        chosen = {k: getattr(self, k) for k in ("training_lightings", "framing_margin") if getattr(self, k) is not None}
        return {"renderer": self.renderer, **counts, **({"without": sorted(self.without)} if self.without else {}), **chosen}


def generate_capture(
    out: str | Path,
    config: CaptureConfig | None = None,
    *,
    test_envmaps: dict[str, np.ndarray] | None = None,
    overwrite: bool = False,
    shard: Shard | None = None,
) -> Capture:
    """Write a synthetic capture; rerunning resumes (existing images are kept, and each image's samples depend only
    on its frame, so a resumed capture equals an uninterrupted one). ``test_envmaps`` (name → validated lat-long
    map): the user's own held-out lighting, in place of the first procedural test envmaps. ``overwrite``: empty a
    folder made by another run first (else it is refused). ``shard``: render only this shard's frames (the rig,
    subject, lighting and capture.json every shard writes alike; the ground truth's noise is measured by the shard
    that finds every image done)."""

    config = config or CaptureConfig()
    config.validate()
    preset, record, out = config.resolved(), config.record(), Path(out)
    ensure_mitsuba()
    envmap_ids = {
        name: hashlib.sha256(np.ascontiguousarray(env, np.float32).tobytes()).hexdigest()[:16] for name, env in (test_envmaps or {}).items()
    }
    claim_output(out, "capture", {}, {"preset": config.preset, **record, "test_envmaps": envmap_ids}, overwrite=overwrite, shard=shard)
    previous = Capture.load(out) if (out / "capture.json").is_file() else None  # a resume keeps what it measured

    _write_subject(preset, out)
    stage = _capture_rig(preset, out)
    write_rig(stage, out / "rig")
    if preset.static_olat:
        schedule = _olat_schedule(preset, stage, out, test_envmaps or {})
    else:
        schedule = _schedule(preset, *_write_lighting(preset, stage, out, test_envmaps or {}))
    atomic_write_text(out / "scene.xml", subject_scene_xml("rig", "subject"))
    maps = _write_true_maps(preset, out, config.without)
    capture = Capture(
        out,
        preset.name,
        config.renderer,
        preset.uv_resolution,
        [c.name for c in stage.cameras[: len(stage.cameras) - preset.eval_cameras]],
        [c.name for c in stage.cameras[len(stage.cameras) - preset.eval_cameras :]],
        schedule,
        ground_truth=dict(record),
    )
    _measure_fidelity(capture, stage, previous)
    _render_images(capture, stage, config, record, maps, shard or Shard())
    return capture


def _capture_rig(preset: CapturePreset, out: Path):
    """The preset's rig; a framed preset crops each camera to the box the subject's whole sequence covers in it."""
    stage = default_lightstage(
        num_leds=preset.num_leds,
        num_cameras=preset.num_cameras,
        camera_distance=preset.camera_distance,
        width=preset.width,
        height=preset.height,
    )
    if preset.framed:
        vertices = load_sequence(out / "subject").vertices
        stage.cameras = frame_subject(stage.cameras, vertices.reshape(-1, 3), preset.width, preset.height, preset.framing_margin)
    return stage


def _write_subject(preset: CapturePreset, out: Path) -> None:
    if (out / "subject" / "sequence.npz").is_file():
        return
    frames_per_clip = [preset.frames_per_clip] * len(preset.train_clips) + [preset.test_frames()] * len(preset.test_clips)
    if preset.subject == "tiny":
        seq = tiny_subject(sum(frames_per_clip))
    else:
        seq = anny_sequence(preset.train_clips + preset.test_clips, frames_per_clip)
    save_sequence(seq, out / "subject")


def _write_lighting(
    preset: CapturePreset, stage, out: Path, user_envmaps: dict[str, np.ndarray]
) -> tuple[list[str], list[tuple[str, str]]]:
    """The training envmaps, and each test clip's lighting: the user's maps first, then procedural ones, or the test
    OLAT. Also the scene file of the capture's rig and subject."""

    n_relit = len(preset.train_clips) * preset.train_kinds().count("envmap")
    train_env = [str(p.relative_to(out)) for p in write_envmap_set(out / "envmaps", "train", max(n_relit, 1), preset.envmap_height)]
    test_kinds = preset.test_lightings()
    n_test_env = sum(k == "envmap" for k in test_kinds)
    if len(user_envmaps) > n_test_env:
        raise GraMiParameterError(
            "test_envmap", f"the {preset.name} preset has {n_test_env} envmap-lit test sequence(s), got {len(user_envmaps)} maps"
        )
    user_paths = []
    for name, image in user_envmaps.items():
        user_paths.append(f"envmaps/test/user_{name}.exr")
        write_exr(out / user_paths[-1], downsample_envmap(image, preset.envmap_height))
        write_png((out / user_paths[-1]).with_suffix(".png"), image, exposure=None)
    remaining = n_test_env - len(user_envmaps)
    procedural = write_envmap_set(out / "envmaps", "test", remaining, preset.envmap_height) if remaining > 0 else []
    test_env = iter(user_paths + [str(p.relative_to(out)) for p in procedural])
    test_sources = [("envmap", next(test_env)) if k == "envmap" else ("pattern", _write_test_olat(stage, out)) for k in test_kinds]
    return train_env, test_sources


def _write_true_maps(preset: CapturePreset, out: Path, without: list[str]) -> dict[str, np.ndarray]:
    """The ground-truth material in UV space (gt/*.exr): albedo, roughness, sheen, the cloth regions, a flat normal map."""
    from gra_mi.render.atlas import UVAtlas

    ls = LightstageScene.load(out / "scene.xml")
    atlas = UVAtlas.build(ls.sequence.faces, ls.sequence.uvs, preset.uv_resolution)
    colors = ls.sequence.vertex_colors if ls.sequence.vertex_colors is not None else np.full((ls.sequence.num_vertices, 3), 0.5, np.float32)
    maps = ground_truth_maps(atlas, colors, ls.sequence.vertices[0])
    write_exr(out / "gt" / "albedo.exr", maps["albedo"])
    write_exr(out / "gt" / "roughness.exr", maps["roughness"])
    write_exr(out / "gt" / "sheen.exr", maps["cloth"] * (0.0 if "sheen" in without else 0.8))
    write_exr(out / "gt" / "cloth.exr", maps["cloth"])  # the material regions (reports score skin and cloth apart)
    write_png(out / "gt" / "albedo.png", maps["albedo"])
    write_exr(out / "gt" / "normal_map.exr", wrinkle_normal_map(maps["cloth"], 0.0))
    return maps


def _measure_fidelity(capture: Capture, stage, previous: Capture | None) -> None:
    """How well the LEDs reproduce each envmap (capture.json), kept from a previous run of the same capture."""

    if previous is not None:
        for key in ("noise", "envmap_fidelity"):
            if key in previous.ground_truth:
                capture.ground_truth[key] = previous.ground_truth[key]
    if "envmap_fidelity" not in capture.ground_truth:
        envmaps = sorted({f.envmap for f in capture.frames if f.envmap})
        capture.ground_truth["envmap_fidelity"] = {
            name: led_fidelity(load_envmap(capture.folder / name), stage)
            for name in progress(envmaps, description="envmap -> LED fidelity")
        }
    capture.save()


def _render_images(capture: Capture, stage, config: CaptureConfig, record: dict, maps: dict, shard: Shard) -> None:
    """Every camera of every frame of the shard, rendered in image space (the fit works in UV space, so the ground
    truth takes another code path); images already on disk are kept. Then, once every image exists, the noise of the
    estimate, once."""

    out, preset = capture.folder, config.resolved()
    bsdf = ONEBOUNCE_BSDF if config.renderer == "onebounce" else GT_BSDF
    atomic_write_text(out / "scene_gt.xml", subject_scene_xml("rig", "subject", spp=preset.spp, bsdf_xml=bsdf))
    renderer_for = ground_truth_renderers(record)
    source = LightstageScene.load(out / "scene_gt.xml")

    def pose(frame: int) -> None:
        if source.set_frame(frame):  # wrinkles follow the pose
            pose_capture_wrinkles(source.params, capture, frame)

    jobs = [(entry, cam) for entry in shard.take(capture.frames) for cam in stage.cameras]
    lit = None  # the frame whose lighting is set: jobs run frame-major, so each frame's envmap is mapped once
    for entry, cam in progress(jobs, description=f"capture ({config.renderer})"):
        path = capture.image_path(cam.name, entry.frame)
        if path.is_file():
            continue
        pose(entry.mesh_frame)
        if lit != entry.frame:
            source.set_led_intensities(capture.lighting(stage, entry))
            lit = entry.frame
        write_exr(path, renderer_for(entry).render(source.scene, source.sensor_index(cam.name), seed=entry.frame))
    complete = all(capture.image_path(cam.name, entry.frame).is_file() for entry in capture.frames for cam in stage.cameras)
    if complete and config.measure_noise and config.renderer == "path" and "noise" not in capture.ground_truth:
        logger.info("measuring the ground truth's noise against %dx the samples", NOISE_REFERENCE_FACTOR)
        capture.ground_truth["noise"] = measure_ground_truth_noise(capture, source, renderer_for, stage.cameras[0].name, pose)
        capture.save()
