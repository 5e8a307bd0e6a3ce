"""Commands that build the stage and its data: ``rig``, ``envmaps``, ``subject``, ``scene``, ``from-scene``, ``render``,
``capture``, ``import``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from gra_mi.capture.colmap import ColmapOptions, import_colmap, write_colmap_rig
from gra_mi.capture.easymocap import EasymocapOptions, import_easymocap
from gra_mi.capture.humanolat import HumanolatOptions, import_humanolat, write_humanolat
from gra_mi.capture.mitsuba_capture import MitsubaOptions, import_mitsuba
from gra_mi.capture.scene_stage import frame_values, stage_from_scene, write_scene_stage
from gra_mi.capture.source import ImportConfig
from gra_mi.capture.synthetic import PRESETS, CaptureConfig, generate_capture
from gra_mi.capture.transforms import TransformsOptions, import_transforms
from gra_mi.cli.options import CommandConfig, Restartable
from gra_mi.core.config import changed_options, comma_list, option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.guard import names_of, scene_references
from gra_mi.core.limits import require_memory
from gra_mi.core.provenance import claim_output
from gra_mi.core.shard import ShardOptions
from gra_mi.render.scene_file import is_lightstage_scene, parse_defines, render_scene_file
from gra_mi.stage.envmap import EnvmapOptions
from gra_mi.stage.envmap_library import BAKE_BYTES_PER_PIXEL, write_envmap_set
from gra_mi.stage.lightstage import RigLayout, load_calibration, load_pattern, olat_pattern
from gra_mi.stage.scene import RenderConfig, render_to_folder, write_rig, write_scene_file
from gra_mi.subject.anny_body import MOTION_CLIPS, anny_frames
from gra_mi.subject.sequence import WHOLE_FRAME_BYTES, SequenceLayout, tiny_subject, write_sequence

RIG_OPTIONS = ("num_leds", "radius", "num_cameras", "camera_distance", "width", "height", "max_led_intensity")


@dataclass(kw_only=True)
class RigCommand(CommandConfig):
    out: Path
    """Folder to write the rig into."""
    from_calibration: Path | None = None
    """Make the XML from an existing calibration JSON instead of the default layout."""
    layout: RigLayout = field(default_factory=RigLayout, metadata=option(fields=RIG_OPTIONS))

    def validate(self) -> None:
        super().validate()
        if self.from_calibration is not None and (given := changed_options(self.layout, RIG_OPTIONS)):
            raise GraMiParameterError(given[0], "lays out the default rig: --from-calibration takes the rig as its calibration has it")


def run_rig(c: RigCommand) -> None:

    stage = load_calibration(c.from_calibration) if c.from_calibration else c.layout.build()
    folder = write_rig(stage, c.out)
    print(f"wrote rig with {stage.num_leds} LEDs and {len(stage.cameras)} cameras to {folder}")


@dataclass(kw_only=True)
class EnvmapsCommand(CommandConfig):
    out: Path
    """Folder; maps go to OUT/train and OUT/test."""
    train: int = 16
    """Number of training envmaps."""
    test: int = 4
    """Number of held-out test envmaps (disjoint seeds)."""
    height: int = 128
    """Lat-long height in pixels (width = 2x)."""

    def validate(self) -> None:
        super().validate()
        for split in ("train", "test"):
            if getattr(self, split) < 0:
                raise GraMiParameterError(split, "must be >= 0")
        if self.height < 4:
            raise GraMiParameterError("height", f"must be >= 4 (lat-long rows), got {self.height}")
        require_memory("height", BAKE_BYTES_PER_PIXEL * 2 * self.height**2, f"a {2 * self.height}x{self.height} map")


def run_envmaps(c: EnvmapsCommand) -> None:

    for split, count in (("train", c.train), ("test", c.test)):
        paths = write_envmap_set(c.out, split, count, c.height)
        print(f"{split}: {len(paths)} envmaps in {c.out / split}")


def _clips(text: str) -> list[str]:
    import argparse

    clips = comma_list(text)
    unknown = [name for name in clips if name not in MOTION_CLIPS]
    if unknown or not clips:
        raise argparse.ArgumentTypeError(f"unknown clip(s) {unknown}; choose from {sorted(MOTION_CLIPS)}")
    return clips


@dataclass(kw_only=True)
class SubjectCommand(CommandConfig):
    out: Path
    """Folder to write the sequence into."""
    kind: str = field(default="anny", metadata=option(choices=("anny", "tiny")))
    """anny: the MakeHuman-based body; tiny: a ~450-triangle procedural subject for tests."""
    clips: list[str] = field(default_factory=lambda: ["walk", "arm_raise", "turn", "squat"], metadata=option(parse=_clips))
    """Comma-separated motion clips for anny (walk, arm_raise, turn, squat, march), played in order."""
    frames_per_clip: int | None = None
    """Frames per clip loop (default: each clip's own, 24-48)."""
    frames: int = 8
    """Frames for --kind tiny."""

    def validate(self) -> None:
        super().validate()
        require_positive({"frames": self.frames})
        if self.frames_per_clip is not None:
            require_positive({"frames_per_clip": self.frames_per_clip})
        ignored = changed_options(self, ("clips", "frames_per_clip") if self.kind == "tiny" else ("frames",))
        if ignored:
            raise GraMiParameterError(ignored[0], f"is not an option of --kind {self.kind} (see `gra-mi subject --help`)")
        if self.kind == "tiny":  # held in memory whole, then written
            require_memory("frames", self.frames * WHOLE_FRAME_BYTES["tiny"], f"{self.frames:,} frames of the tiny subject")


def run_subject(c: SubjectCommand) -> None:

    if c.kind == "tiny":
        seq = tiny_subject(c.frames)
        layout, frames = SequenceLayout.of(seq), zip(seq.vertices, seq.normals, strict=True)
    else:  # posed and written a frame at a time: any number of frames
        layout, frames = anny_frames(c.clips, c.frames_per_clip)
    write_sequence(c.out, layout, frames, source=c.kind)
    print(f"wrote {layout.num_frames} frames, {len(layout.uvs)} vertices, {len(layout.faces)} triangles to {c.out}")


@dataclass(kw_only=True)
class SceneCommand(CommandConfig):
    out: Path = field(metadata=option(writes=(".xml",)))
    """Scene XML file to write."""
    rig: Path
    """Rig folder (from `gra-mi rig`)."""
    subject: Path
    """Sequence folder (from `gra-mi subject`)."""
    spp: int = 64
    """Samples per pixel the written scene renders with (its `spp` parameter; `-D spp=N` changes it at render time)."""


def run_scene(c: SceneCommand) -> None:

    print(f"wrote {write_scene_file(c.out, c.rig, c.subject, c.spp)}")


@dataclass(kw_only=True)
class FromSceneCommand(Restartable):
    scene: Path = field(metadata=option(positional=True))
    """Your Mitsuba 3 scene: perspective sensors (the cameras), point emitters (the LEDs: their intensities become
    lighting.json), a mesh with texture coordinates (the shape id="subject", or the only shape); its other shapes (a floor,
    props) become the stage's set, with their own BSDFs, which shadows the subject, hides it and (with --bounces 2)
    reflects light onto it."""
    define: list[str] = field(default_factory=list, metadata=option(flag="-D", repeat=True, metavar="NAME=VALUE"))
    """Set a parameter the scene declares or uses, as Mitsuba's own tool takes it (repeatable)."""
    out: Path
    """Folder to write: scene.xml, rig/, subject/, lighting.json, albedo.exr and roughness.exr (where the subject's
    material holds them), set/ (the set's meshes and its BSDFs' textures), notes.md (what was kept and left out)."""
    spp: int = 64
    """Samples per pixel the written scene renders with (its `spp` parameter; `-D spp=N` changes it at render time)."""
    frames: str | None = None
    """A moving subject: load the scene once per value of --frame-parameter, 'A:B' (B excluded; zero-padded as the
    parameter's default is, <default name="frame" value="0000"/> gives 0000, 0001, ...) or a comma list of values as
    the scene takes them. The sensors, LEDs and the mesh's triangles and UVs must stay the same. Default: the scene as
    it is, one frame."""
    frame_parameter: str = "frame"
    """The scene parameter that selects the subject's frame (e.g. in <string name="filename" value="body_$frame.ply"/>)."""
    fps: float = 24.0
    """Frames per second of the subject's motion (relight's videos play at it)."""

    def validate(self) -> None:
        super().validate()
        parse_defines(self.define)
        require_positive({"spp": self.spp, "fps": self.fps})
        if self.frames is None and (given := changed_options(self, ("frame_parameter", "fps"))):
            raise GraMiParameterError(given[0], "takes effect with --frames only: add --frames, or leave it out")
        if self.frames is not None and self.frame_parameter in parse_defines(self.define):
            raise GraMiParameterError("define", f"sets {self.frame_parameter}, which --frames sets per frame: leave one out")


def run_from_scene(c: FromSceneCommand) -> None:
    frames = frame_values(c.frames, c.scene, c.frame_parameter) if c.frames is not None else None
    # the first frame is read (and refused) before the folder is claimed; the later ones as they are written
    stage = stage_from_scene(c.scene, parse_defines(c.define), frames, c.frame_parameter, c.fps)
    inputs = {"scene": c.scene} | {f"scene's {ref.name} ({ref})": ref for ref in scene_references(c.scene)}
    said = {"define": sorted(c.define), "spp": c.spp, "frames": c.frames, "frame_parameter": c.frame_parameter, "fps": c.fps}
    claim_output(c.out, "from-scene", inputs, said, overwrite=c.overwrite, restart=True)
    write_scene_stage(stage, c.out, c.spp)
    for note in stage.notes:
        print(f"note: {note}")
    maps = "".join(f" --{name} {c.out / (name + '.exr')}" for name in stage.maps)
    lighting = f"--pattern {c.out / 'lighting.json'}" if stage.intensities.max() > 0 else "--olat 0"
    print(f"wrote {c.out / 'scene.xml'}: {len(stage.stage.cameras)} cameras, {stage.stage.num_leds} LEDs, "
          f"{stage.sequence.num_vertices} vertices, {stage.num_frames} frame(s). Relight it with:\n  gra-mi relight {c.out / 'scene.xml'} {lighting}{maps}")  # fmt: skip


@dataclass(kw_only=True)
class RenderCommand(CommandConfig):
    scene: Path = field(metadata=option(positional=True))
    """Any Mitsuba 3 scene file, or a gra-mi lightstage scene (e.g. scenes/tiny_lightstage.xml: its LEDs are lit by
    --envmap, --olat or --pattern)."""
    envmap: Path | None = None
    """Lightstage scenes: a lat-long HDR map (OpenEXR or Radiance .hdr) mapped onto the LEDs (one of --envmap, --olat,
    --pattern)."""
    olat: int | None = None
    """Lightstage scenes: light one LED (index) at the stage maximum."""
    pattern: Path | None = None
    """Lightstage scenes: LED drive values, JSON {"intensities": [[r,g,b],...]} or .npy of shape (L,) or (L,3)."""
    sensor: list[str] = field(default_factory=list, metadata=option(repeat=True))
    """A plain scene's sensor to render, by id or index (repeatable). Default: every sensor. (Lightstage scenes: --camera.)"""
    define: list[str] = field(default_factory=list, metadata=option(flag="-D", repeat=True, metavar="NAME=VALUE"))
    """Set a parameter the scene declares (<default name=... value=.../>) or uses ($name), as Mitsuba's own tool
    takes it (repeatable: -D spp=16 -D radius=0.3)."""
    render: RenderConfig = field(default_factory=RenderConfig)
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)
    out: Path = Path("outputs/render")
    """Output folder."""

    def validate(self) -> None:
        given = [name for name in ("envmap", "olat", "pattern") if getattr(self, name) is not None]
        if len(given) > 1:
            raise GraMiInputError("lighting", f"give at most one of --envmap, --olat or --pattern (got {len(given)})")
        parse_defines(self.define)
        from gra_mi.render.scene_lights import checked_option

        for name, value in self.render.onebounce_options.items():
            checked_option(name, value, flag=name.replace("_", "-"))
        super().validate()


def run_render(c: RenderCommand) -> None:
    if not is_lightstage_scene(c.scene):
        _render_plain_scene(c)
        return
    if c.sensor or c.define or c.render.onebounce_options:
        raise GraMiInputError(
            c.scene, "a lightstage scene takes --camera, --frame and --spp, not --sensor, -D or gra_onebounce's sample "
            "counts (--dome-lights, --area-samples, --bsdf-samples: its LEDs carry an --envmap)"
        )  # fmt: skip
    if c.envmap is not None:
        light, envmap, drive = c.envmap.stem, c.envmaps.load(c.envmap), None
    elif c.olat is not None:
        light, envmap, drive = f"olat{c.olat:03d}", None, lambda stage: olat_pattern(stage, c.olat)
    elif c.pattern is not None:
        light, envmap, drive = c.pattern.stem, None, lambda stage: load_pattern(stage, c.pattern)
    else:
        raise GraMiInputError(c.scene, "a lightstage scene's LEDs start switched off: give --envmap, --olat or --pattern")
    stem = render_to_folder(scene_path=c.scene, out=c.out, light_name=light, config=c.render, envmap=envmap, drive=drive)
    print(f"wrote {stem}.exr")


def _render_plain_scene(c: RenderCommand) -> None:
    """A scene gra-mi did not write: rendered as it is, one EXR + PNG per sensor."""
    lightstage_only = [flag for flag, value in (("--envmap", c.envmap), ("--olat", c.olat), ("--pattern", c.pattern)) if value is not None]
    if lightstage_only or c.render.frame != 0 or c.render.camera != "0" or c.render.background:
        flag = lightstage_only[0] if lightstage_only else "--frame, --camera or --background"
        raise GraMiInputError(
            c.scene, f"{flag} needs a gra-mi lightstage scene (<default name=\"subject\"> and <default name=\"calibration\">, "
            "LED emitters led_NNN; `gra-mi scene` writes one); this scene is rendered with its own lights: drop it"
        )  # fmt: skip
    renders = render_scene_file(
        c.scene, c.out, sensors=c.sensor, integrator=c.render.integrator, spp=c.render.spp, seed=c.render.seed,
        defines=parse_defines(c.define), options=c.render.onebounce_options,
    )  # fmt: skip
    for r in renders:
        print(f"wrote {r.path} ({r.image.shape[1]}x{r.image.shape[0]})")


@dataclass(kw_only=True)
class CaptureCommand(Restartable):
    out: Path
    """Capture folder (layout: docs/data-format.md). Rerunning resumes."""
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    test_envmap: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """Your own HDR map (OpenEXR or .hdr) as held-out test lighting, in place of a procedural one (repeatable)."""
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)
    shards: ShardOptions = field(default_factory=ShardOptions)
    layout: str = field(default="gra-mi", metadata=option(choices=("gra-mi", "humanolat", "colmap")))
    """Also write the capture as a source gra-mi imports, to try that route end to end. humanolat: as HumanOLAT ships a
    pose (OUT/humanolat/SUBJECT_S001: AVIF images, cameras.calib, LED positions, firing order, the mesh in millimetres
    in a Z-up frame), for `gra-mi import humanolat`; needs --preset olat (a static pose). colmap: as a rig calibrated
    with COLMAP (OUT/colmap: sparse/0 in a reconstruction's frame and scale, places.txt, images/<cam>/ EXR, mask/,
    meshes/, leds.pc, lighting.json), for `gra-mi import colmap … --align-cameras OUT/colmap/places.txt`
    (docs/guides/your-capture.md). Written by a run over every shard (rerun without --shard once they are done)."""

    def validate(self) -> None:
        super().validate()
        if self.layout == "humanolat" and not PRESETS[self.capture.preset].static_olat:
            raise GraMiParameterError("layout", f"the HumanOLAT layout holds a static pose: use --preset olat, not {self.capture.preset}")
        names_of(self.test_envmap, "test_envmap")  # the capture stores them by name
        if self.layout != "gra-mi" and not self.shards.resolved().whole:  # a shard holds only its frames' images
            raise GraMiParameterError("layout", "is written from the whole capture: rerun without --shard once every shard is done")


def run_capture(c: CaptureCommand) -> None:

    test_envmaps = {path.stem: c.envmaps.load(path) for path in c.test_envmap}
    shard = c.shards.resolved()
    capture = generate_capture(c.out, c.capture, test_envmaps=test_envmaps, overwrite=c.overwrite, shard=shard)
    frames = shard.take(capture.frames)
    n = len(frames) * (len(capture.train_cameras) + len(capture.eval_cameras))
    print(f"wrote {n} images of {len(frames)} frames to {c.out}" + ("" if shard.whole else f" (shard {shard})"))
    if c.layout == "humanolat":
        print(f"wrote the HumanOLAT layout to {write_humanolat(capture, c.out / 'humanolat')}")
    elif c.layout == "colmap":
        print(f"wrote the COLMAP rig to {write_colmap_rig(capture, c.out / 'colmap')}; import it with --align-cameras places.txt")


@dataclass(kw_only=True)
class ImportCommand(Restartable):
    source: str = field(metadata=option(positional=True, choices=("humanolat", "transforms", "easymocap", "colmap", "mitsuba")))
    """The source's layout. humanolat: a subject folder of the HumanOLAT dataset (TMT22/HumanOLAT), one pose.
    transforms: a folder with a NeRF / nerfstudio transforms.json (or transforms_train/_test.json) and --mesh.
    easymocap: a calibrated rig (intri.yml, extri.yml, images/<cam>/) with --mesh, --leds and --lighting.
    colmap: a rig calibrated with COLMAP (sparse/0/cameras and images, .bin or .txt; images/<cam>/, the model's
    image names' folders) with --mesh, --leds and --lighting.
    mitsuba: a stage written as a Mitsuba scene (scene.xml: perspective sensors, point-emitter LEDs, the shape
    id="subject"), images/<sensor id>/ and --lighting.
    A lens distortion the calibration states (transforms: camera_model with k1…k4, p1, p2; easymocap: dist_<cam>;
    colmap: its camera models) is undone: every image becomes the pinhole camera's with the same K."""
    folder: Path = field(metadata=option(positional=True))
    """The source folder (humanolat: SUBJECT_<id>, holding shared/ and POSE_<nn>/; transforms: the JSON's folder;
    easymocap, colmap: the rig's folder, holding images/; mitsuba: the stage's folder, holding scene.xml)."""
    out: Path
    """Capture folder to write (layout: docs/data-format.md), with import_report.md. Rerunning resumes."""
    config: ImportConfig = field(default_factory=ImportConfig)
    humanolat: HumanolatOptions = field(default_factory=HumanolatOptions)
    transforms: TransformsOptions = field(default_factory=TransformsOptions)
    easymocap: EasymocapOptions = field(default_factory=EasymocapOptions)
    colmap: ColmapOptions = field(default_factory=ColmapOptions)
    mitsuba: MitsubaOptions = field(default_factory=MitsubaOptions)
    shards: ShardOptions = field(default_factory=ShardOptions)

    def validate(self) -> None:
        self.config.validate()
        self.shards.validate()
        routes = ("humanolat", "transforms", "easymocap", "colmap", "mitsuba")
        read = {
            "humanolat": ["humanolat"],
            "transforms": ["transforms"],
            "easymocap": ["transforms", "easymocap"],
            "colmap": ["transforms", "easymocap", "colmap"],
            "mitsuba": ["easymocap", "mitsuba"],
        }
        read = read[self.source]
        for name in routes:  # another route's option would be ignored unsaid
            if name not in read and (given := changed_options(getattr(self, name))):
                raise GraMiParameterError(given[0], f"is a {name} option: `gra-mi import {self.source}` does not read it")
        for name in read:
            if hasattr(getattr(self, name), "validate"):
                getattr(self, name).validate()


def run_import(c: ImportCommand) -> None:
    from gra_mi.fit.led_gains import estimate_led_gains  # the fit's closed form measures them: a layer above the import

    shard, gains = c.shards.resolved(), estimate_led_gains
    if c.source == "humanolat":
        capture = import_humanolat(c.folder, c.out, c.config, c.humanolat, c.overwrite, shard, gains)
    elif c.source == "transforms":
        capture = import_transforms(c.folder, c.out, c.config, c.transforms, c.overwrite, shard, gains)
    elif c.source == "easymocap":
        capture = import_easymocap(c.folder, c.out, c.config, c.easymocap, c.transforms, c.overwrite, shard, gains)
    elif c.source == "colmap":
        capture = import_colmap(c.folder, c.out, c.config, c.colmap, c.easymocap, c.transforms, c.overwrite, shard, gains)
    else:
        capture = import_mitsuba(c.folder, c.out, c.config, c.mitsuba, c.easymocap.lighting, c.overwrite, shard, gains)
    if capture is None:
        print(f"shard {shard}: its images are in {c.out / 'images'}; the shard that finishes last writes capture.json")
        return
    cameras = len(capture.train_cameras) + len(capture.eval_cameras)
    print(f"imported {len(capture.frames)} lightings × {cameras} cameras into {c.out}; read {c.out / 'import_report.md'} first")
