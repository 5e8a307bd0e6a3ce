"""The ``gra-mi`` command line.

Every subcommand chooses the Mitsuba variant once (``--variant``; automatic by default) and turns bad input
(:class:`GraMiInputError`) into one line on stderr with exit code 2, never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from gra_mi.errors import GraMiInputError

logger = logging.getLogger("gra_mi")

REPO_SCENES = Path(__file__).resolve().parent.parent / "scenes"


def _add_variant(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--variant",
        choices=["llvm_ad_rgb", "cuda_ad_rgb", "scalar_rgb"],
        default=None,
        help="Mitsuba variant. Default: cuda_ad_rgb where a CUDA GPU works, else llvm_ad_rgb (CPU).",
    )


def _parse_clips(text: str) -> list[str]:
    from gra_mi.anny_body import MOTION_CLIPS

    clips = [c.strip() for c in text.split(",") if c.strip()]
    unknown = [c for c in clips if c not in MOTION_CLIPS]
    if unknown or not clips:
        raise argparse.ArgumentTypeError(f"unknown clip(s) {unknown}; choose from {sorted(MOTION_CLIPS)}")
    return clips


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gra-mi",
        description="gra-mi: relightable full-body avatars on Mitsuba 3 / Dr.Jit (Generative Relightable Avatars).",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="Log debug messages.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    # demo ---------------------------------------------------------------------------------------------------
    p = sub.add_parser("demo", help="Run the whole pipeline (as far as it exists) on a small preset and write a report.")
    p.add_argument(
        "--preset",
        choices=["tiny", "small"],
        default="small",
        help="tiny: procedural subject, seconds (CI). small: the anny body on the default 331-LED rig, minutes on 2 cores.",
    )
    p.add_argument(
        "--out", type=Path, default=Path("outputs/demo"), help="Output folder (renders, plots, report.md). Default: outputs/demo."
    )
    _add_variant(p)

    # rig ----------------------------------------------------------------------------------------------------
    p = sub.add_parser("rig", help="Write a lightstage rig folder: calibration.json, leds.xml, cameras.xml.")
    p.add_argument("--out", type=Path, required=True, help="Folder to write the rig into.")
    p.add_argument(
        "--from-calibration", type=Path, default=None, help="Make the XML from an existing calibration JSON instead of the default layout."
    )
    p.add_argument("--num-leds", type=int, default=331, help="LEDs spread evenly over the sphere (Fibonacci spiral). Default: 331.")
    p.add_argument("--radius", type=float, default=2.0, help="LED sphere radius in metres. Default: 2.0.")
    p.add_argument("--num-cameras", type=int, default=40, help="Cameras on four rings at several heights. Default: 40.")
    p.add_argument("--camera-distance", type=float, default=1.8, help="Camera distance from the stage centre in metres. Default: 1.8.")
    p.add_argument("--width", type=int, default=1024, help="Image width in pixels. Default: 1024.")
    p.add_argument("--height", type=int, default=540, help="Image height in pixels. Default: 540.")
    p.add_argument(
        "--max-led-intensity",
        type=float,
        default=4.0,
        help="Radiant intensity (W/sr) of a fully driven LED; envmaps are normalised to it. Default: 4.",
    )

    # envmaps ------------------------------------------------------------------------------------------------
    p = sub.add_parser("envmaps", help="Write procedural HDR environment maps (skies and rooms) as EXR + PNG, split by seed.")
    p.add_argument("--out", type=Path, required=True, help="Folder; maps go to OUT/train and OUT/test.")
    p.add_argument("--train", type=int, default=16, help="Number of training envmaps. Default: 16.")
    p.add_argument("--test", type=int, default=4, help="Number of held-out test envmaps (disjoint seeds). Default: 4.")
    p.add_argument("--height", type=int, default=128, help="Lat-long height in pixels (width = 2x). Default: 128.")
    _add_variant(p)

    # subject ------------------------------------------------------------------------------------------------
    p = sub.add_parser("subject", help="Write an animated tracked mesh sequence (sequence.npz + per-frame PLYs).")
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

    # scene --------------------------------------------------------------------------------------------------
    p = sub.add_parser("scene", help="Write a Mitsuba scene file that puts a subject sequence into a rig.")
    p.add_argument("--out", type=Path, required=True, help="Scene XML file to write.")
    p.add_argument("--rig", type=Path, required=True, help="Rig folder (from `gra-mi rig`).")
    p.add_argument("--subject", type=Path, required=True, help="Sequence folder (from `gra-mi subject`).")
    p.add_argument("--spp", type=int, default=64, help="Default samples per pixel written into the scene. Default: 64.")

    # render -------------------------------------------------------------------------------------------------
    p = sub.add_parser("render", help="Render a lightstage scene with a stock Mitsuba integrator; writes EXR + PNG.")
    p.add_argument("scene", type=Path, help="Scene XML (e.g. scenes/tiny_lightstage.xml).")
    p.add_argument("--frame", type=int, default=0, help="Frame of the subject sequence. Default: 0.")
    p.add_argument("--camera", default="0", help="Camera index or name. Default: 0.")
    light = p.add_mutually_exclusive_group(required=True)
    light.add_argument("--envmap", type=Path, help="Lat-long HDR EXR mapped onto the LEDs.")
    light.add_argument("--olat", type=int, help="Light one LED (index) at the stage maximum.")
    light.add_argument("--pattern", type=Path, help='LED drive values: JSON {"intensities": [[r,g,b],...]} or .npy of shape (L,) or (L,3).')
    p.add_argument(
        "--repair-envmap", action="store_true", help="Replace NaN/Inf/negative envmap pixels (with a warning) instead of stopping."
    )
    p.add_argument("--integrator", choices=["direct", "path"], default="direct", help="Mitsuba integrator. Default: direct.")
    p.add_argument("--spp", type=int, default=128, help="Samples per pixel. Default: 128.")
    p.add_argument("--seed", type=int, default=0, help="Sampler seed. Default: 0.")
    p.add_argument("--background", action="store_true", help="Also write a preview composited over the envmap's background plate.")
    p.add_argument("--out", type=Path, default=Path("outputs/render"), help="Output folder. Default: outputs/render.")
    _add_variant(p)

    # capture ------------------------------------------------------------------------------------------------
    p = sub.add_parser("capture", help="Generate a synthetic lightstage capture (images, masks, lighting, true maps).")
    p.add_argument("--out", type=Path, required=True, help="Capture folder (layout: docs/data-format.md). Rerunning resumes.")
    p.add_argument(
        "--preset",
        choices=["tiny", "small", "full"],
        default="small",
        help="tiny: CI, seconds; small: the demo, minutes; full: 40 cameras at 1024x540, 512² UV.",
    )
    p.add_argument(
        "--renderer",
        choices=["path", "onebounce"],
        default="path",
        help="Ground truth: Mitsuba path tracing of a richer material (default), or gra-mi's one-bounce model (recovery tests).",
    )
    _add_variant(p)

    # fit ----------------------------------------------------------------------------------------------------
    p = sub.add_parser("fit", help="Fit per-texel albedo and roughness to a capture (albedo.exr, roughness.exr, fit_report.md).")
    p.add_argument("capture", type=Path, help="Capture folder (from `gra-mi capture` or converted real data).")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/fit"),
        help="Output folder; holds a checkpoint, so rerunning resumes. Default: outputs/fit.",
    )
    p.add_argument(
        "--roughness-candidates",
        type=int,
        default=11,
        help="Roughness values tried per texel on a uniform grid over [0, 1] before refinement. Default: 11.",
    )
    p.add_argument(
        "--irls-iterations", type=int, default=3, help="L1 reweighting iterations after least squares (0: least squares only). Default: 3."
    )
    p.add_argument("--uv-resolution", type=int, default=None, help="UV resolution of the fitted maps (default: the capture's).")
    _add_variant(p)

    # edit-texture -------------------------------------------------------------------------------------------
    p = sub.add_parser(
        "edit-texture", help="Edit a fitted albedo: paint an image over it, or tint a UV mask; re-render with `relight --albedo`."
    )
    p.add_argument("--albedo", type=Path, required=True, help="Albedo UV texture to edit (square RGB EXR, e.g. from `gra-mi fit`).")
    p.add_argument(
        "--image", type=Path, default=None, help="Edit layer (PNG in sRGB, or EXR in linear), RGB or RGBA: alpha says where it applies."
    )
    p.add_argument("--mask", type=Path, default=None, help="UV mask (PNG or EXR, single channel in [0,1]) for --color.")
    p.add_argument("--color", default=None, help="Linear RGB albedo r,g,b in [0,1] painted where --mask is set.")
    p.add_argument("--opacity", type=float, default=1.0, help="Strength of the edit in [0, 1]. Default: 1.")
    p.add_argument("--out", type=Path, required=True, help="Edited albedo EXR to write (a PNG preview is written beside it).")

    # export-gltf --------------------------------------------------------------------------------------------
    p = sub.add_parser("export-gltf", help="Export the fitted avatar as glTF 2.0 (.glb): mesh, textures, frames as morph targets.")
    p.add_argument("--subject", type=Path, required=True, help="Tracked mesh sequence folder (e.g. CAPTURE/subject).")
    p.add_argument("--albedo", type=Path, required=True, help="Albedo UV texture (EXR), e.g. from `gra-mi fit`.")
    p.add_argument("--roughness", type=Path, required=True, help="Roughness UV texture (EXR), e.g. from `gra-mi fit`.")
    p.add_argument("--frames", type=int, default=None, help="Frames to include as morph targets (default: all).")
    p.add_argument("--out", type=Path, required=True, help="The .glb file to write.")

    # train-relightnet ---------------------------------------------------------------------------------------
    p = sub.add_parser(
        "train-relightnet", help="Train RelightNet on a capture and its fitted maps; validate on held-out cameras and envmaps."
    )
    p.add_argument("capture", type=Path, help="Capture folder.")
    p.add_argument("--fit", type=Path, required=True, help="Fit folder with albedo.exr and roughness.exr (from `gra-mi fit`).")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/relightnet"),
        help="Output folder: weights, logs, plots, validation; a checkpoint makes reruns resume. Default: outputs/relightnet.",
    )
    p.add_argument("--steps", type=int, default=400, help="Optimisation steps. Default: 400.")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate. Default: 1e-3.")
    p.add_argument(
        "--base-channels", type=int, default=16, help="UNet channels at full resolution (doubled per level, capped at 128). Default: 16."
    )
    p.add_argument("--checkpoint-every", type=int, default=50, help="Steps between checkpoints. Default: 50.")
    p.add_argument(
        "--max-train-views", type=int, default=None, help="Train on the first N training views only (an overfitting check). Default: all."
    )
    _add_variant(p)

    # video refiner ------------------------------------------------------------------------------------------
    p = sub.add_parser(
        "refiner-data",
        help="Build the video refiner's sequences (coarse render, ground truth, camera-space envmaps, reference) from a capture, or synthetic ones.",
    )
    p.add_argument("capture", type=Path, nargs="?", default=None, help="Capture folder (omit with --synthetic).")
    p.add_argument("--fit", type=Path, default=None, help="Fit folder with albedo.exr and roughness.exr (from `gra-mi fit`).")
    p.add_argument(
        "--relightnet",
        type=Path,
        default=None,
        help="Trained RelightNet folder: coarse frames are its renders. Default: the microfacet render.",
    )
    p.add_argument("--out", type=Path, required=True, help="Output folder (dataset.json + sequences/).")
    p.add_argument("--scale", type=float, default=0.5, help="Image scale before padding to multiples of 16. Default: 0.5.")
    p.add_argument("--env-height", type=int, default=16, help="Camera-space envmap height (width = 2x). Default: 16.")
    p.add_argument("--train-length", type=int, default=24, help="Frames per training sequence (looping clips repeat). Default: 24.")
    p.add_argument("--test-length", type=int, default=41, help="Frames per test sequence (41 = three 17-frame windows). Default: 41.")
    p.add_argument(
        "--synthetic",
        action="store_true",
        help="Synthetic sequences instead (a textured ball under a new light each frame): fast, for tests and trials.",
    )
    p.add_argument("--subjects", type=int, default=1, help="--synthetic: number of subjects. Default: 1.")
    p.add_argument("--sequences", type=int, default=8, help="--synthetic: training sequences per subject. Default: 8.")
    p.add_argument("--resolution", type=int, default=64, help="--synthetic: frame height and width (multiple of 16). Default: 64.")
    _add_variant(p)

    p = sub.add_parser(
        "train-refiner",
        help="Train the video refiner (WAN2.1-VACE + LoRA + atemporal envmap attention, flow matching with error recycling).",
    )
    p.add_argument("data", type=Path, help="Refiner dataset folder (from `gra-mi refiner-data`).")
    p.add_argument(
        "--out",
        type=Path,
        default=Path("outputs/refiner"),
        help="Output folder: weights, logs, loss plot; a checkpoint makes reruns resume.",
    )
    p.add_argument(
        "--size", choices=["tiny", "1.3B", "14B"], default="tiny", help="Model size. tiny: random weights, CPU. Real sizes need --weights."
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
        "--dtype", choices=["float32", "bfloat16"], default="float32", help="Transformer dtype (the VAE stays float32). Default: float32."
    )
    p.add_argument(
        "--init", type=Path, default=None, help="Start from a trained refiner (few-shot identity adaptation on a new subject's clips)."
    )
    p.add_argument("--lora-rank", type=int, default=32, help="LoRA rank on the main DiT blocks. Default: 32.")
    p.add_argument(
        "--env-blocks",
        default="all",
        help="Main blocks followed by atemporal envmap attention: 'all', 'none' or a comma list. Default: all.",
    )
    p.add_argument("--steps", type=int, default=200, help="Optimisation steps. Default: 200.")
    p.add_argument("--lr", type=float, default=1e-3, help="AdamW learning rate. Default: 1e-3.")
    p.add_argument("--grad-accumulation", type=int, default=1, help="Windows per optimisation step. Default: 1.")
    p.add_argument("--no-error-recycling", action="store_true", help="Plain flow matching (an ablation).")
    p.add_argument("--bank-per-level", type=int, default=32, help="Error-bank residuals kept per noise level (memory bound). Default: 32.")
    p.add_argument("--checkpoint-every", type=int, default=50, help="Steps between checkpoints. Default: 50.")
    p.add_argument("--seed", type=int, default=0, help="Random seed. Default: 0.")

    p = sub.add_parser("refine", help="Refine a sequence of any length with rolling 17-frame windows: EXR/PNG frames, MP4s, refine.json.")
    p.add_argument("data", type=Path, help="Refiner dataset folder holding the sequence.")
    p.add_argument("--model", type=Path, required=True, help="Trained refiner folder (from `gra-mi train-refiner`).")
    p.add_argument("--sequence", default=None, help="Sequence name (default: the first test sequence).")
    p.add_argument("--out", type=Path, default=Path("outputs/refined"), help="Output folder. Default: outputs/refined.")
    p.add_argument("--steps", type=int, default=20, help="Euler steps per window. Default: 20.")
    p.add_argument("--shift", type=float, default=3.0, help="Wan time shift of the sampling schedule (1 = none). Default: 3.0.")
    p.add_argument("--seed", type=int, default=0, help="Seed of the first window (each window uses seed + its index). Default: 0.")
    p.add_argument("--frames", type=int, default=None, help="Refine only the first N frames. Default: all.")
    p.add_argument("--no-handoff", action="store_true", help="Ablation: independent windows (no seed frames from the previous window).")
    p.add_argument(
        "--no-pin",
        action="store_true",
        help="Ablation: let the sampler move the given latents (reference, seed frames) instead of pinning them to their exact flow path.",
    )
    p.add_argument(
        "--no-crossfade", action="store_true", help="Ablation: cut to the new window instead of cross-fading over the handed-off frames."
    )
    p.add_argument(
        "--no-fuse-lora",
        action="store_true",
        help="Keep the LoRA apart from the DiT's weights instead of folding it in (about 13 %% slower per step for real sizes; "
        "folding measured no less accurate, benchmarks/refiner.py).",
    )

    p = sub.add_parser("refiner-prompt", help="Cache the umT5 prompt embedding of a local WAN2.1 pipeline once (real sizes).")
    p.add_argument("--pipeline", type=Path, required=True, help="Local diffusers WAN2.1(-VACE) folder with tokenizer/ and text_encoder/.")
    p.add_argument("--prompt", default="a person, photorealistic, studio lighting", help="The fixed prompt.")
    p.add_argument("--out", type=Path, required=True, help="The .safetensors file to write.")

    # bench --------------------------------------------------------------------------------------------------
    p = sub.add_parser("bench", help="Speed against error of every approximation (report.md, CSV/JSON, Pareto plot).")
    p.add_argument("--quick", action="store_true", help="Small resolutions and fewer configurations: a few minutes on 2 cores (CI).")
    p.add_argument("--out", type=Path, default=Path("outputs/bench"), help="Output folder. Default: outputs/bench.")
    _add_variant(p)

    # relight ------------------------------------------------------------------------------------------------
    p = sub.add_parser("relight", help="One-bounce coarse renders (GGX, per-LED visibility) of frames x cameras x lighting: EXR, PNG, MP4.")
    p.add_argument("scene", type=Path, help="Lightstage scene XML (e.g. scenes/tiny_lightstage.xml).")
    p.add_argument("--frames", default="all", help="Frames: 'all', 'A:B' (B excluded) or a comma list. Default: all.")
    p.add_argument("--cameras", default="0", help="Cameras: 'all' or a comma list of indices or names. Default: 0.")
    p.add_argument("--envmap", type=Path, action="append", default=[], help="Lat-long HDR EXR mapped onto the LEDs (repeatable).")
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
        "--stage",
        choices=["microfacet", "relightnet"],
        default="microfacet",
        help="microfacet: the one-bounce render; relightnet: passed through a trained RelightNet (needs --relightnet).",
    )
    p.add_argument(
        "--relightnet",
        type=Path,
        default=None,
        help="Folder with relightnet.safetensors + relightnet.json (from `gra-mi train-relightnet`).",
    )
    p.add_argument("--point-light-intensity", type=float, default=2.0, help="Radiant intensity of the point light in W/sr. Default: 2.")
    p.add_argument(
        "--point-light-radius", type=float, default=0.03, help="Radius of the point light's sphere in metres (soft shadows). Default: 0.03."
    )
    p.add_argument(
        "--repair-envmap", action="store_true", help="Replace NaN/Inf/negative envmap pixels (with a warning) instead of stopping."
    )
    p.add_argument(
        "--albedo",
        type=Path,
        default=None,
        help="Albedo UV texture (square RGB EXR in [0,1]). Default: the subject's vertex colours baked to UV.",
    )
    p.add_argument(
        "--roughness", type=Path, default=None, help="Roughness UV texture (square single-channel EXR in [0,1]). Default: 0.5 everywhere."
    )
    p.add_argument(
        "--uv-resolution", type=int, default=512, help="UV texture resolution when no albedo texture is given. Default: 512 (the paper's)."
    )
    p.add_argument(
        "--far-field",
        action="store_true",
        help="Treat LEDs as directional lights seen from the stage centre (for comparison with near field).",
    )
    p.add_argument(
        "--save-uv",
        action="store_true",
        help="Also write the UV-space radiance and the RelightNet inputs (normal, position, view direction, mask) as EXR.",
    )
    p.add_argument(
        "--background", action="store_true", help="Composite envmap renders over the camera's background plate in the PNG/MP4 previews."
    )
    p.add_argument("--exposure", type=float, default=None, help="Preview exposure (default: automatic per light and camera).")
    p.add_argument(
        "--vis-cache", type=Path, default=None, help="Folder to keep per-frame visibility in (reused across runs). Default: memory only."
    )
    p.add_argument("--out", type=Path, default=Path("outputs/relight"), help="Output folder. Default: outputs/relight.")
    _add_variant(p)
    return parser


def _parse_list(text: str, count: int, what: str) -> list[str]:
    if text == "all":
        return [str(i) for i in range(count)]
    if ":" in text:
        a, b = text.split(":", 1)
        try:
            return [str(i) for i in range(int(a or 0), int(b) if b else count)]
        except ValueError:
            raise GraMiInputError(f"--{what}", f"expected A:B with integers, got '{text}'") from None
    return [t.strip() for t in text.split(",") if t.strip()]


# --------------------------------------------------------------------------------------------------------------


def _cmd_rig(args) -> None:
    from gra_mi.lightstage import default_lightstage, load_calibration
    from gra_mi.scene import write_rig

    if args.from_calibration:
        stage = load_calibration(args.from_calibration)
    else:
        stage = default_lightstage(
            args.num_leds,
            args.radius,
            args.num_cameras,
            args.camera_distance,
            args.width,
            args.height,
            max_led_intensity=args.max_led_intensity,
        )
    folder = write_rig(stage, args.out)
    print(f"wrote rig with {stage.num_leds} LEDs and {len(stage.cameras)} cameras to {folder}")


def _cmd_envmaps(args) -> None:
    from gra_mi.envmap_library import write_envmap_set
    from gra_mi.variant import choose_variant

    choose_variant(args.variant)
    for split, count in (("train", args.train), ("test", args.test)):
        if count < 0:
            raise GraMiInputError(f"--{split}", "must be >= 0")
        paths = write_envmap_set(args.out, split, count, args.height)
        print(f"{split}: {len(paths)} envmaps in {args.out / split}")


def _cmd_subject(args) -> None:
    from gra_mi.subject import save_sequence, tiny_subject

    if args.kind == "tiny":
        seq = tiny_subject(args.frames)
    else:
        from gra_mi.anny_body import anny_sequence

        seq = anny_sequence(args.clips, args.frames_per_clip)
    save_sequence(seq, args.out)
    print(f"wrote {seq.num_frames} frames, {seq.num_vertices} vertices, {len(seq.faces)} triangles to {args.out}")


def _cmd_scene(args) -> None:
    import os

    from gra_mi.imageio import atomic_write_text
    from gra_mi.scene import subject_scene_xml

    for folder, what in ((args.rig, "calibration.json"), (args.subject, "sequence.npz")):
        if not (folder / what).is_file():
            raise GraMiInputError(folder / what, "file not found")
    base = args.out.resolve().parent
    rig = os.path.relpath(args.rig.resolve(), base)
    subject = os.path.relpath(args.subject.resolve(), base)
    atomic_write_text(args.out, subject_scene_xml(rig, subject, spp=args.spp))
    print(f"wrote {args.out}")


def _cmd_render(args) -> None:
    from gra_mi.envmap import background_plate, load_envmap
    from gra_mi.imageio import write_exr, write_png
    from gra_mi.lightstage import load_pattern, olat_pattern
    from gra_mi.scene import LightstageScene, composite_over, render
    from gra_mi.variant import choose_variant

    if args.spp < 1:
        raise GraMiInputError("--spp", f"must be >= 1, got {args.spp}")
    envmap = load_envmap(args.envmap, repair=args.repair_envmap) if args.envmap else None
    choose_variant(args.variant)
    ls = LightstageScene.load(args.scene, frame=args.frame)
    camera = ls.stage.camera(args.camera)
    if envmap is not None:
        ls.set_envmap(envmap)
        light = args.envmap.stem
    elif args.olat is not None:
        ls.set_pattern(olat_pattern(ls.stage, args.olat))
        light = f"olat{args.olat:03d}"
    else:
        ls.set_pattern(load_pattern(ls.stage, args.pattern))
        light = args.pattern.stem
    image = render(ls, camera.name, args.integrator, args.spp, args.seed)
    stem = args.out / f"{camera.name}_f{args.frame:04d}_{light}"
    write_exr(stem.with_suffix(".exr"), image)
    write_png(stem.with_suffix(".png"), image, exposure=None)
    if args.background and envmap is not None:
        from gra_mi.envmap import envmap_to_leds

        # The plate in the same units as the render: the LED normalisation scales the whole lighting.
        scale = envmap_to_leds(envmap, ls.stage).scale
        composite = composite_over(image, background_plate(envmap, camera) * scale)
        write_png(stem.with_name(stem.name + "_composite.png"), composite, exposure=None)
    print(f"wrote {stem}.exr")


def _cmd_relight(args) -> None:
    import numpy as np

    from gra_mi.envmap import background_plate, envmap_to_leds, load_envmap
    from gra_mi.imageio import auto_exposure, write_exr, write_mp4, write_png
    from gra_mi.lightstage import load_pattern, olat_pattern
    from gra_mi.plugins import register_plugins
    from gra_mi.progress import progress
    from gra_mi.relight import Relighter, load_texture
    from gra_mi.scene import LightstageScene, composite_over
    from gra_mi.variant import choose_variant

    if not (args.envmap or args.olat or args.pattern or args.point_light):
        raise GraMiInputError("lighting", "give at least one --envmap, --olat, --pattern or --point-light")
    from gra_mi.point_light import conditioning_envmap, conditioning_pattern, parse_point_light

    point_light = parse_point_light(args.point_light, args.point_light_intensity, args.point_light_radius) if args.point_light else None
    envmaps = {p.stem: load_envmap(p, repair=args.repair_envmap) for p in args.envmap}
    albedo = load_texture(args.albedo, 3, "albedo") if args.albedo else None
    roughness = load_texture(args.roughness, 1, "roughness") if args.roughness else None
    choose_variant(args.variant)
    register_plugins()
    ls = LightstageScene.load(args.scene)
    stage = ls.stage
    frames = [int(f) for f in _parse_list(args.frames, ls.sequence.num_frames, "frames")]
    for f in frames:
        if not 0 <= f < ls.sequence.num_frames:
            raise GraMiInputError("--frames", f"frame {f} out of range [0, {ls.sequence.num_frames})")
    cameras = [stage.camera(c) for c in _parse_list(args.cameras, len(stage.cameras), "cameras")]
    lights: dict[str, tuple[object, float]] = {}
    if point_light is not None:
        lights["point_light"] = (np.zeros((stage.num_leds, 3)), 1.0)
        pattern = conditioning_pattern(stage, ls.scene, point_light)
        write_exr(args.out / "point_light" / "conditioning.exr", conditioning_envmap(stage, pattern))
        write_png(args.out / "point_light" / "conditioning.png", conditioning_envmap(stage, pattern), exposure=None)
        np.save(args.out / "point_light" / "conditioning_leds.npy", pattern)
    for name, env in envmaps.items():
        lighting = envmap_to_leds(env, stage)
        lights[name] = (lighting.radiant_intensity(stage), lighting.scale)
    for k in args.olat:
        lights[f"olat{k:03d}"] = (olat_pattern(stage, k) * stage.gains, 1.0)
    for path in args.pattern:
        lights[path.stem] = (load_pattern(stage, path) * stage.gains, 1.0)

    model = None
    if args.stage == "relightnet":
        if args.relightnet is None:
            raise GraMiInputError("--relightnet", "--stage relightnet needs the folder of a trained RelightNet")
        from gra_mi.relightnet import RelightNet
        from gra_mi.variant import torch_device

        model = RelightNet.load(args.relightnet, torch_device())
        if albedo is not None and albedo.shape[0] != model.config.resolution:
            raise GraMiInputError(args.albedo, f"RelightNet runs at {model.config.resolution}², the albedo is {albedo.shape[0]}²")
        args.uv_resolution = model.config.resolution
    relighter = Relighter(ls, args.uv_resolution, albedo, roughness, args.far_field, args.vis_cache)
    videos: dict[tuple[str, str], list] = {}
    exposures: dict[tuple[str, str], float] = {}
    jobs = [(f, light, cam) for f in frames for light in lights for cam in cameras]  # frame-major: one trace per frame
    for frame, light, cam in progress(jobs, description="relight"):
        intensities, scale = lights[light]
        light_source = point_light if light == "point_light" else None
        if model is None:
            view = relighter.render(frame, cam.name, intensities, light_source)
        else:
            from gra_mi.relight import ViewRender
            from gra_mi.relightnet_train import relightnet_texture
            from gra_mi.uvspace import rasterize_to_camera

            texture, shading = relightnet_texture(model, relighter, frame, cam.name, intensities, light_source)
            image = rasterize_to_camera(ls.scene, cam, texture, relighter.atlas.mask)
            shading.radiance = relighter.atlas.gather(texture)
            view = ViewRender(image, shading, relighter.geometry(frame))
        folder = args.out / light / cam.name
        write_exr(folder / f"frame_{frame:04d}.exr", view.image)
        shown = view.image[..., :3]
        if args.background and light in envmaps:
            shown = composite_over(view.image, background_plate(envmaps[light], cam) * scale)
        key = (light, cam.name)
        if key not in exposures:
            exposures[key] = args.exposure if args.exposure is not None else 0.8 * auto_exposure(view.image)
        write_png(folder / f"frame_{frame:04d}.png", shown, exposure=exposures[key])
        videos.setdefault(key, []).append(shown)
        if args.save_uv:
            write_exr(folder / f"uv_radiance_{frame:04d}.exr", relighter.atlas.scatter(view.shading.radiance))
            for name, tex in relighter.texel_inputs(view).items():
                write_exr(folder / f"uv_{name}_{frame:04d}.exr", tex)
    if len(frames) > 1:
        for (light, cam_name), images in videos.items():
            write_mp4(args.out / light / f"{cam_name}.mp4", images, fps=ls.sequence.fps, exposure=exposures[(light, cam_name)])
    print(
        f"wrote {len(jobs)} renders to {args.out} (visibility traced for {relighter.cache.misses} frame(s), reused {relighter.cache.hits} times)"
    )


def _cmd_capture(args) -> None:
    from gra_mi.capture import generate_capture

    capture = generate_capture(args.out, args.preset, args.renderer, args.variant)
    n = len(capture.frames) * (len(capture.train_cameras) + len(capture.eval_cameras))
    print(f"wrote {n} images of {len(capture.frames)} frames to {args.out}")


def _cmd_fit(args) -> None:
    from gra_mi.fit import FitConfig, run_fit

    config = FitConfig(args.roughness_candidates, args.irls_iterations, args.uv_resolution)
    _, report = run_fit(args.capture, args.out, config, args.variant)
    print(f"done: open {report}")


def _cmd_edit_texture(args) -> None:
    from gra_mi.imageio import write_exr, write_png
    from gra_mi.relight import load_texture
    from gra_mi.texture_edit import edit_albedo, read_edit_image

    albedo = load_texture(args.albedo, 3, "albedo")
    color = None
    if args.color is not None:
        try:
            color = tuple(float(c) for c in args.color.split(","))
        except ValueError:
            color = ()
        if len(color) != 3:
            raise GraMiInputError("--color", f"expected r,g,b, got '{args.color}'")
    if args.image is None and (args.mask is None or color is None):
        raise GraMiInputError("edit-texture", "give --image, or --mask with --color")
    image = read_edit_image(args.image) if args.image else None
    mask = read_edit_image(args.mask) if args.mask else None
    edited = edit_albedo(albedo, image, mask, color, args.opacity, source=str(args.image or args.mask))
    write_exr(args.out, edited)
    write_png(args.out.with_suffix(".png"), edited)
    print(f"wrote {args.out}; re-render with: gra-mi relight SCENE --albedo {args.out} ...")


def _cmd_export_gltf(args) -> None:
    from gra_mi.gltf import export_glb
    from gra_mi.relight import load_texture
    from gra_mi.subject import load_sequence

    seq = load_sequence(args.subject)
    albedo = load_texture(args.albedo, 3, "albedo")
    roughness = load_texture(args.roughness, 1, "roughness")
    path = export_glb(args.out, seq, albedo, roughness, args.frames)
    print(f"wrote {path}")


def _cmd_train_relightnet(args) -> None:
    from gra_mi.relightnet_train import TrainConfig, train_relightnet

    if args.steps < 1:
        raise GraMiInputError("--steps", f"must be >= 1, got {args.steps}")
    config = TrainConfig(
        steps=args.steps,
        lr=args.lr,
        checkpoint_every=args.checkpoint_every,
        base_channels=args.base_channels,
        max_train_views=args.max_train_views,
    )
    report = train_relightnet(args.capture, args.fit, args.out, config, args.variant)
    print(f"done: open {report}")


def _parse_blocks(text: str) -> list[int] | None:
    if text == "all":
        return None
    if text == "none":
        return []
    try:
        return [int(b) for b in text.split(",") if b.strip()]
    except ValueError:
        raise GraMiInputError("--env-blocks", f"expected 'all', 'none' or a comma list of block indices, got '{text}'") from None


def _cmd_refiner_data(args) -> None:
    if args.synthetic:
        from gra_mi.refiner_data import synthetic_dataset

        if args.resolution % 16:
            raise GraMiInputError("--resolution", f"must be a multiple of 16, got {args.resolution}")
        ds = synthetic_dataset(
            args.out,
            {s: (args.sequences, 1) for s in range(args.subjects)},
            17,
            args.resolution,
            args.resolution,
            args.env_height,
            args.test_length,
        )
    else:
        from gra_mi.refiner_data import dataset_from_capture

        if args.capture is None or args.fit is None:
            raise GraMiInputError("refiner-data", "give a capture folder and --fit (or --synthetic)")
        ds = dataset_from_capture(
            args.capture,
            args.fit,
            args.out,
            args.relightnet,
            args.scale,
            args.env_height,
            args.train_length,
            args.test_length,
            args.variant,
        )
    print(f"wrote {len(ds.sequences)} sequences ({ds.height}x{ds.width}) to {ds.folder}")


def _cmd_train_refiner(args) -> None:
    from gra_mi.refiner_model import RefinerConfig
    from gra_mi.refiner_train import RefinerTrainConfig, train_refiner

    if args.steps < 1:
        raise GraMiInputError("--steps", f"must be >= 1, got {args.steps}")
    model_config = RefinerConfig(
        size=args.size,
        weights=str(args.weights) if args.weights else None,
        vae_weights=str(args.vae_weights) if args.vae_weights else None,
        prompt_embeds=str(args.prompt_embeds) if args.prompt_embeds else None,
        lora_rank=args.lora_rank,
        env_blocks=_parse_blocks(args.env_blocks),
        dtype=args.dtype,
        seed=args.seed,
    )
    config = RefinerTrainConfig(
        steps=args.steps,
        lr=args.lr,
        grad_accumulation=args.grad_accumulation,
        error_recycling=not args.no_error_recycling,
        bank_per_level=args.bank_per_level,
        checkpoint_every=args.checkpoint_every,
        seed=args.seed,
    )
    out = train_refiner(args.data, args.out, config, model_config, args.init)
    print(f"done: weights and logs in {out}")


def _cmd_refine(args) -> None:
    from gra_mi.refiner_data import RefinerDataset
    from gra_mi.refiner_infer import Joins, refine_to_folder

    if args.steps < 1:
        raise GraMiInputError("--steps", f"must be >= 1, got {args.steps}")
    sequence = args.sequence
    if sequence is None:
        names = RefinerDataset(args.data).names("test") or RefinerDataset(args.data).names()
        sequence = names[0]
    joins = Joins(handoff=not args.no_handoff, pin=not args.no_pin, crossfade=not args.no_crossfade)
    summary = refine_to_folder(
        args.model,
        args.data,
        sequence,
        args.out,
        args.steps,
        args.shift,
        args.seed,
        args.frames,
        joins=joins,
        fuse_lora=not args.no_fuse_lora,
    )
    print(
        f"refined {summary['frames']} frames in {summary['windows']} windows ({summary['frames_per_second']:.2f} frames/s) into {args.out}"
    )


def _cmd_refiner_prompt(args) -> None:
    from gra_mi.refiner_model import cache_prompt_embedding

    path = cache_prompt_embedding(args.pipeline, args.prompt, args.out)
    print(f"wrote {path}")


def _cmd_bench(args) -> None:
    from gra_mi.bench import run_bench

    report = run_bench(args.out, "quick" if args.quick else "full", args.variant)
    print(f"done: open {report}")


def _cmd_demo(args) -> None:
    from gra_mi.demo import run_demo

    report = run_demo(args.preset, args.out, variant=args.variant)
    print(f"done: open {report}")


COMMANDS = {
    "demo": _cmd_demo,
    "rig": _cmd_rig,
    "envmaps": _cmd_envmaps,
    "subject": _cmd_subject,
    "scene": _cmd_scene,
    "render": _cmd_render,
    "relight": _cmd_relight,
    "bench": _cmd_bench,
    "capture": _cmd_capture,
    "fit": _cmd_fit,
    "edit-texture": _cmd_edit_texture,
    "export-gltf": _cmd_export_gltf,
    "train-relightnet": _cmd_train_relightnet,
    "refiner-data": _cmd_refiner_data,
    "train-refiner": _cmd_train_refiner,
    "refine": _cmd_refine,
    "refiner-prompt": _cmd_refiner_prompt,
}


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:
        COMMANDS[args.command](args)
    except GraMiInputError as exc:
        print(f"gra-mi {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"gra-mi {args.command}: interrupted (finished files are kept; rerun to resume)", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
