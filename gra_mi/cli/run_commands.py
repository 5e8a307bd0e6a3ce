"""Commands over a whole run: ``demo``, ``bench``, ``eval``."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

from gra_mi.cli.options import CommandConfig, Restartable
from gra_mi.core.config import option
from gra_mi.core.errors import GraMiParameterError
from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate


@dataclass(kw_only=True)
class DemoCommand(Restartable):
    preset: str = field(default="small", metadata=option(choices=("tiny", "small", "olat")))
    """tiny: procedural subject, seconds (CI). small: the anny body on the default 331-LED rig, minutes on 2 cores.
    olat: a static pose lit by each of 331 LEDs (a reflectance field), fitted from the OLATs, RelightNet trained on
    lightings synthesized from them, scored under held-out envmaps and OLATs."""
    out: Path = Path("outputs/demo")
    """Output folder (renders, plots, report.md)."""


def run_demo(c: DemoCommand) -> None:
    from gra_mi.apps.demo import run_demo as demo

    print(f"done: open {demo(c.preset, c.out, c.overwrite)}")


@dataclass(kw_only=True)
class BenchCommand(CommandConfig):
    quick: bool = False
    """Small resolutions and fewer configurations: a few minutes on 2 cores (CI)."""
    out: Path = Path("outputs/bench")
    """Output folder."""


def run_bench(c: BenchCommand) -> None:
    from gra_mi.apps.bench import run_bench as bench

    print(f"done: open {bench(c.out, 'quick' if c.quick else 'full')}")


@dataclass(kw_only=True)
class EvalCommand(CommandConfig):
    run: Path | None = field(default=None, metadata=option(positional=True))
    """A run folder laid out as `gra-mi demo` writes it (capture/, fit/, relightnet/, refiner/data/, refiner/refined/);
    the options below override or replace its parts."""
    capture: Path | None = None
    """Capture folder (the truth, its held-out cameras and lighting)."""
    fit: Path | None = None
    """Fit folder: scores the microfacet render with the fitted maps."""
    relightnet: Path | None = None
    """Trained RelightNet folder: scores + RelightNet."""
    refiner_data: Path | None = None
    """The refiner's data folder (dataset.json): the sequences the refiner saw."""
    refined: list[Path] | None = field(default=None, metadata=option(repeat=True))
    """A `gra-mi refine` output folder (refine.json; its deflickered/ is scored as flicker correction), or a folder of
    them. Repeatable."""
    eval: EvalConfig = field(default_factory=EvalConfig)
    out: Path | None = None
    """Output folder. Default: RUN/eval, or outputs/eval without a run folder."""

    def validate(self) -> None:
        super().validate()
        if self.run is None and self.capture is None:
            raise GraMiParameterError("run", "give a run folder, or --capture (with the stages' folders to score)")


def run_eval(c: EvalCommand) -> int:

    inputs = EvalInputs.from_run(c.run) if c.run is not None else EvalInputs(c.capture)
    for name in ("capture", "fit", "relightnet", "refiner_data"):
        if getattr(c, name) is not None:
            setattr(inputs, name, getattr(c, name))
            inputs.explicit.add(name)
    if c.refined:
        inputs.refined = list(c.refined)
        inputs.explicit.add("refined")
    out = c.out or (c.run / "eval" if c.run is not None else Path("outputs/eval"))
    report = evaluate(inputs, out, c.eval)
    print((out / "eval.md").read_text())
    for problem in report["problems"]:
        print(f"gra-mi eval: error: {problem}", file=sys.stderr)
    print(f"done: open {out / 'eval.md'}")
    return 2 if report["problems"] else 0


COMMANDS = {
    "demo": (DemoCommand, run_demo),
    "bench": (BenchCommand, run_bench),
    "eval": (EvalCommand, run_eval),
}
