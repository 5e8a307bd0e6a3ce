"""Commands on the physics-based texture: ``fit``, ``edit-texture``, ``export``, ``relight``, ``relight-field``,
``eval-lighting``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from gra_mi.apps.field_relight import FieldRelightConfig, relight_from_field
from gra_mi.apps.relight import RelightConfig, SubjectMaps, collect_lights, relight_batch, select
from gra_mi.apps.texture_edit import edit_albedo_file, parse_color
from gra_mi.capture.dataset import Capture
from gra_mi.cli.options import CommandConfig, Restartable
from gra_mi.core.config import option, options_need_switch
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.shard import ShardOptions
from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy
from gra_mi.fit.materials import FitConfig
from gra_mi.render.composite import PLATFORM_FLAGS, PlatformConfig
from gra_mi.stage.envmap import EnvmapOptions
from gra_mi.stage.lightstage import load_calibration, load_pattern
from gra_mi.stage.scene import LightstageScene
from gra_mi.subject.interchange import GLTF_SUFFIXES, USD_SUFFIXES
from gra_mi.subject.sequence import check_frames, load_sequence


@dataclass(kw_only=True)
class FitCommand(Restartable):
    capture: Path = field(metadata=option(positional=True))
    """Capture folder (from `gra-mi capture` or converted real data)."""
    out: Path = Path("outputs/fit")
    """Output folder; holds a checkpoint, so rerunning resumes."""
    fit: FitConfig = field(default_factory=FitConfig)


def run_fit(c: FitCommand) -> None:
    from gra_mi.fit.materials import run_fit as fit

    _, report = fit(c.capture, c.out, c.fit, c.overwrite)
    if report is not None:  # under torchrun, rank 0 writes the report; the others have said nothing
        print(f"done: open {report}")


@dataclass(kw_only=True)
class EditTextureCommand(CommandConfig):
    albedo: Path
    """Albedo UV texture to edit (square RGB EXR, e.g. from `gra-mi fit`)."""
    image: Path | None = None
    """Edit layer (PNG in sRGB, or EXR in linear), RGB or RGBA: alpha says where it applies."""
    mask: Path | None = None
    """UV mask (PNG or EXR, single channel in [0,1]) for --color."""
    color: str | None = None
    """Linear RGB albedo r,g,b in [0,1] painted where --mask is set."""
    opacity: float = 1.0
    """Strength of the edit in [0, 1]."""
    out: Path = field(metadata=option(writes=(".exr",)))
    """Edited albedo EXR to write (a PNG preview is written beside it)."""

    def validate(self) -> None:
        super().validate()
        if self.image is None and (self.mask is None or self.color is None):
            raise GraMiInputError("edit-texture", "give --image, or --mask with --color")


def run_edit_texture(c: EditTextureCommand) -> None:

    color = parse_color(c.color) if c.color is not None else None
    edit_albedo_file(c.albedo, c.out, c.image, c.mask, color, c.opacity)
    print(f"wrote {c.out}; re-render with: gra-mi relight SCENE --albedo {c.out} ...")


@dataclass(kw_only=True)
class ExportCommand(CommandConfig):
    out: Path = field(metadata=option(writes=USD_SUFFIXES + GLTF_SUFFIXES))
    """The file to write; its suffix picks the format: .usdz (one package), .usda / .usdc (textures in a folder
    NAME_textures beside it) or .glb. Each is checked by its format's validator after writing."""
    subject: Path
    """Tracked mesh sequence folder (e.g. CAPTURE/subject), or an avatar exported before (.usd*, .glb)."""
    albedo: Path
    """Albedo UV texture (EXR), e.g. from `gra-mi fit`."""
    roughness: Path
    """Roughness UV texture (EXR), e.g. from `gra-mi fit`."""
    frames: str = "all"
    """Frames to export, as `relight --frames` takes them: 'all', 'A:B' (B excluded; ':N' the first N) or a comma
    list; they become the animation's time 0, 1, … (USD's gra_mi:sourceFrame and glTF's extras name the sequence's
    frame at each). Only these frames are read from a mapped sequence; the export holds them in memory."""
    rig: Path | None = None
    """A rig calibration (calibration.json, or a capture or rig folder holding one) whose cameras are written (USD
    Cameras; glTF perspective cameras, which cannot hold a principal point off the image's centre: said when so), and
    whose LEDs --pattern lights."""
    set_scene: Path | None = field(default=None, metadata=option(flag="--set", metavar="SCENE"))
    """A lightstage scene (scene.xml, or the folder holding it, e.g. from `gra-mi from-scene`) whose set (its shapes
    besides the subject: a floor, walls, props) is written beside the avatar: static meshes in world space, each with
    a preview of its BSDF (base colour, roughness, metallic; said per shape), in both formats."""
    lights: Path | None = field(default=None, metadata=option(metavar="PATH.json"))
    """A light path JSON (as `relight --lights` takes: point and spot lights at keyframes; docs/data-format.md) whose
    lights are written sampled at every exported frame: USD SphereLights (a spot with a cone), glTF point and spot
    lights whose nodes move (a .glb cannot animate a light's intensity or cone, nor hold its radius: said)."""
    envmap: Path | None = None
    """USD only: an environment map to hand over as a DomeLight (lat-long, read like `relight --envmap`)."""
    pattern: Path | None = None
    """LED drive values (JSON or .npy, as `relight --pattern`); the LEDs that are on become USD SphereLights or glTF
    point lights (KHR_lights_punctual, in candela). Needs --rig."""
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)

    def validate(self) -> None:
        super().validate()
        if self.frames.strip().isdigit():  # an export's --frames N once meant the first N frames: say so, never guess
            n = int(self.frames)
            raise GraMiParameterError("frames", f"'{n}' is ambiguous: ':{n}' exports the first {n} frames, '{n}:{n + 1}' frame {n} alone")
        if self.pattern is not None and self.rig is None:
            raise GraMiParameterError("pattern", "needs --rig (the LEDs the pattern drives)")

    def output_paths(self) -> dict[str, Path]:
        """What the export writes besides --out: an unpackaged layer's textures."""
        from gra_mi.apps.usd import textures_beside

        return {"--out's textures": textures_beside(self.out)} if self.out.suffix.lower() in (".usda", ".usdc", ".usd") else {}


def _rig_calibration(path: Path):
    for candidate in (path, path / "calibration.json", path / "rig" / "calibration.json"):
        if candidate.is_file():
            return load_calibration(candidate)
    raise GraMiInputError(path, "no calibration.json here (give the file, a rig folder or a capture folder)")


def run_export(c: ExportCommand) -> int:
    from gra_mi.apps.export import export_avatar
    from gra_mi.apps.export_lights import light_tracks
    from gra_mi.apps.set_export import read_set
    from gra_mi.render.light_path import LightPath
    from gra_mi.render.relighter import load_texture

    albedo, roughness = load_texture(c.albedo, 3, "albedo"), load_texture(c.roughness, 1, "roughness")
    rig = _rig_calibration(c.rig) if c.rig is not None else None
    envmap = c.envmaps.load(c.envmap) if c.envmap is not None else None
    leds = load_pattern(rig, c.pattern) * rig.gains if c.pattern is not None else None  # emitted = drive × gain (W/sr)
    seq = load_sequence(c.subject, every_frame=False)  # the frames exported are checked, not every frame
    frames = select(c.frames, seq.num_frames, "frames", integers=True)
    check_frames(seq, [f for f in frames if 0 <= f < seq.num_frames])
    set_parts, set_notes = read_set(c.set_scene) if c.set_scene is not None else (None, [])
    tracks = light_tracks(LightPath.load(c.lights), frames) if c.lights is not None else None
    report = export_avatar(c.out, seq, albedo, roughness, frames, rig, envmap, leds, set_parts, tracks)
    print(f"wrote {report.summary()}")
    for line in set_notes:
        print(f"  set: {line}")
    for line in report.errors + report.warnings:
        print(f"  {line}")
    if leds is not None and c.out.suffix.lower() != ".glb":
        from gra_mi.apps.usd import LED_RADIUS_M

        print(f"  in Blender, import with light_intensity_scale = {4 * math.pi * LED_RADIUS_M**2:.5f}: its USD importer "
              "ignores a SphereLight's radius (docs/export.md)")  # fmt: skip
    return 1 if report.errors else 0


@dataclass(kw_only=True)
class RelightCommand(Restartable):
    scene: Path = field(metadata=option(positional=True))
    """Lightstage scene XML (e.g. scenes/tiny_lightstage.xml)."""
    frames: str = "all"
    """Frames: 'all', 'A:B' (B excluded) or a comma list."""
    cameras: str = "0"
    """Cameras: 'all' or a comma list of indices or names."""
    envmap: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """Lat-long HDR map (OpenEXR or Radiance .hdr) mapped onto the LEDs (repeatable)."""
    olat: list[int] = field(default_factory=list, metadata=option(repeat=True))
    """Light one LED (index) at the stage maximum (repeatable)."""
    pattern: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """LED drive values, JSON or .npy (repeatable; see docs/data-format.md)."""
    point_light: str | None = field(default=None, metadata=option(metavar="X,Y,Z"))
    """A near-field point light at X,Y,Z metres (LEDs off); also writes its envmap conditioning."""
    point_light_intensity: float = 2.0
    """Radiant intensity of the point light in W/sr."""
    point_light_radius: float = 0.03
    """Radius of the point light's sphere in metres (soft shadows)."""
    lights: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """A light path JSON: point and spot lights that move, several at once, given at keyframes (LEDs off; format in
    docs/data-format.md). Renders a video per camera and the envmap conditioning of every frame (repeatable)."""
    relightnet: Path | None = None
    """Folder with relightnet.safetensors + relightnet.json (from `gra-mi train-relightnet`)."""
    albedo: Path | None = None
    """Albedo UV texture (square RGB EXR in [0,1]). Default: the subject's vertex colours baked to UV."""
    roughness: Path | None = None
    """Roughness UV texture (square single-channel EXR in [0,1]). Default: 0.5 everywhere."""
    vis_cache: Path | None = None
    """Folder to keep per-frame visibility in (reused across runs). Default: memory only."""
    relight: RelightConfig = field(default_factory=RelightConfig)
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)
    platform: PlatformConfig = field(default_factory=PlatformConfig, metadata=option(renames=PLATFORM_FLAGS))
    shards: ShardOptions = field(default_factory=ShardOptions)
    out: Path = Path("outputs/relight")
    """Output folder. Rerunning the same relight into it resumes: views already written are not rendered again."""

    def validate(self) -> None:
        if not (self.envmap or self.olat or self.pattern or self.point_light or self.lights):
            raise GraMiInputError("lighting", "give at least one --envmap, --olat, --pattern, --point-light or --lights")
        super().validate()
        options_need_switch(self.platform, self.relight.composite, "--composite")


def relit_frames(frames: list[int], count: int, stage: str) -> list[int]:
    """The subject's frames a relight reads: those it relights and, for RelightNet, the frames before each (its
    normals of the last few frames)."""
    from gra_mi.render.bridge import NUM_NORMAL_FRAMES

    back = NUM_NORMAL_FRAMES if stage == "relightnet" else 1
    return sorted({max(f - k, 0) for f in frames if 0 <= f < count for k in range(back)})


def run_relight(c: RelightCommand) -> None:
    from gra_mi.render.light_path import LightPath
    from gra_mi.render.point_light import parse_point_light
    from gra_mi.render.relighter import load_texture

    point_light = parse_point_light(c.point_light, c.point_light_intensity, c.point_light_radius) if c.point_light else None
    paths = [LightPath.load(p) for p in c.lights]
    envmaps = [(p, c.envmaps.load(p)) for p in c.envmap]
    maps = SubjectMaps(
        albedo=load_texture(c.albedo, 3, "albedo") if c.albedo else None,
        roughness=load_texture(c.roughness, 1, "roughness") if c.roughness else None,
        relightnet=c.relightnet,
        vis_cache=c.vis_cache,
    )
    ls = LightstageScene.load(c.scene, every_frame=False)  # the frames relit are checked, not every frame of the subject
    patterns = [(p, load_pattern(ls.stage, p)) for p in c.pattern]
    lights = collect_lights(ls.stage, envmaps, c.olat, patterns, point_light, paths)
    frames = select(c.frames, ls.sequence.num_frames, "frames", integers=True)
    check_frames(ls.sequence, relit_frames(frames, ls.sequence.num_frames, c.relight.stage))
    cameras = select(c.cameras, len(ls.stage.cameras), "cameras")
    shard = c.shards.resolved()
    claim_relight(c, shard)
    summary = relight_batch(
        ls, c.out, lights, frames=frames, cameras=cameras, config=c.relight, maps=maps, platform=c.platform, shard=shard, resume=True
    )
    resumed = f"; {summary.done_before} found written by the run it resumed" if summary.done_before else ""
    print(
        f"wrote {summary.renders} renders to {summary.out}{resumed} (visibility traced {summary.visibility_traced} time(s), "
        f"once per frame and lighting model; reused {summary.visibility_reused} times)"
    )


def claim_relight(c: RelightCommand, shard) -> None:
    """Record what makes ``c.out`` (core/provenance.py): its inputs' content and the options that change a view. The
    same relight again resumes, with more cameras too (each camera's previews have their own exposure); another
    (other maps, lights, frames or options) is refused unless ``--overwrite``."""
    from dataclasses import asdict

    from gra_mi.core.guard import scene_references
    from gra_mi.core.provenance import claim_output

    inputs = {"scene": c.scene, **{f"scene's {ref.name}": ref for ref in scene_references(c.scene)}}
    inputs |= {"albedo": c.albedo, "roughness": c.roughness, "relightnet": c.relightnet}
    inputs |= {"envmaps": list(c.envmap), "patterns": list(c.pattern), "lights": list(c.lights)}
    paths = {"scene", "envmap", "pattern", "lights", "relightnet", "albedo", "roughness", "vis_cache", "out", "shards", "overwrite"}
    config = {key: value for key, value in asdict(c).items() if key not in paths}
    claim_output(c.out, "relight", inputs, config, overwrite=c.overwrite, free=("cameras",), shard=shard)


@dataclass(kw_only=True)
class RelightFieldCommand(CommandConfig):
    capture: Path = field(metadata=option(positional=True))
    """Capture folder with OLAT frames (a pattern lighting one LED): `gra-mi capture --preset olat` or an import."""
    cameras: str = "all"
    """Cameras: 'all' or a comma list of names or indices (the capture's training cameras, then its held-out ones). A
    camera that lacks an OLAT image takes that LED's light from its 3 nearest LEDs' OLATs where it is at most 2 % of
    every lighting's; where it is more, the camera is named and left out ('all') or refused (named)."""
    envmap: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """Lat-long HDR map (OpenEXR or Radiance .hdr) mapped onto the LEDs (repeatable)."""
    olat: list[int] = field(default_factory=list, metadata=option(repeat=True))
    """Light one LED (index) at the stage maximum (repeatable)."""
    pattern: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """LED drive values, JSON or .npy (repeatable; see docs/data-format.md)."""
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)
    field_relight: FieldRelightConfig = field(default_factory=FieldRelightConfig)
    out: Path = Path("outputs/relight_field")
    """Output folder: LIGHT/CAMERA.exr (linear RGBA) and .png, summary.json."""

    def validate(self) -> None:
        if not (self.envmap or self.olat or self.pattern):
            raise GraMiInputError("lighting", "give at least one --envmap, --olat or --pattern")
        super().validate()


def run_relight_field(c: RelightFieldCommand) -> None:
    capture = Capture.load(c.capture)
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    envmaps = [(p, c.envmaps.load(p)) for p in c.envmap]
    lights = collect_lights(stage, envmaps, c.olat, [(p, load_pattern(stage, p)) for p in c.pattern])
    names = capture.train_cameras + capture.eval_cameras
    cameras = [names[int(x)] if x.isdigit() and x not in names else x for x in select(c.cameras, len(names), "cameras")]
    if unknown := [x for x in cameras if x not in names]:
        raise GraMiParameterError("cameras", f"{', '.join(unknown)}: not cameras of {capture.folder} ({', '.join(names)})")
    lights = {name: light.intensities for name, light in lights.items()}
    summary = relight_from_field(capture, c.out, lights, cameras, c.field_relight, skip_incomplete=c.cameras == "all")
    cost = ", ".join(f"{cam} {s['ms_per_lighting']:.1f} ms ({s['held']})" for cam, s in summary["cameras"].items())
    print(
        f"wrote {len(lights)} lightings x {len(summary['cameras'])} cameras from {summary['olats']} OLATs to {c.out}; per lighting: {cost}"
    )
    for cam, why in summary["skipped"].items():
        print(f"left out camera {cam}: {why}")


@dataclass(kw_only=True)
class EvalLightingCommand(CommandConfig):
    capture: Path = field(metadata=option(positional=True))
    """Capture folder made by `gra-mi capture` (its scene_gt.xml holds the true materials)."""
    fit: Path
    """Fit folder (albedo.exr, roughness.exr from `gra-mi fit`)."""
    relightnet: Path | None = None
    """A trained RelightNet folder: also score RelightNet on the far-field render."""
    accuracy: EnvmapAccuracyConfig = field(default_factory=EnvmapAccuracyConfig)
    shards: ShardOptions = field(default_factory=ShardOptions)
    out: Path = Path("outputs/lighting")
    """Output folder."""


def run_eval_lighting(c: EvalLightingCommand) -> None:

    shard = c.shards.resolved()
    if not envmap_accuracy(c.capture, c.fit, c.out, c.relightnet, c.accuracy, shard=shard):
        print(f"shard {shard}: truths written to {c.out / 'truth'}; the shard that finishes last scores every map")
        return
    print((c.out / "accuracy.md").read_text())
    print(f"done: open {c.out / 'accuracy.md'}")
