"""Batch relighting (``gra-mi relight``): frames × lights × cameras through one stage, written as EXR, PNG and MP4.

Lights are envmaps (mapped onto the LEDs), OLATs, LED patterns, a near-field point light and light paths (point and
spot lights that move, several at once: :mod:`gra_mi.render.light_path`), all in one run. The
stage is the one-bounce microfacet render or RelightNet on top of it (:func:`gra_mi.relightnet.infer.render_view`).
Jobs run frame-major, so each frame's visibility is traced once per lighting model (near, far) and reused by every
light and camera.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.core.color import display_exposure
from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import path_component
from gra_mi.core.io import atomic_path, atomic_write_text, write_exr, write_mp4_srgb8, write_png
from gra_mi.core.progress import progress
from gra_mi.core.runtime import torch_device
from gra_mi.core.shard import Shard, record_shard_count
from gra_mi.render.atlas import MIN_RESOLUTION
from gra_mi.render.composite import PlatformCompositor
from gra_mi.render.light_path import LightPath
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.transport import LightTransport
from gra_mi.stage.envmap import background_plate, envmap_to_leds, led_fidelity
from gra_mi.stage.lighting_checks import lighting_warnings
from gra_mi.stage.lightstage import olat_pattern, validate_pattern
from gra_mi.stage.scene import LightstageScene, composite_over

logger = logging.getLogger(__name__)

STAGES = ("microfacet", "relightnet")
LIGHTING_MODELS = ("auto", "far", "near")


@dataclass(kw_only=True)
class RelightConfig:
    stage: str = field(default="microfacet", metadata=option(choices=STAGES))
    """microfacet: the one-bounce render; relightnet: passed through a trained RelightNet (needs --relightnet)."""
    uv_resolution: int = 512
    """UV texture resolution when no albedo texture is given (the paper's)."""
    lighting_model: str = field(default="auto", metadata=option(choices=LIGHTING_MODELS))
    """How the LEDs light the subject. far: as an environment at infinity (directions and irradiance from the stage
    centre): what relighting under an HDRI means. near: as the stage's point LEDs where they are: how a capture was
    lit. auto: far for envmaps, near for OLATs and LED patterns (docs/accuracy.md, lighting models)."""
    save_uv: bool = False
    """Also write the UV-space radiance and the RelightNet inputs (normal, position, view direction, mask) as EXR."""
    background: bool = False
    """Composite envmap renders over the camera's background plate in the PNG/MP4 previews."""
    composite: bool = False
    """Composite envmap renders over the background plate on a platform with the subject's shadow (a Mitsuba
    path-traced layer under the same envmap, gra_mi.render.composite) in the PNG/MP4 previews."""
    exposure: float | None = None
    """Preview exposure (default: automatic per light and camera)."""
    fidelity: bool = False
    """Also measure how well the LEDs reproduce each envmap's irradiance at the stage centre (envmap_fidelity.json:
    error over 256 normals next to the NNLS optimum; about 9 s per map on 2 cores with 331 LEDs)."""
    transport: LightTransport = field(default_factory=LightTransport)

    def validate(self) -> None:
        self.transport.validate(fixed=True)
        if self.stage not in STAGES:
            raise GraMiParameterError("stage", f"expected one of {STAGES}, got '{self.stage}'")
        if self.lighting_model not in LIGHTING_MODELS:
            raise GraMiParameterError("lighting_model", f"expected one of {', '.join(LIGHTING_MODELS)}, got '{self.lighting_model}'")
        if self.uv_resolution < MIN_RESOLUTION:
            raise GraMiParameterError("uv_resolution", f"must be >= {MIN_RESOLUTION}, got {self.uv_resolution}")
        if self.exposure is not None and not (np.isfinite(self.exposure) and self.exposure > 0):
            raise GraMiParameterError("exposure", f"must be a positive number, got {self.exposure}")


@dataclass
class SubjectMaps:
    """What the subject is rendered with: its material maps (None: the vertex colours baked to UV, roughness 0.5), a
    trained RelightNet for ``stage="relightnet"``, and a folder to keep per-frame visibility in across runs."""

    albedo: np.ndarray | None = None
    roughness: np.ndarray | None = None
    relightnet: Path | None = None
    vis_cache: Path | None = None


@dataclass
class Light:
    """One lighting of the batch: LED radiant intensities (L, 3) and what the previews need."""

    intensities: np.ndarray
    envmap: np.ndarray | None = None  # for the background plate
    plate_scale: float = 1.0  # the envmap → LED mapping's normalisation, which the background plate takes too
    path: LightPath | None = None  # near-field lights (a still point light or a light path), lit with every LED off

    def far_field(self, lighting_model: str) -> bool:
        """Whether this light is rendered far field under ``lighting_model`` (auto: envmaps are, stage lightings not)."""
        return self.envmap is not None if lighting_model == "auto" else lighting_model == "far"


@dataclass
class RelightSummary:
    renders: int
    out: Path
    visibility_traced: int  # frames whose visibility was traced
    visibility_reused: int
    done_before: int = 0  # views a resumed run found written


def collect_lights(
    stage,
    envmaps: list[tuple[Path, np.ndarray]] | dict[str, np.ndarray],
    olats: list[int],
    patterns: list[tuple[Path, np.ndarray]] | dict[str, np.ndarray],
    point_light=None,
    paths: list | None = None,
):
    """Name → :class:`Light` for every lighting asked for (patterns are LED drive values, emitted = drive × gain;
    ``paths``: :class:`LightPath` objects, named by their file). Envmaps and patterns come as (file, array) pairs, or
    as a dict name → array from library callers. A lighting's name is its output folder: envmaps and
    patterns are named by their file's stem, OLATs ``olatNNN``; two lightings with one name, of one kind or of two, are
    refused naming both (one would overwrite the other's images)."""

    lights: dict[str, Light] = {}
    origins: dict[str, str] = {}

    def add(name: str, origin: str, light: Light) -> None:
        path_component(name, origin, "lighting name")
        if name in lights:
            raise GraMiParameterError(
                "lights", f"{origins[name]} and {origin} are both named '{name}' and would write one output folder: rename one"
            )
        lights[name], origins[name] = light, origin

    if point_light is not None:
        add("point_light", "--point-light", Light(np.zeros((stage.num_leds, 3)), path=LightPath.still(point_light)))
    for path in paths or []:
        add(path.name, str(path.source), Light(np.zeros((stage.num_leds, 3)), path=path))
    for file, env in envmaps.items() if isinstance(envmaps, dict) else envmaps:
        lighting = envmap_to_leds(env, stage)
        add(Path(file).stem, str(file), Light(lighting.radiant_intensity(stage), envmap=env, plate_scale=lighting.scale))
    for k in olats:
        add(f"olat{k:03d}", f"--olat {k}", Light(olat_pattern(stage, k) * stage.gains))
    for file, drive in patterns.items() if isinstance(patterns, dict) else patterns:
        name = Path(file).stem
        add(name, str(file), Light(validate_pattern(stage, drive, source=name) * stage.gains))
    if not lights:
        raise GraMiParameterError("lights", "give at least one envmap, OLAT, pattern or point light")
    return lights


def _write_conditioning(folder: Path, frame: int, stage, scene, near_lights) -> None:
    """The paper's envmap conditioning for near-field lights at one frame (what RelightNet sees in their place):
    ``folder/conditioning/frame_NNNN.{exr,png}`` and the LED pattern as ``_leds.npy``."""
    from gra_mi.render.point_light import conditioning_envmap, conditioning_of

    pattern = conditioning_of(stage, scene, near_lights)
    envmap = conditioning_envmap(stage, pattern)
    stem = folder / "conditioning" / f"frame_{frame:04d}"
    write_exr(stem.with_suffix(".exr"), envmap)
    write_png(stem.with_suffix(".png"), envmap, exposure=None)
    with atomic_path(stem.with_name(stem.name + "_leds.npy")) as tmp, open(tmp, "wb") as fh:
        np.save(fh, pattern)


def relight_batch(
    scene: str | Path | LightstageScene,
    out: str | Path,
    lights: dict[str, Light],
    *,
    frames: list[int] | None = None,
    cameras: list[str] | None = None,
    config: RelightConfig | None = None,
    maps: SubjectMaps | None = None,
    platform=None,
    shard: Shard | None = None,
    resume: bool = False,
) -> RelightSummary:
    """Render every (frame, light, camera) of ``scene`` (a path or a loaded scene) (+ ``envmap_fidelity.json`` if asked)
    into ``out/LIGHT/CAMERA/frame_NNNN.{exr,png}`` (+ ``CAMERA.mp4``).

    ``frames``/``cameras`` None: all frames, camera 0. ``platform``: the :class:`gra_mi.render.composite.PlatformConfig`
    of ``config.composite``. ``shard``: render only its frames; the files are those one process writes (previews
    exposed from the selection's first frame, videos written by the shard that finds every frame done). ``resume``: a
    view whose preview (its last file) is on disk is not rendered again; the caller has checked that the folder holds
    this same run (``gra-mi relight`` claims it: :func:`gra_mi.core.provenance.claim_output`). Everything is checked
    before the first file is written.
    """
    from gra_mi.relightnet.infer import render_view

    config = config or RelightConfig()
    config.validate()
    ensure_mitsuba()
    out, shard = Path(out), shard or Shard()
    ls = scene if isinstance(scene, LightstageScene) else LightstageScene.load(scene)
    frames = list(range(ls.sequence.num_frames)) if frames is None else frames
    for f in frames:
        if not 0 <= f < ls.sequence.num_frames:
            raise GraMiParameterError("frames", f"frame {f} out of range [0, {ls.sequence.num_frames})")
    cams = list({cam.name: cam for cam in (ls.stage.camera(c) for c in (cameras or [0]))}.values())  # 'cam00,0': once
    model, relighter = _stage_model(ls, config, maps or SubjectMaps())
    if model is None and not config.save_uv:  # RelightNet and --save-uv use the whole UV texture: trace every texel
        relighter.only_for([cam.name for cam in cams])
    for light in lights.values():
        if light.path is not None:
            light.path.check_frames(frames)
            light.path.check_clear_of(ls.sequence.vertices, frames)
    record_shard_count(out, shard)
    if config.fidelity:
        _write_fidelity(out, lights, ls.stage)

    def view_of(frame: int, name: str, cam):
        light = lights[name]
        near = light.path.at(frame) if light.path is not None else None
        return render_view(relighter, model, frame, cam.name, light.intensities, near, light.far_field(config.lighting_model)), near

    previews = _Previews(out, config, ls, keep=len(lights) * len(cams), platform=platform)
    every = [(f, name, cam) for f in shard.take(frames) for name in lights for cam in cams]  # frame-major: one trace per frame
    jobs = [job for job in every if not (resume and previews.done(*job))]
    for name in lights:
        for cam in cams:
            first = next((f for f, n, c in jobs if n == name and c is cam), frames[0])
            if first != frames[0] and config.exposure is None:  # a shard or a resume that does not render the first frame
                previews.exposure_from(name, cam, view_of(frames[0], name, cam)[0])
    for frame, name, cam in progress(jobs, description="relight" if shard.whole else f"relight (shard {shard})"):
        view, near = view_of(frame, name, cam)
        if cam is cams[0]:  # said and written once per frame and lighting, not per camera
            light = lights[name]
            for warning in lighting_warnings(ls, light.intensities, near, light.far_field(config.lighting_model)):
                logger.warning("%s: %s", name, warning)
            if near:
                _write_conditioning(out / name, frame, ls.stage, ls.scene, near)
        if config.save_uv:
            _write_uv(out / name / cam.name, frame, relighter, view)
        previews.add(frame, name, cam, lights[name], view)  # the PNG last: a view is done when its PNG is there
    if len(frames) > 1:
        previews.write_videos(frames, lights, cams, ls.sequence.fps)
    return RelightSummary(len(jobs), out, relighter.cache.misses, relighter.cache.hits, len(every) - len(jobs))


def _stage_model(ls, config: RelightConfig, maps: SubjectMaps):
    """(RelightNet or None, the relighter at its resolution) for ``config.stage``, checked against the maps."""
    from gra_mi.render.relighter import Relighter

    model, resolution = None, config.uv_resolution
    if config.stage == "relightnet":
        if maps.relightnet is None:
            raise GraMiParameterError("relightnet", "the relightnet stage needs the folder of a trained RelightNet")
        from gra_mi.relightnet.model import RelightNet, check_input_transport

        model = RelightNet.load(maps.relightnet, torch_device())
        check_input_transport(model.config, config.transport, maps.relightnet)
        if maps.albedo is not None and maps.albedo.shape[0] != model.config.resolution:
            raise GraMiInputError("albedo", f"RelightNet runs at {model.config.resolution}², the albedo is {maps.albedo.shape[0]}²")
        resolution = model.config.resolution
    relighter = Relighter(ls, resolution, maps.albedo, maps.roughness, cache_dir=maps.vis_cache, transport=config.transport)
    relighter.cache.keep = 4  # the jobs are frame-major: a frame's entries (near, far field) are done before the next
    return model, relighter


def _write_fidelity(out: Path, lights: dict[str, Light], stage) -> None:
    """How well the LEDs stand in for each envmap (irradiance error over 256 normals, next to the NNLS optimum):
    logged and written to ``envmap_fidelity.json``. Asked for only: it costs several times a relight."""

    fidelity = {name: led_fidelity(light.envmap, stage) for name, light in lights.items() if light.envmap is not None}
    for name, f in fidelity.items():
        logger.info(
            "%s on the LEDs: irradiance error mean %.2f %%, max %.2f %% over %d normals",
            name, 100 * f["mean_rel_error"], 100 * f["max_rel_error"], f["normals"],
        )  # fmt: skip
    if fidelity:
        atomic_write_text(out / "envmap_fidelity.json", json.dumps(fidelity, indent=1) + "\n")


def _write_uv(folder: Path, frame: int, relighter, view) -> None:
    """``--save-uv``: the UV-space radiance and RelightNet's per-texel inputs of one view, as EXR."""
    write_exr(folder / f"uv_radiance_{frame:04d}.exr", relighter.atlas.scatter(view.shading.radiance))
    for channel, texture in relighter.texel_inputs(view).items():
        write_exr(folder / f"uv_{channel}_{frame:04d}.exr", texture)


class _Previews:
    """Each view as EXR (linear) and PNG (one exposure per light and camera, over the background plate or a platform
    if asked), and the MP4 of each light and camera at the end."""

    def __init__(self, out: Path, config: RelightConfig, ls, keep: int, platform=None):
        self.out, self.config = out, config
        self.exposures: dict[tuple[str, str], float] = {}
        self.compositor = None
        if config.composite:
            self.compositor = PlatformCompositor(ls.sequence, platform, keep=keep)

    def add(self, frame: int, name: str, cam, light: Light, view) -> None:

        folder = self.out / name / cam.name
        write_exr(folder / f"frame_{frame:04d}.exr", view.image)
        shown = view.image[..., :3]
        if self.compositor is not None and light.envmap is not None:
            shown = self.compositor(view.image, frame, cam, light.envmap, light.plate_scale, name)
        elif self.config.background and light.envmap is not None:
            shown = composite_over(view.image, background_plate(light.envmap, cam) * light.plate_scale)
        self.exposure_from(name, cam, view)
        write_png(folder / f"frame_{frame:04d}.png", shown, exposure=self.exposures[(name, cam.name)])

    def done(self, frame: int, name: str, cam) -> bool:
        """Whether a view's files are written: its PNG is, the last of them (each file is written whole or not at all)."""
        return (self.out / name / cam.name / f"frame_{frame:04d}.png").is_file()

    def exposure_from(self, name: str, cam, view) -> None:
        """Set a light and camera's preview exposure from a view of the selection's first frame (a shard that does
        not render that frame renders its view for this): the same exposure whichever frames a process renders."""
        if (name, cam.name) not in self.exposures:
            self.exposures[(name, cam.name)] = self.config.exposure if self.config.exposure is not None else display_exposure(view.image)

    def write_videos(self, frames: list[int], names, cams, fps: float) -> int:
        """Each light and camera's MP4, from the PNG previews on disk, once every frame's exists (the shard that finds
        the others done writes them; one process writes them at its end). Returns how many were written."""
        import imageio.v3 as iio

        written = 0
        for name in names:
            for cam in cams:
                pngs = [self.out / name / cam.name / f"frame_{f:04d}.png" for f in frames]
                if all(p.is_file() for p in pngs):
                    written += write_mp4_srgb8(self.out / name / f"{cam.name}.mp4", (iio.imread(p) for p in pngs), fps=fps)
        return written


def select(text: str, count: int, parameter: str, integers: bool = False) -> list:
    """``--frames``/``--cameras``: 'all', 'A:B' (B excluded) or a comma list; an empty selection (``5:2``, ``,``) is an
    error, not a run that writes nothing."""
    if text == "all":
        items = [str(i) for i in range(count)]
    elif ":" in text:
        a, b = text.split(":", 1)
        try:
            items = [str(i) for i in range(int(a or 0), int(b) if b else count)]
        except ValueError:
            raise GraMiParameterError(parameter, f"expected A:B with integers, got '{text}'") from None
    else:
        items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise GraMiParameterError(parameter, f"'{text}' selects nothing (of {count})")
    if integers:
        try:
            return [int(t) for t in items]
        except ValueError:
            raise GraMiParameterError(parameter, f"expected integers, 'A:B' or 'all', got '{text}'") from None
    return items
