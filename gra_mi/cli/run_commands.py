"""Commands over a whole run: ``demo``, ``bench``, ``eval``, ``view``."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

from gra_mi.cli.options import CommandConfig, Restartable
from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.guard import names_of
from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate
from gra_mi.render.atlas import MIN_RESOLUTION
from gra_mi.render.transport import LightTransport
from gra_mi.stage.envmap import EnvmapOptions


@dataclass(kw_only=True)
class DemoCommand(Restartable):
    preset: str = field(default="small", metadata=option(choices=("tiny", "small", "olat")))
    """tiny: procedural subject, seconds (CI). small: the anny body on the default 331-LED rig, minutes on 2 cores.
    olat: a static pose lit by each of 331 LEDs (a reflectance field), fitted from the OLATs, RelightNet trained on
    lightings synthesized from them, scored under held-out envmaps and OLATs."""
    out: Path = Path("outputs/demo")
    """Output folder (renders, plots, report.md)."""
    transport: LightTransport = field(default_factory=LightTransport)


def run_demo(c: DemoCommand) -> None:
    from gra_mi.apps.demo import run_demo as demo

    print(f"done: open {demo(c.preset, c.out, c.overwrite, c.transport)}")


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

    def output_folder(self) -> Path:
        return self.out or (self.run / "eval" if self.run is not None else Path("outputs/eval"))


def run_eval(c: EvalCommand) -> int:

    inputs = EvalInputs.from_run(c.run) if c.run is not None else EvalInputs(c.capture)
    for name in ("capture", "fit", "relightnet", "refiner_data"):
        if getattr(c, name) is not None:
            setattr(inputs, name, getattr(c, name))
            inputs.explicit.add(name)
    if c.refined:
        inputs.refined = list(c.refined)
        inputs.explicit.add("refined")
    out = c.output_folder()
    report = evaluate(inputs, out, c.eval)
    print((out / "eval.md").read_text())
    for problem in report["problems"]:
        print(f"gra-mi eval: error: {problem}", file=sys.stderr)
    print(f"done: open {out / 'eval.md'}")
    return 2 if report["problems"] else 0


@dataclass(kw_only=True)
class ViewCommand(CommandConfig):
    run: Path | None = field(default=None, metadata=option(positional=True))
    """A folder `gra-mi demo` wrote (capture/, fit/, relightnet/): the subject with its fitted maps, RelightNet where
    its weights exist, the capture's images as ground truth and its envmaps."""
    capture: Path | None = None
    """A capture folder instead of a run (with --fit and --relightnet as you have them)."""
    fit: Path | None = None
    """Fit folder (albedo.exr, roughness.exr, confidence.exr). Without one the subject shows its own colours."""
    relightnet: Path | None = None
    """Trained RelightNet folder: adds '+ RelightNet' to the page's stages."""
    scene: Path | None = None
    """A lightstage scene without a capture (e.g. scenes/tiny_lightstage.xml)."""
    envmap: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """Your own HDR map (OpenEXR or .hdr) to offer in the page, next to the capture's and the reference maps
    (repeatable). The page offers only maps named here: it reads no path a browser sends."""
    host: str = "127.0.0.1"
    """Address to listen on. The default answers this machine only; reach a remote server through an SSH tunnel
    (ssh -L 8080:localhost:8080 SERVER). 0.0.0.0 opens it to the network."""
    port: int = 8080
    """Port to listen on."""
    max_size: int = 512
    """Longest side, in pixels, of the images the server renders for the browser."""
    uv_resolution: int = 256
    """UV resolution without a fit (a fit sets its own)."""
    vis_cache: Path | None = None
    """Folder to keep per-frame visibility in across runs. Default: memory only."""
    seconds: float | None = None
    """Stop after this many seconds (scripts, tests). Default: run until Ctrl-C."""
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)
    transport: LightTransport = field(default_factory=LightTransport)
    """The bounces of light the page starts with (it has a control for them)."""

    def validate(self) -> None:
        super().validate()
        if sum(x is not None for x in (self.run, self.capture, self.scene)) != 1:
            raise GraMiParameterError("run", "give one of: a run folder, --capture, or --scene")
        if self.run is not None and (given := [n for n in ("fit", "relightnet") if getattr(self, n) is not None]):
            raise GraMiParameterError(given[0], "a run folder brings its own fit/ and relightnet/: give --capture with it instead")
        if not 0 < self.port < 65536:
            raise GraMiParameterError("port", f"must be in 1..65535, got {self.port}")
        if self.seconds is not None:
            require_positive({"seconds": self.seconds})
        names_of(self.envmap, "envmap")  # the page offers maps by name
        if self.max_size < 16:
            raise GraMiParameterError("max_size", f"must be >= 16, got {self.max_size}")
        if self.uv_resolution < MIN_RESOLUTION:
            raise GraMiParameterError("uv_resolution", f"must be >= {MIN_RESOLUTION}, got {self.uv_resolution}")


def run_view(c: ViewCommand) -> None:
    import socket
    import time

    from gra_mi.apps.viewer import ViewerSession, ViewSources
    from gra_mi.apps.viewer_page import ViewerPage
    from gra_mi.core.runtime import torch_device

    with socket.socket() as probe:  # say a busy port plainly, before loading anything
        try:
            probe.bind((c.host, c.port))
        except socket.gaierror as exc:  # before OSError: it is one
            raise GraMiParameterError("host", f"'{c.host}' is not an address of this machine ({exc.strerror})") from None
        except OSError as exc:
            raise GraMiParameterError("port", f"cannot listen on {c.host}:{c.port} ({exc.strerror}): give another --port") from None
    extra = {"envmaps": c.envmap, "vis_cache": c.vis_cache, "uv_resolution": c.uv_resolution}
    named = frozenset(name for name in ("fit", "relightnet") if getattr(c, name) is not None)
    if c.run is not None:
        sources = ViewSources.of_run(c.run, **extra)
    elif c.capture is not None:
        if not (c.capture / "scene.xml").is_file():
            raise GraMiInputError(c.capture, "not a capture folder: no scene.xml")
        sources = ViewSources(c.capture / "scene.xml", c.capture, c.fit, c.relightnet, **extra, named=named)
    else:
        sources = ViewSources(c.scene, None, c.fit, c.relightnet, **extra, named=named)
    session = ViewerSession(sources, c.envmaps, str(torch_device()), c.transport)
    for path in c.envmap:  # the maps named here are checked now (the session loads a map when it is first chosen)
        session.envmap(path.stem)
    for notice in session.notices:
        print(f"gra-mi view: note: {notice}")
    page = ViewerPage(session, c.host, c.port, c.max_size)
    print(f"gra-mi view: open http://{'localhost' if c.host == '127.0.0.1' else c.host}:{c.port} (Ctrl-C stops)", flush=True)
    try:
        deadline = None if c.seconds is None else time.monotonic() + c.seconds
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        page.close()
