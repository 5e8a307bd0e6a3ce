"""The ``gra-mi`` command line: each command parses, validates, starts the runtime once and calls one library function.

Options of the stages' configs are generated from the configs themselves (:mod:`gra_mi.cli.options`), so a default
and its help are written once. Bad input (:class:`GraMiInputError`) and failures on output files become one line on
stderr and exit code 2, never a traceback (``-v`` shows it); a parameter the library names (``steps``) is reported as
the flag the user typed (``--steps``).
"""

from __future__ import annotations

import argparse
import inspect
import logging
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from gra_mi.cli.options import add_config_options, config_from_args, finite_float, option_flags
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive, require_seed
from gra_mi.core.runtime import SUPPORTED_VARIANTS

logger = logging.getLogger("gra_mi")


def _defaults(fn: Callable) -> dict[str, object]:
    """A library function's keyword defaults: the CLI shows these instead of restating them."""
    return {k: p.default for k, p in inspect.signature(fn).parameters.items() if p.default is not inspect.Parameter.empty}


def _add_runtime(p: argparse.ArgumentParser, torch: bool = False) -> None:
    p.add_argument(
        "--variant",
        choices=list(SUPPORTED_VARIANTS),
        default=None,
        help="Mitsuba variant. Default: cuda_ad_rgb where a CUDA GPU works, else llvm_ad_rgb (CPU).",
    )
    if torch:
        _add_device(p)


def _add_device(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--device", default=None, help="Torch device for the learned stages (cpu, cuda, cuda:N). Default: cuda where torch sees a GPU."
    )


def _add_envmap_input(p: argparse.ArgumentParser) -> None:
    from gra_mi.stage.envmap import DEFAULT_ENVMAP_HEIGHT, ENVMAP_CONVENTIONS

    p.add_argument(
        "--envmap-convention",
        choices=sorted(ENVMAP_CONVENTIONS),
        default="mitsuba",
        help="Which tool's lat-long layout the envmaps follow: mitsuba/gra-mi (image centre = +Z), blender/polyhaven or "
        "threejs/gltf (centre = +X after the usual Y-up conversion); see docs/conventions.md. Default: mitsuba.",
    )
    p.add_argument(
        "--envmap-rotate",
        type=finite_float,
        default=0.0,
        help="Turn the envmaps about the up axis by this many degrees (counter-clockwise seen from above).",
    )
    p.add_argument(
        "--envmap-height",
        type=int,
        default=DEFAULT_ENVMAP_HEIGHT,
        help=f"Larger envmaps are downsampled to this many rows, flux kept, before the LED mapping. Default: {DEFAULT_ENVMAP_HEIGHT}.",
    )
    p.add_argument(
        "--repair-envmap",
        action="store_true",
        help="Replace NaN/Inf envmap pixels (with a warning) instead of stopping. Negative pixels (lossy-compression ringing) "
        "are always removed with the flux kept, with a warning.",
    )


def _envmap_loader(args) -> Callable[[Path], object]:
    from gra_mi.stage.envmap import load_envmap

    if args.envmap_height < 2:
        raise GraMiParameterError("envmap_height", f"must be >= 2, got {args.envmap_height}")
    if not math.isfinite(args.envmap_rotate):
        raise GraMiParameterError("envmap_rotate", f"must be a finite angle in degrees, got {args.envmap_rotate}")
    return lambda path: load_envmap(path, args.repair_envmap, args.envmap_convention, args.envmap_rotate, args.envmap_height)


def _parse_clips(text: str) -> list[str]:
    from gra_mi.subject.anny_body import MOTION_CLIPS

    clips = [c.strip() for c in text.split(",") if c.strip()]
    unknown = [c for c in clips if c not in MOTION_CLIPS]
    if unknown or not clips:
        raise argparse.ArgumentTypeError(f"unknown clip(s) {unknown}; choose from {sorted(MOTION_CLIPS)}")
    return clips


def _parse_blocks(text: str) -> list[int] | None:
    if text == "all":
        return None
    if text == "none":
        return []
    try:
        return [int(b) for b in text.split(",") if b.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'all', 'none' or a comma list of block indices, got '{text}'") from None


def _parse_list(text: str, count: int, parameter: str, integers: bool = False) -> list:
    """'all', 'A:B' (B excluded) or a comma list; an empty selection (``5:2``, ``,``) is an error, not a run that
    writes nothing."""
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


# --------------------------------------------------------------------------------------------------------------
# Commands: (arguments) -> one library call. Each registers its parser and what runtime it needs.
# --------------------------------------------------------------------------------------------------------------


@dataclass
class Command:
    run: Callable[[argparse.Namespace], int | None]  # an exit code, or None for 0
    add_arguments: Callable[[argparse.ArgumentParser], None]
    help: str
    mitsuba: bool = True  # starts the Mitsuba variant (and registers the plugins)
    torch: bool = False  # picks the torch device


def _add_overwrite(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="Start over: empty the output folder first (only a folder gra-mi made). Without it, rerunning the same run "
        "resumes, and a folder made by a different run (other inputs or options; its provenance.json says which) is refused.",
    )


def _args_demo(p):
    p.add_argument(
        "--preset",
        choices=["tiny", "small"],
        default="small",
        help="tiny: procedural subject, seconds (CI). small: the anny body on the default 331-LED rig, minutes on 2 cores.",
    )
    p.add_argument(
        "--out", type=Path, default=Path("outputs/demo"), help="Output folder (renders, plots, report.md). Default: outputs/demo."
    )
    _add_overwrite(p)
    _add_runtime(p, torch=True)


def _cmd_demo(args) -> None:
    from gra_mi.apps.demo import run_demo

    print(f"done: open {run_demo(args.preset, args.out, args.overwrite)}")


def _args_rig(p):
    from gra_mi.stage.lightstage import default_lightstage

    d = _defaults(default_lightstage)
    p.add_argument("--out", type=Path, required=True, help="Folder to write the rig into.")
    p.add_argument(
        "--from-calibration", type=Path, default=None, help="Make the XML from an existing calibration JSON instead of the default layout."
    )
    p.add_argument(
        "--num-leds",
        type=int,
        default=d["num_leds"],
        help=f"LEDs spread evenly over the sphere (Fibonacci spiral). Default: {d['num_leds']}.",
    )
    p.add_argument("--radius", type=finite_float, default=d["radius"], help=f"LED sphere radius in metres. Default: {d['radius']}.")
    p.add_argument(
        "--num-cameras", type=int, default=d["num_cameras"], help=f"Cameras on four rings at several heights. Default: {d['num_cameras']}."
    )
    p.add_argument(
        "--camera-distance",
        type=finite_float,
        default=d["camera_distance"],
        help=f"Camera distance from the stage centre in metres. Default: {d['camera_distance']}.",
    )
    p.add_argument("--width", type=int, default=d["width"], help=f"Image width in pixels. Default: {d['width']}.")
    p.add_argument("--height", type=int, default=d["height"], help=f"Image height in pixels. Default: {d['height']}.")
    p.add_argument(
        "--max-led-intensity",
        type=finite_float,
        default=d["max_led_intensity"],
        help=f"Radiant intensity (W/sr) of a fully driven LED; envmaps are normalised to it. Default: {d['max_led_intensity']}.",
    )


def _cmd_rig(args) -> None:
    from gra_mi.stage.lightstage import default_lightstage, load_calibration
    from gra_mi.stage.scene import write_rig

    if args.from_calibration:
        stage = load_calibration(args.from_calibration)
    else:
        names = ("num_leds", "radius", "num_cameras", "camera_distance", "width", "height", "max_led_intensity")
        stage = default_lightstage(**{n: getattr(args, n) for n in names})
    folder = write_rig(stage, args.out)
    print(f"wrote rig with {stage.num_leds} LEDs and {len(stage.cameras)} cameras to {folder}")


def _args_envmaps(p):
    p.add_argument("--out", type=Path, required=True, help="Folder; maps go to OUT/train and OUT/test.")
    p.add_argument("--train", type=int, default=16, help="Number of training envmaps. Default: 16.")
    p.add_argument("--test", type=int, default=4, help="Number of held-out test envmaps (disjoint seeds). Default: 4.")
    p.add_argument("--height", type=int, default=128, help="Lat-long height in pixels (width = 2x). Default: 128.")
    _add_runtime(p)


def _cmd_envmaps(args) -> None:
    from gra_mi.stage.envmap_library import write_envmap_set

    for split, count in (("train", args.train), ("test", args.test)):
        if count < 0:
            raise GraMiParameterError(split, "must be >= 0")
    if args.height < 4:
        raise GraMiParameterError("height", f"must be >= 4 (lat-long rows), got {args.height}")
    for split, count in (("train", args.train), ("test", args.test)):
        paths = write_envmap_set(args.out, split, count, args.height)
        print(f"{split}: {len(paths)} envmaps in {args.out / split}")


def _args_subject(p):
    p.add_argument("--out", type=Path, required=True, help="Folder to write the sequence into.")
    p.add_argument(
        "--kind",
        choices=["anny", "tiny"],
        default="anny",
        help="anny: the MakeHuman-based body; tiny: a ~450-triangle procedural subject for tests.",
    )
    p.add_argument(
        "--clips",
        type=_parse_clips,
        default=["walk", "arm_raise", "turn", "squat"],
        help="Comma-separated motion clips for anny (walk, arm_raise, turn, squat), played in order.",
    )
    p.add_argument("--frames-per-clip", type=int, default=None, help="Frames per clip loop (default: each clip's own, 24-48).")
    p.add_argument("--frames", type=int, default=8, help="Frames for --kind tiny. Default: 8.")


def _cmd_subject(args) -> None:
    from gra_mi.subject.sequence import save_sequence, tiny_subject

    require_positive({"frames": args.frames})
    if args.frames_per_clip is not None:
        require_positive({"frames_per_clip": args.frames_per_clip})
    if args.kind == "tiny":
        seq = tiny_subject(args.frames)
    else:
        from gra_mi.subject.anny_body import anny_sequence

        seq = anny_sequence(args.clips, args.frames_per_clip)
    save_sequence(seq, args.out)
    print(f"wrote {seq.num_frames} frames, {seq.num_vertices} vertices, {len(seq.faces)} triangles to {args.out}")


def _args_scene(p):
    p.add_argument("--out", type=Path, required=True, help="Scene XML file to write.")
    p.add_argument("--rig", type=Path, required=True, help="Rig folder (from `gra-mi rig`).")
    p.add_argument("--subject", type=Path, required=True, help="Sequence folder (from `gra-mi subject`).")
    p.add_argument("--spp", type=int, default=64, help="Default samples per pixel written into the scene. Default: 64.")


def _cmd_scene(args) -> None:
    from gra_mi.stage.scene import write_scene_file

    print(f"wrote {write_scene_file(args.out, args.rig, args.subject, args.spp)}")


def _args_render(p):
    p.add_argument("scene", type=Path, help="Scene XML (e.g. scenes/tiny_lightstage.xml).")
    p.add_argument("--frame", type=int, default=0, help="Frame of the subject sequence. Default: 0.")
    p.add_argument("--camera", default="0", help="Camera index or name. Default: 0.")
    light = p.add_mutually_exclusive_group(required=True)
    light.add_argument("--envmap", type=Path, help="Lat-long HDR map (OpenEXR or Radiance .hdr) mapped onto the LEDs.")
    light.add_argument("--olat", type=int, help="Light one LED (index) at the stage maximum.")
    light.add_argument("--pattern", type=Path, help='LED drive values: JSON {"intensities": [[r,g,b],...]} or .npy of shape (L,) or (L,3).')
    _add_envmap_input(p)
    p.add_argument("--integrator", choices=["direct", "path"], default="direct", help="Mitsuba integrator. Default: direct.")
    p.add_argument(
        "--spp", type=int, default=64, help="Samples per pixel (the low-discrepancy sampler rounds up to a power of 4). Default: 64."
    )
    p.add_argument("--seed", type=int, default=0, help="Sampler seed. Default: 0.")
    p.add_argument("--background", action="store_true", help="Also write a preview composited over the envmap's background plate.")
    p.add_argument("--out", type=Path, default=Path("outputs/render"), help="Output folder. Default: outputs/render.")
    _add_runtime(p)


def _cmd_render(args) -> None:
    from gra_mi.stage.lightstage import load_pattern, olat_pattern
    from gra_mi.stage.scene import render_to_folder

    if args.spp < 1:
        raise GraMiParameterError("spp", f"must be >= 1, got {args.spp}")
    require_seed(args.seed)
    if args.envmap:
        light, envmap, drive = args.envmap.stem, _envmap_loader(args)(args.envmap), None
    elif args.olat is not None:
        light, envmap, drive = f"olat{args.olat:03d}", None, lambda stage: olat_pattern(stage, args.olat)
    else:
        light, envmap, drive = args.pattern.stem, None, lambda stage: load_pattern(stage, args.pattern)
    stem = render_to_folder(
        args.scene, args.out, args.frame, args.camera, light, envmap, drive, args.integrator, args.spp, args.seed, args.background
    )
    print(f"wrote {stem}.exr")


def _args_capture(p):
    from gra_mi.capture.synthetic import PRESETS

    p.add_argument("--out", type=Path, required=True, help="Capture folder (layout: docs/data-format.md). Rerunning resumes.")
    p.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default="small",
        help="tiny: CI, seconds; small: the demo, minutes; medium: 48 training envmaps, 8 cameras, OLAT test, about 15 "
        "minutes on 2 cores; full: 40 cameras at 1024x540, 512² UV (a GPU's work).",
    )
    p.add_argument(
        "--renderer",
        choices=["path", "onebounce"],
        default="path",
        help="Ground truth: Mitsuba path tracing of a richer material (default), or gra-mi's one-bounce model (recovery tests).",
    )
    p.add_argument(
        "--spp", type=int, default=None, help="Samples per pixel of the exact direct light (a power of 4). Default: the preset's."
    )
    p.add_argument(
        "--indirect-spp",
        type=int,
        default=None,
        help="Path samples per pixel of the interreflections (a power of 4). Default: the preset's.",
    )
    p.add_argument(
        "--without",
        default="",
        help="Effects to leave out of the path-traced ground truth, comma-separated: sheen, wrinkles, interreflection. "
        "Fitting such captures shows what each effect costs the one-bounce fit (docs/results/fit.md).",
    )
    p.add_argument(
        "--test-envmap",
        type=Path,
        action="append",
        default=[],
        help="Your own HDR map (OpenEXR or .hdr) as held-out test lighting, in place of a procedural one (repeatable).",
    )
    _add_envmap_input(p)
    _add_overwrite(p)
    _add_runtime(p)


def _cmd_capture(args) -> None:
    from gra_mi.capture.synthetic import generate_capture

    load = _envmap_loader(args)
    stems = [path.stem for path in args.test_envmap]
    if len(set(stems)) != len(stems):
        raise GraMiParameterError("test_envmap", f"two maps share a name ({stems}); the capture stores them by name")
    test_envmaps = {path.stem: load(path) for path in args.test_envmap}
    capture = generate_capture(
        args.out,
        args.preset,
        args.renderer,
        test_envmaps=test_envmaps,
        spp=args.spp,
        indirect_spp=args.indirect_spp,
        without=tuple(e.strip() for e in args.without.split(",") if e.strip()),
        overwrite=args.overwrite,
    )
    n = len(capture.frames) * (len(capture.train_cameras) + len(capture.eval_cameras))
    print(f"wrote {n} images of {len(capture.frames)} frames to {args.out}")


def _args_fit(p):
    from gra_mi.fit.materials import FitConfig

    p.add_argument("capture", type=Path, help="Capture folder (from `gra-mi capture` or converted real data).")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/fit"),
        help="Output folder; holds a checkpoint, so rerunning resumes. Default: outputs/fit.",
    )
    add_config_options(
        p,
        FitConfig,
        [
            "solver", "iterations", "lr_albedo", "lr_roughness", "smooth_albedo", "smooth_roughness", "min_view_cos",
            "roughness_candidates", "irls_iterations", "resolution", "calibrate_brightness",
        ],
        flags={"resolution": "--uv-resolution"},
        choices={"solver": ["adam", "closed-form"]},
    )  # fmt: skip
    _add_overwrite(p)
    _add_runtime(p)


def _cmd_fit(args) -> None:
    from gra_mi.fit.materials import FitConfig, run_fit

    _, report = run_fit(args.capture, args.out, config_from_args(FitConfig, args), args.overwrite)
    print(f"done: open {report}")


def _args_edit_texture(p):
    p.add_argument("--albedo", type=Path, required=True, help="Albedo UV texture to edit (square RGB EXR, e.g. from `gra-mi fit`).")
    p.add_argument(
        "--image", type=Path, default=None, help="Edit layer (PNG in sRGB, or EXR in linear), RGB or RGBA: alpha says where it applies."
    )
    p.add_argument("--mask", type=Path, default=None, help="UV mask (PNG or EXR, single channel in [0,1]) for --color.")
    p.add_argument("--color", default=None, help="Linear RGB albedo r,g,b in [0,1] painted where --mask is set.")
    p.add_argument("--opacity", type=finite_float, default=1.0, help="Strength of the edit in [0, 1]. Default: 1.")
    p.add_argument("--out", type=Path, required=True, help="Edited albedo EXR to write (a PNG preview is written beside it).")


def _cmd_edit_texture(args) -> None:
    from gra_mi.apps.texture_edit import edit_albedo_file, parse_color

    color = parse_color(args.color) if args.color is not None else None
    if args.image is None and (args.mask is None or color is None):
        raise GraMiInputError("edit-texture", "give --image, or --mask with --color")
    edit_albedo_file(args.albedo, args.out, args.image, args.mask, color, args.opacity)
    print(f"wrote {args.out}; re-render with: gra-mi relight SCENE --albedo {args.out} ...")


def _args_export_gltf(p):
    p.add_argument("--subject", type=Path, required=True, help="Tracked mesh sequence folder (e.g. CAPTURE/subject).")
    p.add_argument("--albedo", type=Path, required=True, help="Albedo UV texture (EXR), e.g. from `gra-mi fit`.")
    p.add_argument("--roughness", type=Path, required=True, help="Roughness UV texture (EXR), e.g. from `gra-mi fit`.")
    p.add_argument("--frames", type=int, default=None, help="Frames to include as morph targets (default: all).")
    p.add_argument("--out", type=Path, required=True, help="The .glb file to write.")


def _cmd_export_gltf(args) -> None:
    from gra_mi.apps.gltf import export_glb
    from gra_mi.render.relighter import load_texture
    from gra_mi.subject.sequence import load_sequence

    if args.frames is not None:
        require_positive({"frames": args.frames})
    path = export_glb(
        args.out,
        load_sequence(args.subject),
        load_texture(args.albedo, 3, "albedo"),
        load_texture(args.roughness, 1, "roughness"),
        args.frames,
    )
    print(f"wrote {path}")


def _args_train_relightnet(p):
    from gra_mi.relightnet.train import TrainConfig

    p.add_argument("capture", type=Path, help="Capture folder.")
    p.add_argument("--fit", type=Path, required=True, help="Fit folder with albedo.exr and roughness.exr (from `gra-mi fit`).")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/relightnet"),
        help="Output folder: weights, logs, plots, validation; a checkpoint makes reruns resume. Default: outputs/relightnet.",
    )
    add_config_options(
        p,
        TrainConfig,
        ["steps", "lr", "weight_decay", "batch_size", "env_dropout", "validate_every", "selection_views", "base_channels", "patch"]
        + ["env_height", "checkpoint_every", "max_train_views", "seed"],
    )
    _add_overwrite(p)
    _add_runtime(p, torch=True)


def _cmd_train_relightnet(args) -> None:
    from gra_mi.relightnet.train import TrainConfig, train_relightnet

    print(f"done: open {train_relightnet(args.capture, args.fit, args.out, config_from_args(TrainConfig, args), args.overwrite)}")


def _args_refiner_data(p):
    from gra_mi.refiner.data import dataset_from_capture, synthetic_dataset

    d, s = _defaults(dataset_from_capture), _defaults(synthetic_dataset)
    p.add_argument("capture", type=Path, nargs="?", default=None, help="Capture folder (omit with --synthetic).")
    p.add_argument("--fit", type=Path, default=None, help="Fit folder with albedo.exr and roughness.exr (from `gra-mi fit`).")
    p.add_argument(
        "--relightnet",
        type=Path,
        default=None,
        help="Trained RelightNet folder: coarse frames are its renders. Default: the microfacet render.",
    )
    p.add_argument("--out", type=Path, required=True, help="Output folder (dataset.json + sequences/).")
    p.add_argument(
        "--scale",
        type=finite_float,
        default=d["scale"],
        help=f"Capture images → the delivered (and evaluated) frames. Default: {d['scale']}.",
    )
    p.add_argument(
        "--zoom",
        type=finite_float,
        default=d["zoom"],
        help="The refiner works on a fixed box around the subject per sequence, magnified this many times over --scale "
        "(cut from the full-resolution images); its change goes back into the delivered frames. 0: whole frames, padded "
        f"to multiples of 16. Default: {d['zoom']}.",
    )
    p.add_argument(
        "--env-height", type=int, default=d["env_height"], help=f"Camera-space envmap height (width = 2x). Default: {d['env_height']}."
    )
    p.add_argument(
        "--train-length",
        type=int,
        default=d["train_length"],
        help=f"Frames per training sequence (looping clips repeat). Default: {d['train_length']}.",
    )
    p.add_argument(
        "--test-length",
        type=int,
        default=d["test_length"],
        help=f"Frames per test sequence (41 = three 17-frame windows). Default: {d['test_length']}.",
    )
    p.add_argument(
        "--synthetic",
        action="store_true",
        help="Synthetic sequences instead (a textured ball under a new light each frame): fast, for tests and trials.",
    )
    p.add_argument("--subjects", type=int, default=1, help="--synthetic: number of subjects. Default: 1.")
    p.add_argument("--sequences", type=int, default=8, help="--synthetic: training sequences per subject. Default: 8.")
    p.add_argument(
        "--resolution", type=int, default=s["height"], help=f"--synthetic: frame height and width (multiple of 16). Default: {s['height']}."
    )
    _add_overwrite(p)
    _add_runtime(p, torch=True)


def _cmd_refiner_data(args) -> None:
    require_positive({"scale": args.scale, "train_length": args.train_length, "test_length": args.test_length})
    require_positive({"subjects": args.subjects, "sequences": args.sequences, "resolution": args.resolution})
    if args.env_height < 4:
        raise GraMiParameterError("env_height", f"must be >= 4 (lat-long rows), got {args.env_height}")
    if args.zoom != 0 and not args.zoom >= 1:  # before the capture and fit are read
        raise GraMiParameterError("zoom", f"must be >= 1 (or 0: whole frames), got {args.zoom}")
    if args.synthetic:
        from gra_mi.refiner.data import synthetic_dataset

        if args.resolution % 16:
            raise GraMiParameterError("resolution", f"must be a multiple of 16, got {args.resolution}")
        subjects = {s: (args.sequences, 1, 1) for s in range(args.subjects)}
        ds = synthetic_dataset(
            args.out, subjects, 17, args.resolution, args.resolution, args.env_height, args.test_length, overwrite=args.overwrite
        )
    else:
        from gra_mi.refiner.data import dataset_from_capture

        if args.capture is None or args.fit is None:
            raise GraMiParameterError("capture", "give a capture folder and --fit (or --synthetic)")
        ds = dataset_from_capture(
            args.capture,
            args.fit,
            args.out,
            args.relightnet,
            args.scale,
            args.env_height,
            args.train_length,
            args.test_length,
            overwrite=args.overwrite,
            zoom=args.zoom or None,
        )
    print(f"wrote {len(ds.sequences)} sequences ({ds.height}x{ds.width}) to {ds.folder}")


def _args_train_refiner(p):
    from gra_mi.refiner.model import TRANSFORMER_CONFIGS, RefinerConfig
    from gra_mi.refiner.train import RefinerTrainConfig

    p.add_argument("data", type=Path, help="Refiner dataset folder (from `gra-mi refiner-data`).")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/refiner"),
        help="Output folder: weights, logs, loss plot; a checkpoint makes reruns resume.",
    )
    p.add_argument(
        "--weights",
        type=Path,
        default=None,
        help="Real sizes: local diffusers WAN2.1-VACE folder, or original-format transformer checkpoint.",
    )
    p.add_argument(
        "--vae-weights", type=Path, default=None, help="With an original-format checkpoint: the Wan2.1 VAE checkpoint (Wan2.1_VAE.pth)."
    )
    p.add_argument(
        "--prompt-embeds", type=Path, default=None, help="Real sizes: cached umT5 prompt embedding (from `gra-mi refiner-prompt`)."
    )
    p.add_argument(
        "--init", type=Path, default=None, help="Start from a trained refiner (few-shot identity adaptation on a new subject's clips)."
    )
    add_config_options(
        p,
        RefinerConfig,
        ["size", "dtype", "lora_rank", "env_blocks", "prior", "seed"],
        choices={"size": sorted(TRANSFORMER_CONFIGS), "dtype": ["float32", "bfloat16"]},
        parsers={"env_blocks": _parse_blocks},
    )
    add_config_options(
        p,
        RefinerTrainConfig,
        [
            "steps",
            "lr",
            "grad_accumulation",
            "error_recycling",
            "bank_per_level",
            "checkpoint_every",
            "seed",
            "choose_mix",
            "selection_steps",
        ],
    )
    _add_overwrite(p)
    _add_device(p)


def _cmd_train_refiner(args) -> None:
    from gra_mi.refiner.model import RefinerConfig
    from gra_mi.refiner.train import RefinerTrainConfig, train_refiner

    paths = {k: str(getattr(args, k)) if getattr(args, k) else None for k in ("weights", "vae_weights", "prompt_embeds")}
    model_config = config_from_args(RefinerConfig, args, **paths)
    out = train_refiner(args.data, args.out, config_from_args(RefinerTrainConfig, args), model_config, args.init, args.overwrite)
    print(f"done: weights and logs in {out}")


def _args_refine(p):
    from gra_mi.refiner.infer import Joins, RefineConfig

    p.add_argument("data", type=Path, help="Refiner dataset folder holding the sequence.")
    p.add_argument("--model", type=Path, required=True, help="Trained refiner folder (from `gra-mi train-refiner`).")
    p.add_argument("--sequence", default=None, help="Sequence name (default: the first test sequence).")
    p.add_argument("--out", type=Path, default=Path("outputs/refined"), help="Output folder. Default: outputs/refined.")
    add_config_options(p, RefineConfig, ["steps", "shift", "denoise", "mix", "seed", "frames", "fuse_lora"])
    add_config_options(p, Joins, ["handoff", "pin", "crossfade"])
    p.add_argument(
        "--deflicker",
        action="store_true",
        help="Also write flicker-corrected frames (guided filter towards the coarse input; paper supplementary) to OUT/deflickered/.",
    )
    _add_deflicker_options(p)
    p.add_argument(
        "--composite",
        action="store_true",
        help="Also write composite.mp4: the frames over the environment on a platform with the subject's shadow (data made from a capture).",
    )
    _add_platform_options(p)
    _add_overwrite(p)
    _add_device(p)


def _add_deflicker_options(p) -> None:
    from gra_mi.refiner.deflicker import DeflickerConfig

    add_config_options(p, DeflickerConfig, ["filter_radius", "filter_eps", "strength"])


def _add_platform_options(p) -> None:
    from gra_mi.render.composite import PlatformConfig

    add_config_options(
        p,
        PlatformConfig,
        ["radius", "thickness", "reflectance", "spp"],
        flags={
            "radius": "--platform-radius",
            "thickness": "--platform-thickness",
            "reflectance": "--platform-reflectance",
            "spp": "--platform-spp",
        },
    )


def _platform_config(args):
    from gra_mi.render.composite import PlatformConfig

    config = config_from_args(PlatformConfig, args)
    config.validate()
    return config


def _cmd_refine(args) -> None:
    from gra_mi.refiner.data import RefinerDataset
    from gra_mi.refiner.infer import Joins, RefineConfig, refine_to_folder

    config = config_from_args(RefineConfig, args, joins=config_from_args(Joins, args))
    config.validate()  # before the model and data are read
    from gra_mi.refiner.deflicker import DeflickerConfig

    deflicker = config_from_args(DeflickerConfig, args) if args.deflicker else None
    if deflicker is not None:
        deflicker.validate()
    composite = _platform_config(args) if args.composite else None
    sequence = args.sequence
    if sequence is None:
        dataset = RefinerDataset(args.data)
        sequence = (dataset.names("test") or dataset.names())[0]
    summary = refine_to_folder(
        args.model, args.data, sequence, args.out, config, deflicker=deflicker, composite=composite, overwrite=args.overwrite
    )
    print(
        f"refined {summary['frames']} frames in {summary['windows']} windows ({summary['frames_per_second']:.2f} frames/s) into {args.out}"
    )
    if summary["mix"] < 1:
        said = "the input unchanged" if summary["mix"] == 0 else f"{summary['mix']:g} of the refiner's change"
        print(
            f"delivered {said}: mix {summary['mix']:g} ({'--mix' if args.mix is not None else 'chosen in training: ' + str(Path(args.model) / 'mix.md')})"
        )


def _args_refiner_prompt(p):
    p.add_argument("--pipeline", type=Path, required=True, help="Local diffusers WAN2.1(-VACE) folder with tokenizer/ and text_encoder/.")
    p.add_argument("--prompt", default="a person, photorealistic, studio lighting", help="The fixed prompt.")
    p.add_argument("--out", type=Path, required=True, help="The .safetensors file to write.")


def _cmd_refiner_prompt(args) -> None:
    from gra_mi.refiner.model import cache_prompt_embedding

    print(f"wrote {cache_prompt_embedding(args.pipeline, args.prompt, args.out)}")


def _args_bench(p):
    p.add_argument("--quick", action="store_true", help="Small resolutions and fewer configurations: a few minutes on 2 cores (CI).")
    p.add_argument("--out", type=Path, default=Path("outputs/bench"), help="Output folder. Default: outputs/bench.")
    _add_runtime(p)


def _cmd_bench(args) -> None:
    from gra_mi.apps.bench import run_bench

    print(f"done: open {run_bench(args.out, 'quick' if args.quick else 'full')}")


def _args_relight(p):
    from gra_mi.apps.relight import LIGHTING_MODELS, STAGES, RelightConfig

    p.add_argument("scene", type=Path, help="Lightstage scene XML (e.g. scenes/tiny_lightstage.xml).")
    p.add_argument("--frames", default="all", help="Frames: 'all', 'A:B' (B excluded) or a comma list. Default: all.")
    p.add_argument("--cameras", default="0", help="Cameras: 'all' or a comma list of indices or names. Default: 0.")
    p.add_argument(
        "--envmap",
        type=Path,
        action="append",
        default=[],
        help="Lat-long HDR map (OpenEXR or Radiance .hdr) mapped onto the LEDs (repeatable).",
    )
    p.add_argument("--olat", type=int, action="append", default=[], help="Light one LED (index) at the stage maximum (repeatable).")
    p.add_argument(
        "--pattern", type=Path, action="append", default=[], help="LED drive values, JSON or .npy (repeatable; see docs/data-format.md)."
    )
    p.add_argument(
        "--point-light",
        default=None,
        metavar="X,Y,Z",
        help="A near-field point light at X,Y,Z metres (LEDs off); also writes its envmap conditioning.",
    )
    p.add_argument(
        "--point-light-intensity", type=finite_float, default=2.0, help="Radiant intensity of the point light in W/sr. Default: 2."
    )
    p.add_argument(
        "--point-light-radius",
        type=finite_float,
        default=0.03,
        help="Radius of the point light's sphere in metres (soft shadows). Default: 0.03.",
    )
    p.add_argument(
        "--stage",
        choices=STAGES,
        default="microfacet",
        help="microfacet: the one-bounce render; relightnet: passed through a trained RelightNet (needs --relightnet).",
    )
    p.add_argument(
        "--relightnet",
        type=Path,
        default=None,
        help="Folder with relightnet.safetensors + relightnet.json (from `gra-mi train-relightnet`).",
    )
    _add_envmap_input(p)
    p.add_argument(
        "--albedo",
        type=Path,
        default=None,
        help="Albedo UV texture (square RGB EXR in [0,1]). Default: the subject's vertex colours baked to UV.",
    )
    p.add_argument(
        "--roughness", type=Path, default=None, help="Roughness UV texture (square single-channel EXR in [0,1]). Default: 0.5 everywhere."
    )
    add_config_options(
        p,
        RelightConfig,
        ["uv_resolution", "lighting_model", "save_uv", "background", "composite", "exposure", "fidelity"],
        choices={"lighting_model": list(LIGHTING_MODELS)},
    )
    _add_platform_options(p)
    p.add_argument(
        "--vis-cache", type=Path, default=None, help="Folder to keep per-frame visibility in (reused across runs). Default: memory only."
    )
    p.add_argument("--out", type=Path, default=Path("outputs/relight"), help="Output folder. Default: outputs/relight.")
    _add_runtime(p, torch=True)


def _cmd_relight(args) -> None:
    from gra_mi.apps.relight import RelightConfig, collect_lights, relight_batch
    from gra_mi.render.point_light import parse_point_light
    from gra_mi.render.relighter import load_texture
    from gra_mi.stage.lightstage import load_pattern
    from gra_mi.stage.scene import LightstageScene

    if not (args.envmap or args.olat or args.pattern or args.point_light):
        raise GraMiInputError("lighting", "give at least one --envmap, --olat, --pattern or --point-light")
    config = config_from_args(RelightConfig, args)
    config.validate()  # before any file is read
    point_light = parse_point_light(args.point_light, args.point_light_intensity, args.point_light_radius) if args.point_light else None
    for option, paths in (("envmap", args.envmap), ("pattern", args.pattern)):
        stems = [p.stem for p in paths]
        if twice := sorted({s for s in stems if stems.count(s) > 1}):
            raise GraMiParameterError(option, f"two files named '{twice[0]}' would write to one folder {args.out / twice[0]}; rename one")
    load = _envmap_loader(args)
    envmaps = {p.stem: load(p) for p in args.envmap}
    albedo = load_texture(args.albedo, 3, "albedo") if args.albedo else None
    roughness = load_texture(args.roughness, 1, "roughness") if args.roughness else None
    ls = LightstageScene.load(args.scene)
    lights = collect_lights(ls.stage, envmaps, args.olat, {p.stem: load_pattern(ls.stage, p) for p in args.pattern}, point_light)
    frames = _parse_list(args.frames, ls.sequence.num_frames, "frames", integers=True)
    cameras = _parse_list(args.cameras, len(ls.stage.cameras), "cameras")
    summary = relight_batch(
        ls,
        args.out,
        lights,
        frames,
        cameras,
        config,
        args.stage,
        args.relightnet,
        albedo,
        roughness,
        args.vis_cache,
        _platform_config(args),
    )
    print(
        f"wrote {summary.renders} renders to {summary.out} (visibility traced {summary.visibility_traced} time(s), once per frame and lighting model; "
        f"reused {summary.visibility_reused} times)"
    )


def _args_eval_lighting(p):
    from gra_mi.eval.lighting import EnvmapAccuracyConfig

    p.add_argument("capture", type=Path, help="Capture folder made by `gra-mi capture` (its scene_gt.xml holds the true materials).")
    p.add_argument("--fit", type=Path, required=True, help="Fit folder (albedo.exr, roughness.exr from `gra-mi fit`).")
    p.add_argument(
        "--relightnet", type=Path, default=None, help="A trained RelightNet folder: also score RelightNet on the far-field render."
    )
    add_config_options(
        p, EnvmapAccuracyConfig, ["maps", "frame", "cameras", "spp", "map_height"], parsers={"maps": _comma_list, "cameras": _comma_list}
    )
    p.add_argument("--out", type=Path, default=Path("outputs/lighting"), help="Output folder. Default: outputs/lighting.")
    _add_runtime(p, torch=True)


def _comma_list(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def _cmd_eval_lighting(args) -> None:
    from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy

    envmap_accuracy(args.capture, args.fit, args.out, args.relightnet, config_from_args(EnvmapAccuracyConfig, args))
    print((args.out / "accuracy.md").read_text())
    print(f"done: open {args.out / 'accuracy.md'}")


def _args_eval(p):
    from gra_mi.eval.protocol import FRAME_SELECTIONS, EvalConfig

    p.add_argument(
        "run",
        type=Path,
        nargs="?",
        default=None,
        help="A run folder laid out as `gra-mi demo` writes it (capture/, fit/, relightnet/, refiner/data/, refiner/refined/); "
        "the options below override or replace its parts.",
    )
    p.add_argument("--capture", type=Path, default=None, help="Capture folder (the truth, its held-out cameras and lighting).")
    p.add_argument("--fit", type=Path, default=None, help="Fit folder: scores the microfacet render with the fitted maps.")
    p.add_argument("--relightnet", type=Path, default=None, help="Trained RelightNet folder: scores + RelightNet.")
    p.add_argument(
        "--refiner-data", type=Path, default=None, help="The refiner's data folder (dataset.json): the sequences the refiner saw."
    )
    p.add_argument(
        "--refined",
        type=Path,
        action="append",
        default=None,
        help="A `gra-mi refine` output folder (refine.json; its deflickered/ is scored as flicker correction), or a folder of them. Repeatable.",
    )
    p.add_argument(
        "--lpips-weights",
        type=str,
        action="append",
        default=None,
        help="LPIPS weights on disk: torchvision's alexnet-owt-7be5be79.pth and the lpips package's weights/v0.1/alex.pth "
        "(repeat the flag, or give their folder), or one lpips.LPIPS(net='alex') state dict. Never downloaded.",
    )
    add_config_options(p, EvalConfig, ["frames", "scale", "i3d_weights", "composite"], choices={"frames": list(FRAME_SELECTIONS)})
    _add_platform_options(p)
    p.add_argument("--out", type=Path, default=None, help="Output folder. Default: RUN/eval, or outputs/eval without a run folder.")
    _add_runtime(p, torch=True)


def _cmd_eval(args) -> int:
    from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate

    config = config_from_args(EvalConfig, args, lpips_weights=args.lpips_weights, platform=_platform_config(args))
    config.validate()
    if args.run is not None:
        inputs = EvalInputs.from_run(args.run)
    elif args.capture is not None:
        inputs = EvalInputs(args.capture)
    else:
        raise GraMiParameterError("run", "give a run folder, or --capture (with the stages' folders to score)")
    for name in ("capture", "fit", "relightnet", "refiner_data"):
        if getattr(args, name) is not None:
            setattr(inputs, name, getattr(args, name))
            inputs.explicit.add(name)
    if args.refined:
        inputs.refined = list(args.refined)
        inputs.explicit.add("refined")
    out = args.out or (args.run / "eval" if args.run is not None else Path("outputs/eval"))
    report = evaluate(inputs, out, config)
    print((out / "eval.md").read_text())
    for problem in report["problems"]:
        print(f"gra-mi eval: error: {problem}", file=sys.stderr)
    print(f"done: open {out / 'eval.md'}")
    return 2 if report["problems"] else 0


def _args_deflicker(p):
    p.add_argument("frames", type=Path, help="Folder of frames to correct (EXR, or PNG; sorted by name), e.g. a refine output's frames/.")
    p.add_argument(
        "--stable",
        type=Path,
        required=True,
        help="Folder of the temporally stable renders of the same views (e.g. RelightNet's), one per frame, same size.",
    )
    p.add_argument(
        "--exposure",
        type=finite_float,
        default=None,
        help="Linear → display exposure the filter works at (default: the first stable frame's 99th percentile at 0.8).",
    )
    p.add_argument("--out", type=Path, default=Path("outputs/deflickered"), help="Output folder. Default: outputs/deflickered.")
    _add_deflicker_options(p)


def _cmd_deflicker(args) -> None:
    from gra_mi.refiner.deflicker import DeflickerConfig, deflicker_folder

    if args.exposure is not None and not (math.isfinite(args.exposure) and args.exposure > 0):
        raise GraMiParameterError("exposure", f"must be a finite number > 0, got {args.exposure}")
    written = deflicker_folder(args.frames, args.stable, args.out, config_from_args(DeflickerConfig, args), args.exposure)
    print(f"deflickered {len(written)} frames into {args.out}")


COMMANDS: dict[str, Command] = {
    "demo": Command(
        _cmd_demo, _args_demo, "Run the whole pipeline (as far as it exists) on a small preset and write a report.", torch=True
    ),
    "rig": Command(_cmd_rig, _args_rig, "Write a lightstage rig folder: calibration.json, leds.xml, cameras.xml.", mitsuba=False),
    "envmaps": Command(_cmd_envmaps, _args_envmaps, "Write procedural HDR environment maps (skies and rooms) as EXR + PNG, split by seed."),
    "subject": Command(
        _cmd_subject, _args_subject, "Write an animated tracked mesh sequence (sequence.npz + per-frame PLYs).", mitsuba=False
    ),
    "scene": Command(_cmd_scene, _args_scene, "Write a Mitsuba scene file that puts a subject sequence into a rig.", mitsuba=False),
    "render": Command(_cmd_render, _args_render, "Render a lightstage scene with a stock Mitsuba integrator; writes EXR + PNG."),
    "relight": Command(
        _cmd_relight,
        _args_relight,
        "One-bounce coarse renders (GGX, per-LED visibility) of frames x cameras x lighting: EXR, PNG, MP4.",
        torch=True,
    ),
    "bench": Command(_cmd_bench, _args_bench, "Speed against error of every approximation (report.md, CSV/JSON, Pareto plot)."),
    "eval-lighting": Command(
        _cmd_eval_lighting,
        _args_eval_lighting,
        "Relight under reference environments (sun, studio, interior, night), near vs far field (vs RelightNet), against the path-traced truth.",
        torch=True,
    ),
    "eval": Command(
        _cmd_eval,
        _args_eval,
        "Score every stage (microfacet, + RelightNet, + refiner, + flicker correction) on held-out cameras and lighting: "
        "PSNR, SSIM, FLIP, temporal error (LPIPS, FVD with local weights); eval.md table, contact sheets, MP4s.",
        torch=True,
    ),
    "deflicker": Command(
        _cmd_deflicker,
        _args_deflicker,
        "Flicker correction of a folder of frames towards temporally stable renders (guided filter; paper supplementary).",
        mitsuba=False,
        torch=True,
    ),
    "capture": Command(_cmd_capture, _args_capture, "Generate a synthetic lightstage capture (images, masks, lighting, true maps)."),
    "fit": Command(_cmd_fit, _args_fit, "Fit per-texel albedo and roughness to a capture (albedo.exr, roughness.exr, fit_report.md)."),
    "edit-texture": Command(
        _cmd_edit_texture,
        _args_edit_texture,
        "Edit a fitted albedo: paint an image over it, or tint a UV mask; re-render with `relight --albedo`.",
        mitsuba=False,
    ),
    "export-gltf": Command(
        _cmd_export_gltf,
        _args_export_gltf,
        "Export the fitted avatar as glTF 2.0 (.glb): mesh, textures, frames as morph targets.",
        mitsuba=False,
    ),
    "train-relightnet": Command(
        _cmd_train_relightnet,
        _args_train_relightnet,
        "Train RelightNet on a capture and its fitted maps; validate on held-out cameras and envmaps.",
        torch=True,
    ),
    "refiner-data": Command(
        _cmd_refiner_data,
        _args_refiner_data,
        "Build the video refiner's sequences (coarse render, ground truth, camera-space envmaps, reference) from a capture, or synthetic ones.",
        torch=True,
    ),
    "train-refiner": Command(
        _cmd_train_refiner,
        _args_train_refiner,
        "Train the video refiner (WAN2.1-VACE + LoRA + atemporal envmap attention, flow matching with error recycling).",
        mitsuba=False,
        torch=True,
    ),
    "refine": Command(
        _cmd_refine,
        _args_refine,
        "Refine a sequence of any length with rolling 17-frame windows: EXR/PNG frames, MP4s, refine.json.",
        mitsuba=False,
        torch=True,
    ),
    "refiner-prompt": Command(
        _cmd_refiner_prompt,
        _args_refiner_prompt,
        "Cache the umT5 prompt embedding of a local WAN2.1 pipeline once (real sizes).",
        mitsuba=False,
    ),
}


class Parser(argparse.ArgumentParser):
    """argparse with the house error format: one line naming the option, exit code 2 (not usage + error)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see `{self.prog} --help`)\n")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The whole parser, or (``only``) one whose other commands carry no arguments: building a command's options
    imports its stage (torch, diffusers), which ``gra-mi rig --help`` should not wait for."""
    parser = Parser(
        prog="gra-mi", description="gra-mi: relightable full-body avatars on Mitsuba 3 / Dr.Jit (Generative Relightable Avatars)."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="Log debug messages, and show the traceback of an error.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, command in COMMANDS.items():
        p = sub.add_parser(name, help=command.help, description=command.help)
        if only is None or name == only:
            command.add_arguments(p)
        p.set_defaults(flags=option_flags(p))
    return parser


def _message(exc: GraMiInputError, flags: dict[str, str]) -> str:
    """The error in the CLI user's words: a parameter the library names is shown as its flag."""
    if isinstance(exc, GraMiParameterError) and exc.parameter in flags:
        return f"{flags[exc.parameter]}: {exc.problem}"
    return str(exc)


def main(argv: list[str] | None = None) -> int:
    from gra_mi.core.provenance import discard_unused_claims
    from gra_mi.render.runtime import start_runtime

    words = sys.argv[1:] if argv is None else argv
    selected = next((w for w in words if not w.startswith("-")), None)
    try:
        args = build_parser(selected if selected in COMMANDS else None).parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option, already said in one line (2)
        return int(exc.code or 0)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    command = COMMANDS[args.command]
    try:
        start_runtime(getattr(args, "variant", None), getattr(args, "device", None), mitsuba=command.mitsuba, torch=command.torch)
        code = command.run(args)
    except GraMiInputError as exc:
        discard_unused_claims()
        if args.verbose:
            logger.exception("bad input")
        print(f"gra-mi {args.command}: error: {_message(exc, args.flags)}", file=sys.stderr)
        return 2
    except OSError as exc:  # an output that cannot be written (read-only, full disk, a file where a folder belongs)
        discard_unused_claims()
        if args.verbose:
            logger.exception("file system error")
        print(f"gra-mi {args.command}: error: {exc.filename or ''}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gra-mi {args.command}: interrupted (finished files are kept; rerun to resume)", file=sys.stderr)
        return 130
    return int(code or 0)  # a command that finished but could not do all it was asked returns 2 itself


if __name__ == "__main__":
    sys.exit(main())
