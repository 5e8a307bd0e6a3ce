"""The ``gra-mi`` command line: each command is a config (its inputs, output and options, with their help as field
docstrings), parsed, validated, then handed to one library call (``gra_mi/cli/*_commands.py``).

Options are generated from the configs (:mod:`gra_mi.cli.options`), so a default and its help are written once. Bad
input (:class:`GraMiInputError`) and failures on output files become one line on stderr and exit code 2, never a
traceback (``-v`` shows it); a parameter the library names (``steps``) is reported as the flag the user typed
(``--steps``).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from dataclasses import dataclass

from gra_mi.cli.options import add_config, command_paths, config_from_args, option_flags, output_files
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import check_apart, writing_into
from gra_mi.core.provenance import discard_unused_claims
from gra_mi.core.runtime import SUPPORTED_VARIANTS, bind_local_gpu
from gra_mi.render.runtime import start_runtime

logger = logging.getLogger("gra_mi")


@dataclass(frozen=True)
class Command:
    group: str  # gra_mi.cli.<group>_commands holds its config and run function (imported only when it runs)
    help: str
    mitsuba: bool = True  # starts the Mitsuba variant (and registers the plugins): --variant
    torch: bool = False  # picks the torch device: --device

    def load(self, name: str):
        """(config class, run function): ``<Name>Command`` and ``run_<name>`` of its group's module (``relight-field`` →
        ``RelightFieldCommand``, ``run_relight_field``), so that a command's name is written once, in :data:`COMMANDS`."""
        module = importlib.import_module(f"gra_mi.cli.{self.group}_commands")
        words = name.split("-")
        return getattr(module, "".join(w.capitalize() for w in words) + "Command"), getattr(module, "run_" + "_".join(words))


def _add_runtime(p: argparse.ArgumentParser, command: Command) -> None:
    if command.mitsuba:
        p.add_argument(
            "--variant",
            choices=list(SUPPORTED_VARIANTS),
            default=None,
            help="Mitsuba variant. Default: cuda_ad_rgb where a CUDA GPU works, else llvm_ad_rgb (CPU).",
        )
    if command.torch:
        p.add_argument(
            "--device", default=None, help="Torch device for the learned stages (cpu, cuda, cuda:N). Default: cuda where torch sees a GPU."
        )


COMMANDS: dict[str, Command] = {
    "demo": Command("run", "Run the whole pipeline (as far as it exists) on a small preset and write a report.", torch=True),
    "rig": Command("scene", "Write a lightstage rig folder: calibration.json, leds.xml, cameras.xml.", mitsuba=False),
    "envmaps": Command("scene", "Write procedural HDR environment maps (skies and rooms) as EXR + PNG, split by seed."),
    "subject": Command("scene", "Write an animated tracked mesh sequence (sequence.npz + per-frame PLYs).", mitsuba=False),
    "scene": Command("scene", "Write a Mitsuba scene file that puts a subject sequence into a rig.", mitsuba=False),
    "from-scene": Command(
        "scene",
        "A gra-mi lightstage from a Mitsuba scene you wrote: its perspective sensors as the cameras, point emitters as "
        "the LEDs, the subject mesh and its material's albedo and roughness, the other shapes as the set (then relight, view, "
        "export).",
    ),
    "view": Command(
        "run", "Relight the avatar live in a browser: envmaps, OLATs, a draggable point light (viser; prints its URL).", torch=True
    ),
    "render": Command(
        "scene", "Render any Mitsuba 3 scene (or a lightstage scene under an envmap, OLAT or pattern): EXR + PNG per sensor."
    ),
    "relight": Command(
        "texture",
        "One-bounce coarse renders (GGX, per-LED visibility) of frames x cameras x lighting: EXR, PNG, MP4.",
        torch=True,
    ),
    "bench": Command("run", "Speed against error of every approximation (report.md, CSV/JSON, Pareto plot)."),
    "relight-field": Command(
        "texture",
        "A capture's cameras under any LED lighting as the weighted sum of its OLAT photographs (no model).",
        mitsuba=False,
    ),
    "eval-lighting": Command(
        "texture",
        "Relight under reference environments (sun, studio, interior, night), near vs far field (vs RelightNet), against the path-traced truth.",
        torch=True,
    ),
    "eval": Command(
        "run",
        "Score every stage (microfacet, + RelightNet, + refiner, + flicker correction) on held-out cameras and lighting: "
        "PSNR, SSIM, FLIP, temporal error (LPIPS, FVD with local weights); eval.md table, contact sheets, MP4s.",
        torch=True,
    ),
    "deflicker": Command(
        "learned",
        "Flicker correction of a folder of frames towards temporally stable renders (guided filter; paper supplementary).",
        mitsuba=False,
        torch=True,
    ),
    "capture": Command("scene", "Generate a synthetic lightstage capture (images, masks, lighting, true maps)."),
    "import": Command(
        "scene",
        "Import a real capture (HumanOLAT, transforms.json, EasyMocap, a COLMAP-calibrated rig, a stage written as a Mitsuba scene) into the capture layout, "
        "with an import report to read first.",
    ),
    "fit": Command(
        "texture",
        "Fit per-texel albedo and roughness to a capture (albedo.exr, roughness.exr, fit_report.md). Under torchrun "
        "(--nproc_per_node N) the N processes fit together, each its share of the frames (docs/guides/scale.md).",
    ),
    "edit-texture": Command(
        "texture",
        "Edit a fitted albedo: paint an image over it, or tint a UV mask; re-render with `relight --albedo`.",
        mitsuba=False,
    ),
    "export": Command(
        "texture",
        "Export the avatar as USD (.usdz/.usda/.usdc: animated mesh, UsdPreviewSurface, cameras, LEDs, moving lights, a "
        "scene's set) or glTF (.glb), checked by the format's validator.",
    ),
    "train-relightnet": Command(
        "learned",
        "Train RelightNet on a capture and its fitted maps; validate on held-out cameras and envmaps.",
        torch=True,
    ),
    "refiner-data": Command(
        "learned",
        "Build the video refiner's sequences (coarse render, ground truth, camera-space envmaps, reference) from a capture, or synthetic ones.",
        torch=True,
    ),
    "train-refiner": Command(
        "learned",
        "Train the video refiner (WAN2.1-VACE + LoRA + atemporal envmap attention, flow matching with error recycling).",
        mitsuba=False,
        torch=True,
    ),
    "refine": Command(
        "learned",
        "Refine a sequence of any length with rolling 17-frame windows: EXR/PNG frames, MP4s, refine.json.",
        mitsuba=False,
        torch=True,
    ),
    "refiner-prompt": Command(
        "learned",
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
            add_config(p, command.load(name)[0])
            _add_runtime(p, command)
        p.set_defaults(flags=option_flags(p))
    return parser


def _message(exc: GraMiInputError, flags: dict[str, str]) -> str:
    """The error in the CLI user's words: a parameter the library names is shown as its flag."""
    if isinstance(exc, GraMiParameterError) and exc.parameter in flags:
        return f"{flags[exc.parameter]}: {exc.problem}"
    return str(exc)


def main(argv: list[str] | None = None) -> int:

    words = sys.argv[1:] if argv is None else argv
    selected = next((w for w in words if not w.startswith("-")), None)
    try:
        args = build_parser(selected if selected in COMMANDS else None).parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option, already said in one line (2)
        return int(exc.code or 0)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    command = COMMANDS[args.command]
    try:
        bind_local_gpu()  # before anything starts CUDA: one GPU per process under torchrun / srun
        start_runtime(getattr(args, "variant", None), getattr(args, "device", None), mitsuba=command.mitsuba, torch=command.torch)
        config_class, run = command.load(args.command)
        config = config_from_args(config_class, args)
        config.validate()
        outputs, inputs = command_paths(config)
        check_apart(outputs, inputs, output_files(config))  # before anything is written
        with writing_into(outputs.values()):
            code = run(config)
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
