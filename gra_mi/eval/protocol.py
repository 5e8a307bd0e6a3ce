"""``gra-mi eval``: every stage of the pipeline scored the paper's way, in one table (paper Sec. 4, Table 2).

Protocol (docs/evaluation.md):

- **Splits**: the held-out cameras under the held-out lighting sequence (the capture's test frames), one split per
  camera. With the refiner's data, a split is its test sequence of that camera (the capture's clip looped to the
  sequence's length, ``capture_frames`` in dataset.json), so every stage sees the same frames.
- **Stages**: the microfacet render with the fitted maps, + RelightNet, + the video refiner, + flicker correction;
  each is scored only where its outputs exist, and the table says what was skipped and why.
- **Frames**: per-frame metrics on every 10th frame of each sequence (``every10``, the paper's protocol), or on the
  middle frame of each 17-frame refiner window (``window-middles``), or on all frames (``all``); the temporal
  metric and FVD use every frame.
- **One mask** per frame for every stage: the truth's alpha ≥ 0.5 (:func:`gra_mi.core.metrics.subject_mask`), at
  one resolution for all stages (the refiner's delivered frames when a video stage is scored, the capture's otherwise).
- **Metrics**: display PSNR and SSIM (:func:`gra_mi.core.metrics.compare`), LDR-ꟻLIP, the temporal error
  (:func:`gra_mi.core.metrics.temporal_error`), and LPIPS / FVD when their weights are given
  (:mod:`gra_mi.eval.perceptual`).

Outputs: ``eval.md`` (the table), ``eval.csv``, ``eval.json``, ``contact_<split>.png`` (truth | each stage, their ꟻLIP
maps below), ``videos/<split>.mp4`` (truth | each stage side by side; ``--composite``: over the environment on a
platform with the subject's shadow).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture, load_observation
from gra_mi.core.color import display_exposure, to_display
from gra_mi.core.config import option, options_need_switch
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import names_of
from gra_mi.core.io import atomic_write_text, read_exr, read_json
from gra_mi.core.limits import DRIVE_BYTES, require_memory
from gra_mi.core.metrics import compare, flip, subject_mask, temporal_error
from gra_mi.core.progress import progress
from gra_mi.core.runtime import torch_device
from gra_mi.eval.media import contact_sheet, write_videos
from gra_mi.eval.reflectance import TRUTH
from gra_mi.eval.report import STAGES, UNCHANGED, eval_csv, eval_markdown
from gra_mi.refiner.config import RefinerConfig
from gra_mi.render.composite import PLATFORM_FLAGS, PlatformConfig
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.transport import LightTransport
from gra_mi.stage.envmap import EnvmapOptions

logger = logging.getLogger(__name__)

FRAME_SELECTIONS = ("every10", "window-middles", "all")


@dataclass
class EvalConfig:
    frames: str = field(default="every10", metadata=option(choices=FRAME_SELECTIONS))
    """Frames scored per sequence: every10 (every 10th frame, the paper's protocol), window-middles (the middle frame
    of each 17-frame refiner window) or all. The temporal metric and FVD always use every frame."""
    scale: float | None = None
    """Capture images → evaluation resolution (default: the refiner data's scale when a video stage is scored, else 1)."""
    lpips_weights: list[str] | None = field(default=None, metadata=option(repeat=True))
    """LPIPS weights on disk: torchvision's alexnet-owt-7be5be79.pth and the lpips package's weights/v0.1/alex.pth
    (repeat the flag, or give their folder), or one lpips.LPIPS(net='alex') state dict. Never downloaded; none: no
    LPIPS column."""
    i3d_weights: str | None = None
    """TorchScript I3D (i3d_torchscript.pt, the usual FVD feature network) on disk; default none: no FVD column."""
    composite: bool = False
    """Also write the side-by-side videos over the environment on a platform with the subject's shadow."""
    platform: PlatformConfig = field(default_factory=PlatformConfig, metadata=option(renames=PLATFORM_FLAGS))
    """The platform of the composites (gra_mi.render.composite)."""
    envmap: list[Path] = field(default_factory=list, metadata=option(repeat=True))
    """A static OLAT capture: also score under this HDR map (repeatable), the truth the sum of the capture's OLATs
    under the map's LED drive (its reflectance field; docs/evaluation.md)."""
    library_envmaps: int = 0
    """A static OLAT capture: also score under this many held-out procedural maps (skies, rooms), truth from the OLATs."""
    envmaps: EnvmapOptions = field(default_factory=EnvmapOptions)
    transport: LightTransport = field(default_factory=LightTransport)

    def validate(self) -> None:
        self.transport.validate(fixed=True)
        if self.library_envmaps < 0:
            raise GraMiParameterError("library_envmaps", f"must be >= 0, got {self.library_envmaps}")
        require_memory("library_envmaps", self.library_envmaps * DRIVE_BYTES, f"{self.library_envmaps:,} library maps' LED drives")
        self.envmaps.validate()
        names_of(self.envmap, "envmap")  # the scores are keyed by the map's name
        if self.frames not in FRAME_SELECTIONS:
            raise GraMiParameterError("frames", f"expected one of {', '.join(FRAME_SELECTIONS)}, got '{self.frames}'")
        if self.scale is not None and not (0 < self.scale <= 1):
            raise GraMiParameterError("scale", f"must be in (0, 1], got {self.scale}")
        self.platform.validate()
        options_need_switch(self.platform, self.composite, "--composite")


@dataclass
class EvalInputs:
    """Where each stage's outputs are. ``explicit`` names the ones the user pointed to: a problem with one of those is
    an error (exit 2); a stage merely absent from a run folder is skipped and said so."""

    capture: Path
    fit: Path | None = None
    relightnet: Path | None = None
    refiner_data: Path | None = None
    refined: list[Path] = field(default_factory=list)
    explicit: set[str] = field(default_factory=set)

    @classmethod
    def from_run(cls, run: str | Path) -> EvalInputs:
        """The layout ``gra-mi demo`` writes: capture/, fit/, relightnet/, refiner/data/, refiner/refined/."""
        run = Path(run)
        if not run.is_dir():
            raise GraMiInputError(run, "run folder not found")
        refined = run / "refiner" / "refined"
        inputs = cls(run / "capture", run / "fit", run / "relightnet", run / "refiner" / "data", [refined] if refined.is_dir() else [])
        # A stage folder the run holds is one the user points to: if it cannot be scored, that is a problem (exit 2);
        # a stage the run never made is skipped and said so.
        present = {"fit": inputs.fit, "relightnet": inputs.relightnet, "refiner_data": inputs.refiner_data}
        inputs.explicit |= {name for name, folder in present.items() if folder.is_dir()}
        return inputs


def frame_selection(count: int, how: str) -> list[int]:
    """The sequence frames scored per frame (see :class:`EvalConfig`)."""
    if how == "all":
        return list(range(count))
    if how == "every10":
        return list(range(0, count, 10))
    from gra_mi.refiner.infer import window_starts

    window, handoff = RefinerConfig.window, RefinerConfig.handoff  # the refiner's own windows (their defaults)
    return [s + window // 2 for s in window_starts(count, window, handoff) if s + window // 2 < count]


def _downscale(image: np.ndarray, scale: float) -> np.ndarray:
    """Area-average downscale (the refiner data's own resampling), every channel."""
    if scale == 1.0:
        return np.asarray(image, np.float32)
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(image, np.float32)).permute(2, 0, 1)[None]
    return F.interpolate(t, scale_factor=scale, mode="area")[0].permute(1, 2, 0).numpy()


@dataclass
class Split:
    """One held-out camera under the held-out lighting: the capture frame of each sequence frame."""

    name: str
    camera: str
    capture_frames: list[int]  # negative: a lighting of ``lights`` (no capture frame; truth from the OLATs)
    refined_dir: Path | None = None
    lighting_set: bool = False  # one pose under many lightings (not a video): every frame is scored
    lights: dict[int, object] = field(default_factory=dict)  # frame id < 0 → FieldLighting
    missing: list[int] = field(default_factory=list)  # held-out frames the camera has no image of (left out)
    breaks: list[int] = field(default_factory=list)  # positions in capture_frames that follow such a gap
    truth_note: str = ""  # how a reflectance-field truth stands in for an OLAT image the camera lacks


def scored_frames(split: Split, how: str) -> list[int]:
    return list(range(len(split.capture_frames))) if split.lighting_set else frame_selection(len(split.capture_frames), how)


@dataclass
class StageResult:
    stage: str
    status: str = "done"  # or "skipped: why"
    splits: dict[str, dict] = field(default_factory=dict)  # split → metrics
    seconds_per_frame: float | None = None
    fvd: float | None = None
    fvd_clips: int = 0


def _refined_folders(paths: list[Path]) -> dict[str, Path]:
    """Sequence name → refined folder (a folder with refine.json, or a folder of such folders)."""

    found = {}
    for path in paths:
        candidates = (
            [path]
            if (path / "refine.json").is_file()
            else sorted(p for p in path.iterdir() if (p / "refine.json").is_file())
            if path.is_dir()
            else []
        )
        if not candidates:
            raise GraMiInputError(path, "--refined: no refine.json here or in its sub-folders (write one with `gra-mi refine`)")
        for folder in candidates:
            summary = read_json(folder / "refine.json")
            if "sequence" not in summary:
                raise GraMiInputError(folder / "refine.json", "missing field 'sequence'")
            found[summary["sequence"]] = folder
    return found


def _splits(capture, dataset, refined: dict[str, Path]) -> tuple[list[Split], dict[str, str]]:
    """The held-out cameras × the held-out lighting sequences, each without the frames its camera has no image of (a
    real capture's gaps); and the splits left with none (name → why)."""
    test = [f.frame for f in capture.frames if f.split == "test"]
    if not test or not capture.eval_cameras:
        what = "test frames" if not test else "held-out cameras (eval_cameras)"
        raise GraMiInputError(capture.folder / "capture.json", f"no {what}: nothing is held out to evaluate on")
    # The capture's held-out lighting sequences; the refiner's data plays them one after another per camera.
    sequences: dict[int, list[int]] = {}
    for f in capture.frames:
        if f.split == "test":
            sequences.setdefault(f.sequence, []).append(f.frame)
    splits, unscored = [], {}
    for cam in capture.eval_cameras:
        entry = None
        if dataset is not None:
            entry = next((s for s in dataset.meta["sequences"] if s.get("camera") == cam and s["split"] == "test"), None)
        if entry is not None:
            frames = entry.get("capture_frames") or [test[i % len(test)] for i in range(int(entry["frames"]))]
            splits.append(Split(entry["name"], cam, list(frames), refined.get(entry["name"])))
            continue
        static = len({f.mesh_frame for f in capture.frames}) == 1
        for k, frames in sequences.items():
            name = f"test_{cam}" if len(sequences) == 1 else f"test{k}_{cam}"
            present, missing, breaks = capture.frames_with_images(cam, frames)
            if not present:
                unscored[name] = f"camera {cam} has no image of any of its {len(frames)} frames (the import recorded them missing)"
                logger.warning("%s: not scored: %s", name, unscored[name])
                continue
            splits.append(Split(name, cam, present, lighting_set=static, missing=missing, breaks=breaks))
    if not splits:
        raise GraMiInputError(capture.folder / "capture.json", "no held-out camera has an image of the held-out lighting", field="frames")
    return splits, unscored


def _field_splits(capture, config: EvalConfig) -> tuple[list[Split], dict[str, str]]:
    """One split per held-out camera under the user's and the library's maps, truth from the reflectance field; and
    the cameras' splits left out for want of an OLAT image (name → why)."""
    from gra_mi.capture.reflectance import OlatIndex, static_pose
    from gra_mi.eval.reflectance import field_lightings
    from gra_mi.stage.lightstage import load_calibration

    if not (config.envmap or config.library_envmaps):
        return [], {}
    static_pose(capture)
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    lights = field_lightings(capture, stage, {p.stem: config.envmaps.load(p) for p in config.envmap}, config.library_envmaps)
    by_id = {-(k + 1): light for k, light in enumerate(lights)}
    index, incomplete, notes = OlatIndex.of(capture, stage), {}, {}
    for cam in capture.eval_cameras:  # a camera that lost an OLAT: its truth takes that LED's light from neighbours
        try:
            shares = index.light_from_neighbours(capture, cam, {light.name: light.intensities for light in lights})
        except GraMiInputError as exc:
            incomplete[cam] = str(exc)
            logger.warning("field_%s: not scored: %s", cam, exc)
            continue
        if shares:
            notes[cam] = (f"; the light of the LEDs whose OLAT image camera {cam} lacks (at most {100 * max(shares.values()):.2f} % "
                          "of a lighting's) from their neighbours' OLATs")  # fmt: skip
            logger.warning("field_%s: truth %s", cam, notes[cam][2:])
    splits = [Split(f"field_{c}", c, list(by_id), lighting_set=True, lights=by_id, truth_note=notes.get(c, ""))
              for c in capture.eval_cameras if c not in incomplete]  # fmt: skip
    return splits, {f"field_{cam}": why for cam, why in incomplete.items()}


def _perceptual_models(config: EvalConfig):
    """(LPIPS, I3D) from the weights the config names (None where not asked for)."""
    from gra_mi.eval.perceptual import load_i3d, load_lpips

    return (
        load_lpips(config.lpips_weights) if config.lpips_weights else None,
        load_i3d(config.i3d_weights) if config.i3d_weights else None,
    )


def evaluate(inputs: EvalInputs, out: str | Path, config: EvalConfig | None = None) -> dict:
    """Score every stage found in ``inputs`` on every split; write the table, contact sheets and videos under ``out``.
    Returns the eval.json content; its ``problems`` lists what the user pointed to that could not be evaluated."""

    config = config or EvalConfig()
    config.validate()
    lpips_model, i3d = _perceptual_models(config)  # a bad weights file stops here, before any work
    ensure_mitsuba()
    out = Path(out)
    capture = Capture.load(inputs.capture)
    status = _Status(inputs)
    relighter, model = _texture_stages(inputs, capture, out, status, config.transport)
    dataset, refined = _video_stages(inputs, status)
    splits, unscored = _splits(capture, dataset if refined else None, refined)
    field_splits, field_unscored = _field_splits(capture, config)
    splits, unscored = splits + field_splits, unscored | field_unscored
    scale = config.scale
    if scale is None:
        scale = float(dataset.meta.get("scale", dataset.crop[1] / capture_width(capture))) if refined else 1.0
    frames_of = _Frames(capture, relighter, model, scale)
    videos = {}
    for split in progress(splits, description="evaluate splits"):
        frames = frames_of.split(split, status)
        videos[split.name] = _score_split(split, frames, status.results, config, lpips_model, out)
    _settle(status.results, splits, videos, frames_of.seconds)
    if i3d is not None:
        _fvd(i3d, status.results, videos)
    composited = write_videos(out / "videos", videos, splits, capture, relighter, scale, config.platform if config.composite else None)
    report = {
        "protocol": _protocol(config, scale, splits, capture, videos)
        | {"lpips": lpips_model is not None, "fvd": i3d is not None, "composited": composited, "unscored": unscored},
        "stages": {s: asdict(r) for s, r in status.results.items()},
        "problems": status.problems,
    }
    atomic_write_text(out / "eval.json", json.dumps(report, indent=1, default=float) + "\n")
    atomic_write_text(out / "eval.csv", eval_csv(report))
    atomic_write_text(out / "eval.md", eval_markdown(report))
    return report


class _Status:
    """Each stage's result, and the problems: what the user pointed to that could not be scored (exit 2)."""

    def __init__(self, inputs: EvalInputs):
        self.inputs, self.problems = inputs, []
        self.results = {s: StageResult(s) for s in STAGES}

    def skip(self, stage: str, why: str, source: str | None = None) -> None:
        self.results[stage].status = f"skipped: {why}"
        if source is not None and source in self.inputs.explicit:
            self.problem(why)

    def problem(self, why: str) -> None:
        if why not in self.problems:
            self.problems.append(why)


def _texture_stages(inputs: EvalInputs, capture, out: Path, status: _Status, transport: LightTransport):
    """(the fitted relighter, RelightNet), None for a stage that cannot be scored (said in ``status``)."""
    from gra_mi.fit.fitted import fitted_relighter

    try:
        if inputs.fit is None or not (inputs.fit / "albedo.exr").is_file():
            raise GraMiInputError(inputs.fit or "--fit", "no albedo.exr (a fit folder from `gra-mi fit`)")
        _, relighter = fitted_relighter(capture.folder, inputs.fit, out / "cache", transport)
    except GraMiInputError as exc:
        for stage in ("microfacet", "RelightNet"):
            status.skip(stage, str(exc), "fit")
        return None, None
    try:
        from gra_mi.relightnet.model import RelightNet, check_input_transport

        if inputs.relightnet is None or not (inputs.relightnet / "relightnet.json").is_file():
            raise GraMiInputError(inputs.relightnet or "--relightnet", "no relightnet.json (a folder from `gra-mi train-relightnet`)")
        model = RelightNet.load(inputs.relightnet, torch_device())
        check_input_transport(model.config, transport, inputs.relightnet)
        return relighter, model
    except GraMiInputError as exc:
        status.skip("RelightNet", str(exc), "relightnet")
        return relighter, None


def _video_stages(inputs: EvalInputs, status: _Status):
    """(the refiner's dataset, sequence name → refined folder); refined sequences need the dataset for their frames."""
    from gra_mi.refiner.dataset import RefinerDataset

    dataset = None
    try:
        if inputs.refiner_data is not None and (inputs.refiner_data / "dataset.json").is_file():
            dataset = RefinerDataset(inputs.refiner_data)
        elif "refiner_data" in inputs.explicit:
            raise GraMiInputError(inputs.refiner_data, "no dataset.json (a folder from `gra-mi refiner-data`)")
        refined = _refined_folders(inputs.refined) if inputs.refined else {}
        if refined and dataset is None:
            raise GraMiInputError(
                next(iter(refined.values())), "refined frames need the refiner's data (--refiner-data) to know their frames"
            )
    except GraMiInputError as exc:
        status.skip("refined", str(exc))
        if {"refined", "refiner_data"} & inputs.explicit:
            status.problem(str(exc))
        return dataset, {}
    if not refined and status.results["refined"].status == "done":
        status.results["refined"].status = "skipped: no refined sequence (`gra-mi refine`)"
    return dataset, refined


class _Frames:
    """Every stage's frames of a split at the evaluation scale; truths and renders are cached across splits (the
    same view often appears in several) and each render is timed."""

    def __init__(self, capture, relighter, model, scale: float):
        self.capture, self.relighter, self.model, self.scale = capture, relighter, model, scale
        self.entries = {f.frame: f for f in capture.frames}
        self.pose = capture.frames[0].mesh_frame  # a static capture's one pose (the reflectance-field splits')
        self.field_truth = None  # made when a reflectance-field split is scored
        self.cache: dict[tuple, np.ndarray] = {}
        self.seconds: dict[str, list[float]] = {"microfacet": [], "RelightNet": []}

    def truths(self, split: Split) -> list[np.ndarray]:
        from gra_mi.eval.reflectance import FieldTruth

        for f in split.capture_frames:
            if ("truth", split.camera, f) not in self.cache:
                if f < 0:  # a lighting the capture never photographed: the sum of its OLATs
                    self.field_truth = self.field_truth or FieldTruth(self.capture)
                    image = self.field_truth(split.camera, split.lights[f])
                else:
                    image = load_observation(self.capture, split.camera, f)
                self.cache["truth", split.camera, f] = _downscale(image, self.scale)
        return [self.cache["truth", split.camera, f] for f in split.capture_frames]

    def lighting(self, split: Split, f: int) -> tuple[int, np.ndarray]:
        """(mesh frame, LED intensities) of a split's frame."""
        if f < 0:
            return self.pose, split.lights[f].intensities
        return self.entries[f].mesh_frame, self.capture.lighting(self.relighter.ls.stage, self.entries[f])

    def rendered(self, stage: str, split: Split) -> list[np.ndarray]:
        from gra_mi.relightnet.infer import render_view

        net = self.model if stage == "RelightNet" else None
        for f in split.capture_frames:
            if (stage, split.camera, f) not in self.cache:
                start = time.perf_counter()
                pose, lighting = self.lighting(split, f)
                image = render_view(self.relighter, net, pose, split.camera, lighting).image
                self.seconds[stage].append(time.perf_counter() - start)
                self.cache[stage, split.camera, f] = _downscale(image, self.scale)
        return [self.cache[stage, split.camera, f] for f in split.capture_frames]

    def split(self, split: Split, status: _Status) -> dict[str, list[np.ndarray]]:
        """Stage → frames (``truth`` too) of the stages that can be scored on this split."""
        results, truths = status.results, self.truths(split)
        frames = {"truth": truths}
        for stage in ("microfacet", "RelightNet"):
            if results[stage].status == "done":
                frames[stage] = self.rendered(stage, split)
        if split.refined_dir is None or results["refined"].status != "done":
            return frames
        for stage, folder in (("refined", split.refined_dir / "frames"), ("deflickered", split.refined_dir / "deflickered")):
            if stage == "deflickered" and not folder.is_dir():
                break
            loaded = _read_sequence(folder, len(truths), truths[0].shape[:2])
            if isinstance(loaded, str):  # unreadable: said, and the flicker correction of it is not scored
                results[stage].splits[split.name] = {"skipped": loaded}
                if stage == "deflickered" or "refined" in status.inputs.explicit:
                    status.problem(loaded)
                break
            frames[stage] = loaded
        return frames


def _score_split(split: Split, frames: dict, results: dict, config: EvalConfig, lpips_model, out: Path) -> dict:
    """Score each stage's frames of one split against the truth, write its contact sheet; what the videos need."""

    truths = frames["truth"]
    masks = [subject_mask(t) for t in truths]
    exposure = float(np.median([display_exposure(t, m) for t, m in zip(truths, masks, strict=True)]))
    scored, previous = scored_frames(split, config.frames), None
    for stage in (s for s in STAGES if s in frames):
        row = _score(frames[stage], truths, masks, exposure, scored, lpips_model, split.breaks)
        if previous is not None and same_frames(frames[stage], frames[previous]):
            row["unchanged_from"] = previous  # the stage delivered its input: its numbers are not its own result
        results[stage].splits[split.name] = row
        previous = stage
    contact_sheet(out / f"contact_{split.name}.png", frames, truths, masks, exposure, scored, split.name)
    heights = [subject_height(masks[f]) for f in scored]
    return {
        "frames": frames,
        "exposure": exposure,
        "coverage": frames.get("microfacet", frames.get("RelightNet")),
        "subject_pixels": [min(heights), max(heights)],
        "breaks": split.breaks,
    }


def subject_height(mask: np.ndarray) -> int:
    """How many pixel rows the subject spans (0 without a subject)."""
    rows = np.flatnonzero(np.asarray(mask).any(axis=1))
    return int(rows[-1] - rows[0] + 1) if rows.size else 0


def same_frames(frames: list[np.ndarray], inputs: list[np.ndarray]) -> bool:
    """Whether a stage's frames are its input's, to ``UNCHANGED`` (the refiner at mix 0, flicker correction of a
    video that does not flicker): then the table says so instead of showing its input's numbers as its own."""
    if len(frames) != len(inputs):
        return False
    for a, b in zip(frames, inputs, strict=True):
        a, b = np.asarray(a, np.float64)[..., :3], np.asarray(b, np.float64)[..., :3]
        if a.shape != b.shape or np.abs(a - b).mean() > UNCHANGED * max(np.abs(b).mean(), 1e-12):
            return False
    return True


def _settle(results: dict, splits: list[Split], videos: dict, seconds: dict[str, list[float]]) -> None:
    """Statuses that only the whole run shows, and each stage's seconds per frame."""

    if not any("deflickered" in v["frames"] for v in videos.values()) and not results["deflickered"].splits:
        results["deflickered"].status = "skipped: no deflickered frames (`gra-mi refine --deflicker` or `gra-mi deflicker`)"
    for stage in ("microfacet", "RelightNet"):
        if seconds[stage]:
            results[stage].seconds_per_frame = float(np.median(seconds[stage]))
    if results["refined"].status != "done":
        return
    for split in splits:
        if split.refined_dir is not None:
            fps = read_json(split.refined_dir / "refine.json").get("frames_per_second")
            results["refined"].seconds_per_frame = 1.0 / fps if fps else None
    if not any(split.name in results["refined"].splits for split in splits):
        results["refined"].status = "skipped: no refined sequence matches a held-out camera"


def _protocol(config: EvalConfig, scale: float, splits: list[Split], capture, videos: dict) -> dict:
    """What was scored, at what resolution, on which splits (eval.json's ``protocol``)."""
    return {
        "frames": config.frames,
        "scale": scale,
        "resolution": list(next(iter(videos.values()))["frames"]["truth"][0].shape[1::-1]),
        "splits": {
            s.name: {
                "camera": s.camera,
                "lighting": _lighting_said(capture, s),
                "truth": TRUTH + s.truth_note if s.lights else "the capture's images",
                "frames": len(s.capture_frames),
                "missing": s.missing,
                "scored": scored_frames(s, config.frames),
                "lighting_set": s.lighting_set,
                "subject_pixels": videos[s.name]["subject_pixels"],  # rows the subject spans, least and most, scored frames
            }
            for s in splits
        },
    }


def capture_width(capture) -> int:
    """Pixels across a capture image (refiner data written before ``scale`` was recorded give only their crop)."""

    return read_exr(capture.image_path(capture.eval_cameras[0], next(f.frame for f in capture.frames if f.split == "test"))).shape[1]


def _read_sequence(folder: Path, count: int, size: tuple[int, int]) -> list[np.ndarray] | str:
    """A refined sequence's frames ``frame_NNNN.exr``; a string says why they cannot be scored."""

    if not folder.is_dir():
        return f"{folder}: folder not found"
    images = []
    for i in range(count):
        path = folder / f"frame_{i:04d}.exr"
        if not path.is_file():
            return f"{path}: missing (the sequence has {count} frames)"
        try:
            image = read_exr(path)
        except GraMiInputError as exc:
            return str(exc)
        if image.shape[:2] != size:
            return f"{path}: {image.shape[1]}×{image.shape[0]} pixels, the truth at the evaluation scale is {size[1]}×{size[0]}"
        images.append(image)
    return images


def _score(images, truths, masks, exposure, scored: list[int], lpips_model, breaks: list[int]) -> dict:

    rows = []
    for i in scored:
        row = compare(images[i], truths[i], masks[i])
        row["flip"] = flip(images[i], truths[i], masks[i])
        if lpips_model is not None:
            from gra_mi.eval.perceptual import lpips_distance

            row["lpips"] = lpips_distance(lpips_model, images[i], truths[i], masks[i], display_exposure(truths[i], masks[i]))
        rows.append(row)
    result = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
    result["temporal"] = temporal_error(images, truths, masks, exposure, set(breaks))
    result["frames_scored"] = len(rows)
    return result


def _fvd(i3d, results: dict[str, StageResult], videos: dict) -> None:
    """FVD of each stage against the truth over all splits' clips of the refiner's window (non-overlapping, from 0)."""
    from gra_mi.eval.perceptual import frechet_distance, i3d_features

    window = RefinerConfig.window  # FVD's clips: the refiner's windows
    for stage in STAGES:
        real, fake = [], []
        for video in videos.values():
            frames, exposure = video["frames"], video["exposure"]
            if stage not in frames:
                continue
            for start in range(0, len(frames["truth"]) - window + 1, window):
                if any(start < b < start + window for b in video["breaks"]):
                    continue  # a clip across a gap in the capture is no video
                real.append(np.stack([to_display(f, exposure) for f in frames["truth"][start : start + window]]))
                fake.append(np.stack([to_display(f, exposure) for f in frames[stage][start : start + window]]))
        if len(real) >= 2:
            results[stage].fvd = frechet_distance(i3d_features(i3d, real), i3d_features(i3d, fake))
            results[stage].fvd_clips = len(real)


def _lighting_said(capture, split: Split) -> str:
    """The held-out lighting of a split in words: its envmaps' names, or its LED patterns' kind."""
    if split.lights:
        return ", ".join(light.name for light in split.lights.values())
    entries = {f.frame: f for f in capture.frames}
    return ", ".join(dict.fromkeys(entries[f].lighting_name for f in split.capture_frames))
