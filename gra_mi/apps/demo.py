"""The main job: the pipeline as far as it exists, on a small preset, into a folder a person can open.

Stages: synthetic lightstage capture (path-traced ground truth under interleaved uniform and envmap lighting) →
envmap→LED energy check → material fit (per-texel albedo and roughness) → coarse one-bounce relighting with the
fitted maps under held-out envmaps and from held-out cameras, against the ground truth → RelightNet training and
its ablation → the video refiner (tiny WAN2.1-VACE on CPU: RelightNet renders → refined video, 17-frame windows
rolled over a held-out sequence) → a near-field point light → glTF export → plots, MP4 and report.md.

Finished files are kept: rerunning after an interruption resumes (capture images, fit checkpoint, renders).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gra_mi.apps.demo_report import demo_markdown
from gra_mi.apps.export import export_avatar
from gra_mi.capture.dataset import load_observation
from gra_mi.capture.synthetic import CaptureConfig, generate_capture
from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_write_text, auto_exposure, pyplot, read_exr, save_figure, to_srgb8, write_exr, write_mp4, write_png
from gra_mi.core.provenance import claim_output
from gra_mi.core.runtime import torch_device
from gra_mi.core.stamp import run_stamp
from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy
from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate
from gra_mi.render.composite import PlatformCompositor, PlatformConfig
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.transport import LightTransport
from gra_mi.stage.envmap import direction_to_uv, envmap_to_leds, load_envmap, stage_background_plate
from gra_mi.stage.scene import LightstageScene, composite_over

logger = logging.getLogger(__name__)


@dataclass(kw_only=True, frozen=True)
class DemoPreset:
    name: str
    capture: str  # capture preset
    renderer: str  # ground truth renderer of the capture
    roughness_candidates: int
    fit_frame_step: int  # the fit sees every Nth training frame (RelightNet sees them all)
    relightnet_steps: int
    refiner_scale: float  # capture images → refiner frames (then padded to multiples of 16)
    refiner_zoom: float  # the refiner's subject crop, magnified over refiner_scale (1: a framed capture's subject)
    refiner_steps: int  # training steps of the tiny refiner
    refiner_euler_steps: int
    refiner_train_cameras: int | None  # the refiner's training sequences come from this many training cameras (None: all)
    lighting_spp: int  # samples per pixel of the path-traced truth under the reference environments
    platform_spp: int  # samples per pixel of the platform layer of the composites


@dataclass(kw_only=True, frozen=True)
class OlatDemoPreset:
    """The static-pose pipeline: an OLAT capture → a fit from the OLATs → RelightNet on lightings synthesized from the
    reflectance field → evaluation under held-out envmaps and OLATs (no video stages: one pose)."""

    name: str
    capture: str  # a static_olat capture preset
    renderer: str
    roughness_candidates: int
    relightnet_steps: int
    synthesized_lightings: int
    library_envmaps: int  # held-out procedural maps scored by `gra-mi eval`, truth from the OLATs


PRESETS = {
    "olat": OlatDemoPreset(
        name="olat", capture="olat_quick", renderer="path", roughness_candidates=11,
        relightnet_steps=1600, synthesized_lightings=1024, library_envmaps=8,
    ),
    "tiny": DemoPreset(
        name="tiny", capture="tiny", renderer="onebounce", roughness_candidates=5, fit_frame_step=1, relightnet_steps=20,
        refiner_scale=0.25, refiner_zoom=4.0, refiner_steps=20, refiner_euler_steps=4, refiner_train_cameras=None,
        lighting_spp=16, platform_spp=4,
    ),
    "small": DemoPreset(
        name="small", capture="small", renderer="path", roughness_candidates=11, fit_frame_step=3, relightnet_steps=1000,
        refiner_scale=1.0, refiner_zoom=1.0, refiner_steps=30, refiner_euler_steps=10, refiner_train_cameras=3,
        lighting_spp=256, platform_spp=32,
    ),
}  # fmt: skip


def _timed(timings: dict, name: str):
    class _Timer:
        def __enter__(self):
            self.t = time.perf_counter()

        def __exit__(self, *exc):
            timings[name] = time.perf_counter() - self.t

    return _Timer()


# --------------------------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------------------------


def plot_rig(stage, path: Path) -> None:

    plt = pyplot()

    fig = plt.figure(figsize=(6, 6))
    ax = fig.add_subplot(projection="3d")
    p = stage.led_positions
    ax.scatter(p[:, 0], p[:, 2], p[:, 1], s=6, c="orange", label=f"{stage.num_leds} LEDs")
    c = np.stack([cam.position for cam in stage.cameras])
    ax.scatter(c[:, 0], c[:, 2], c[:, 1], s=30, marker="^", c="tab:blue", label=f"{len(stage.cameras)} cameras")
    for cam in stage.cameras:
        f = cam.rotation[:, 2] * 0.3
        ax.plot(
            [cam.position[0], cam.position[0] + f[0]],
            [cam.position[2], cam.position[2] + f[2]],
            [cam.position[1], cam.position[1] + f[1]],
            c="tab:blue",
            lw=0.8,
        )
    ax.set_xlabel("x (m)")
    ax.set_ylabel("z (m)")
    ax.set_zlabel("y, up (m)")
    ax.legend(loc="upper left")
    ax.set_title("Lightstage rig")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def plot_led_mapping(envmap: np.ndarray, stage, drive: np.ndarray, path: Path, title: str) -> None:
    """The envmap with each LED drawn at its (u, v), coloured by its drive: shows the convention at a glance."""

    plt = pyplot()

    u, v = direction_to_uv(stage.led_directions())
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.4))
    axes[0].imshow(to_srgb8(envmap, auto_exposure(envmap)), extent=(0, 1, 1, 0))
    axes[0].set_title(f"{title}: envmap")
    scaled = to_srgb8(drive[None], 1.0 / max(float(np.percentile(drive, 99)), 1e-9))[0] / 255.0
    axes[1].set_facecolor("black")
    axes[1].scatter(u, v, c=scaled[:, :3], s=28, edgecolors="0.4", linewidths=0.3)
    axes[1].set_xlim(0, 1)
    axes[1].set_ylim(1, 0)
    axes[1].set_title("LED drive values at their lat-long positions")
    for ax in axes:
        ax.set_xlabel("u  (0.25 = +X, 0.5 = +Z)")
        ax.set_ylabel("v  (0 = up)")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def contact_sheet(images: list[list[np.ndarray]]) -> np.ndarray:
    rows = [np.concatenate(row, axis=1) for row in images]
    return np.concatenate(rows, axis=0)


# --------------------------------------------------------------------------------------------------------------


def run_demo(preset_name: str, out: Path, overwrite: bool = False, transport: LightTransport | None = None) -> Path:
    """Run every stage on ``preset_name`` into ``out`` with ``transport``'s bounces of light in every stage that shades
    texels; write demo.json (the stages' records) and report.md from it."""
    transport = transport or LightTransport()
    transport.validate(fixed=True)

    if preset_name not in PRESETS:
        raise GraMiParameterError("preset", f"unknown preset '{preset_name}', expected one of {sorted(PRESETS)}")
    preset = PRESETS[preset_name]
    claimed = {"preset": preset_name} | ({"transport": asdict(transport)} if transport != LightTransport() else {})
    out = claim_output(out, "demo", {}, claimed, overwrite=overwrite)  # a rerun resumes its own run only
    (out / "plots").mkdir(exist_ok=True)
    runtime = {"variant": ensure_mitsuba(), "torch_device": torch_device()}
    record = {"stamp": run_stamp(preset=preset_name, variant=runtime["variant"]), "preset": asdict(preset), "runtime": runtime}
    record["transport"] = asdict(transport)
    record["timings"] = {}
    atomic_write_text(out / "config.json", json.dumps({"preset": record["preset"], **record["runtime"]}, indent=1) + "\n")
    timings = record["timings"]
    with _timed(timings, f"capture ({preset.capture}, {preset.renderer} ground truth)"):
        capture, ls = _capture_stage(preset, out, record)
    if isinstance(preset, OlatDemoPreset):
        return _olat_demo(preset, capture, ls, out, record, transport)
    with _timed(timings, "envmap→LED"):
        record["led_mappings"] = _led_mapping_plots(capture, ls.stage, out)
    fit_result = _learn_stages(preset, capture, out, record, transport)
    _render_stages(preset, capture, ls, fit_result, out, record, transport)

    with _timed(timings, "evaluation (gra-mi eval)"):
        eval_config = EvalConfig(composite=True, platform=PlatformConfig(spp=preset.platform_spp), transport=transport)
        record["eval"] = evaluate(EvalInputs.from_run(out), out / "eval", eval_config)
    return _finish(out, record)


def _olat_demo(preset: OlatDemoPreset, capture, ls, out: Path, record: dict, transport: LightTransport) -> Path:
    """Fit from the OLATs, RelightNet on synthesized lightings, the relit contact sheet, `gra-mi eval` (the capture's
    held-out envmaps and OLATs, and library maps whose truth is the OLAT sum), glTF; demo.json and report.md."""
    from gra_mi.fit.materials import FitConfig, run_fit
    from gra_mi.relightnet.train import TrainConfig, train_relightnet
    from gra_mi.render.relighter import Relighter

    timings = record["timings"]
    with _timed(timings, "material fit from the OLATs"):
        config = FitConfig(roughness_candidates=preset.roughness_candidates, transport=transport)  # OLATs: no brightness calibration
        fit_result, _ = run_fit(capture.folder, out / "fit", config)
    record["fit"] = json.loads((out / "fit" / "fit.json").read_text())
    with _timed(timings, f"RelightNet training ({preset.relightnet_steps} steps, {preset.synthesized_lightings} synthesized lightings)"):
        train = TrainConfig(steps=preset.relightnet_steps, synthesized_lightings=preset.synthesized_lightings, transport=transport)
        train_relightnet(capture.folder, out / "fit", out / "relightnet", train)
    record["relightnet"] = json.loads((out / "relightnet" / "validation.json").read_text())
    cache = out / "cache" / "visibility"
    relighter = Relighter(ls, albedo=fit_result.albedo, roughness=fit_result.roughness, cache_dir=cache, transport=transport)
    with _timed(timings, f"relight (fitted maps, {transport.label})"):
        relit_contact_sheet(capture, relighter, [f for f in capture.frames if f.split == "test"], out)
    with _timed(timings, "evaluation (gra-mi eval; library maps' truth from the OLATs)"):
        eval_config = EvalConfig(library_envmaps=preset.library_envmaps, transport=transport)
        record["eval"] = evaluate(EvalInputs.from_run(out), out / "eval", eval_config)
    record["export"] = _export(out, ls, fit_result, record)
    return _finish(out, record)


def _capture_stage(preset: DemoPreset | OlatDemoPreset, out: Path, record: dict):
    """The synthetic capture; what the report says of its rig, subject and ground truth."""

    capture = generate_capture(out / "capture", CaptureConfig(preset=preset.capture, renderer=preset.renderer))
    ls = LightstageScene.load(capture.folder / "scene.xml")
    stage, seq = ls.stage, ls.sequence
    plot_rig(stage, out / "plots" / "rig.png")
    record["capture"] = {
        "rig": {"leds": stage.num_leds, "radius": stage.radius, "cameras": len(stage.cameras)}
        | {"width": stage.cameras[0].width, "height": stage.cameras[0].height},
        "eval_cameras": capture.eval_cameras,
        "subject": {"vertices": seq.num_vertices, "triangles": len(seq.faces), "frames": seq.num_frames}
        | {"clips": list(dict.fromkeys(seq.frame_labels))},
        "renderer": capture.renderer,
        "ground_truth": capture.ground_truth,
    }
    return capture, ls


def _led_mapping_plots(capture, stage, out: Path) -> list[str]:
    """A training and a held-out envmap with their LED drive values (the convention at a glance)."""

    train_env = next(f.envmap for f in capture.frames if f.kind == "envmap" and f.split == "train")
    test_env = next(f.envmap for f in capture.frames if f.split == "test" and f.envmap is not None)
    for path in (train_env, test_env):
        env = load_envmap(capture.folder / path)
        plot_led_mapping(env, stage, envmap_to_leds(env, stage).drive, out / "plots" / f"leds_{Path(path).stem}.png", Path(path).stem)
    return [Path(p).stem for p in (train_env, test_env)]


def _learn_stages(preset: DemoPreset, capture, out: Path, record: dict, transport: LightTransport):
    """Material fit → RelightNet → video refiner; their records. Returns the fit."""
    from gra_mi.fit.materials import FitConfig, run_fit
    from gra_mi.relightnet.train import TrainConfig, train_relightnet

    timings = record["timings"]
    with _timed(timings, "material fit"):
        fit_config = FitConfig(roughness_candidates=preset.roughness_candidates, frame_step=preset.fit_frame_step, transport=transport)
        fit_result, _ = run_fit(capture.folder, out / "fit", fit_config)
    record["fit"] = json.loads((out / "fit" / "fit.json").read_text())
    with _timed(timings, f"RelightNet training ({preset.relightnet_steps} steps) + validation"):
        train_relightnet(capture.folder, out / "fit", out / "relightnet", TrainConfig(steps=preset.relightnet_steps, transport=transport))
    record["relightnet"] = json.loads((out / "relightnet" / "validation.json").read_text())
    record["refiner"] = _refiner_stage(preset, capture, out, timings)
    return fit_result


def _render_stages(preset: DemoPreset, capture, ls, fit_result, out: Path, record: dict, transport: LightTransport) -> None:
    """Relit contact sheet, lighting models against the path-traced truth, a point light, composites, glTF."""
    from gra_mi.render.relighter import Relighter

    timings = record["timings"]
    cache = out / "cache" / "visibility"
    relighter = Relighter(ls, albedo=fit_result.albedo, roughness=fit_result.roughness, cache_dir=cache, transport=transport)
    test_frames = [f for f in capture.frames if f.split == "test"]
    with _timed(timings, f"relight (fitted maps, {transport.label})"):
        relit_contact_sheet(capture, relighter, test_frames, out)
    with _timed(timings, "lighting models vs path-traced truth (reference maps)"):
        config = EnvmapAccuracyConfig(spp=preset.lighting_spp, transport=transport)
        envmap_accuracy(capture.folder, out / "fit", out / "lighting", relightnet_dir=out / "relightnet", config=config)
    record["lighting"] = json.loads((out / "lighting" / "accuracy.json").read_text())
    with _timed(timings, "near-field point light"):
        _point_light(capture, relighter, test_frames[0].mesh_frame, out)
    with _timed(timings, "composites on a platform (RelightNet, held-out camera)"):
        record["video"] = _composite_video(preset, capture, relighter, test_frames, out)
    record["export"] = _export(out, ls, fit_result, record)


def _finish(out: Path, record: dict) -> Path:
    """demo.json and report.md, with the outputs this machine could not make (no ffmpeg, no usd-core) named."""
    from gra_mi.core.io import PREVIEWS_NOT_MADE

    not_made = record.setdefault("not_made", {})
    not_made |= {str(Path(path).relative_to(out)): why for path, why in PREVIEWS_NOT_MADE.items() if Path(path).is_relative_to(out)}
    for name, why in not_made.items():
        logger.warning("not made: %s (%s)", name, why)
    atomic_write_text(out / "demo.json", json.dumps(record, indent=1, default=float) + "\n")
    atomic_write_text(out / "report.md", demo_markdown(record))
    return out / "report.md"


def _export(out: Path, ls, fit_result, record: dict) -> dict[str, str]:
    """The avatar as USD (with the rig's cameras) and glTF, each with its validator's verdict. Without usd-core (a
    machine that could not install it) the USD file is named in ``record["not_made"]`` and the run goes on."""
    verdicts = {}
    with _timed(record["timings"], "export (USD + glTF, validated)"):
        for name, rig in (("avatar.usdz", ls.stage), ("avatar.glb", None)):
            try:
                report = export_avatar(out / name, ls.sequence, fit_result.albedo, fit_result.roughness, rig=rig)
            except ModuleNotFoundError as missing:
                if (missing.name or "").split(".")[0] != "pxr":
                    raise
                record.setdefault("not_made", {})[name] = "no usd-core (pip install usd-core)"
                continue
            verdicts[name] = report.summary()
            if report.errors:
                raise RuntimeError(f"{report.summary()}: {report.errors[:3]}")
    return verdicts


def _point_light(capture, relighter, frame: int, out: Path) -> None:
    from gra_mi.render.point_light import PointLight, conditioning_envmap, conditioning_pattern

    stage = relighter.ls.stage
    light = PointLight(stage.center + np.array([0.45, 0.3, 0.35]), 1.5)
    image = relighter.render(frame, capture.train_cameras[0], np.zeros((stage.num_leds, 3)), light).image
    write_exr(out / "renders" / "point_light.exr", image)
    write_png(out / "point_light.png", image, exposure=None)
    conditioning = conditioning_envmap(stage, conditioning_pattern(stage, relighter.ls.scene, light))
    write_png(out / "point_light_conditioning.png", conditioning, exposure=None)


def _composite_video(preset: DemoPreset, capture, relighter, test_frames, out: Path) -> str:
    """The held-out camera through the first environment-lit test sequence: RelightNet's render on a platform with
    the subject's shadow (path-traced under the same envmap) over the envmap's background plate. Returns its path."""
    from gra_mi.relightnet.infer import render_view
    from gra_mi.relightnet.model import RelightNet

    stage, seq = relighter.ls.stage, relighter.ls.sequence
    net = RelightNet.load(out / "relightnet", torch_device())
    cam = stage.camera(capture.eval_cameras[0])
    compositor = PlatformCompositor(seq, PlatformConfig(spp=preset.platform_spp))
    frames = []
    lit = [f for f in test_frames if f.envmap is not None]  # an OLAT test sequence has no environment to stand in
    for entry in [f for f in lit if f.sequence == lit[0].sequence]:
        env = load_envmap(capture.folder / entry.envmap)
        image = render_view(relighter, net, entry.mesh_frame, cam.name, capture.lighting(stage, entry)).image
        frames.append(compositor(image, entry.mesh_frame, cam, env, envmap_to_leds(env, stage).scale, entry.envmap))
    exposure = 0.8 / max(float(np.percentile(frames[0], 99)), 1e-6)
    write_png(out / "composite.png", frames[len(frames) // 2], exposure=exposure)
    video = f"videos/{cam.name}_test.mp4"
    write_mp4(out / video, frames, fps=seq.fps / 2, exposure=exposure)
    return video


def relit_contact_sheet(capture, relighter, test_frames, out: Path) -> None:
    """One-bounce renders with the fitted maps (renders/, EXR) of two held-out-lighting frames from a training and a
    held-out camera, next to the ground truth over the background plate. Pictures only: `gra-mi eval` scores them."""

    stage = relighter.ls.stage
    lit = [f for f in test_frames if f.envmap is not None]  # shown over their environment's background plate
    rows = []
    for entry in (lit[0], lit[len(lit) // 2]):
        for cam_name in (capture.train_cameras[0], capture.eval_cameras[0]):
            exr = out / "renders" / cam_name / f"frame_{entry.frame:04d}.exr"
            image = read_exr(exr) if exr.is_file() else relighter.render(entry.mesh_frame, cam_name, capture.lighting(stage, entry)).image
            write_exr(exr, image)
            plate = stage_background_plate(load_envmap(capture.folder / entry.envmap), stage.camera(cam_name), stage)
            rows.append([composite_over(load_observation(capture, cam_name, entry.frame), plate), composite_over(image, plate)])
    write_png(out / "contact_truth_vs_relit.png", contact_sheet(rows), exposure=None)


def _refiner_stage(preset: DemoPreset, capture, out: Path, timings: dict) -> dict:
    """RelightNet renders → refiner sequences → train the tiny refiner → roll it over a held-out sequence."""
    from gra_mi.refiner.data import CaptureSequencesConfig, dataset_from_capture
    from gra_mi.refiner.dataset import RefinerDataset
    from gra_mi.refiner.deflicker import DeflickerConfig
    from gra_mi.refiner.infer import refine_to_folder
    from gra_mi.refiner.train import RefinerTrainConfig, train_refiner

    data_dir, model_dir = out / "refiner" / "data", out / "refiner" / "model"
    with _timed(timings, "refiner sequences (RelightNet renders)"):
        if (data_dir / "dataset.json").is_file():
            dataset = RefinerDataset(data_dir)
        else:
            dataset = dataset_from_capture(
                capture.folder,
                out / "fit",
                data_dir,
                relightnet_dir=out / "relightnet",
                config=CaptureSequencesConfig(
                    scale=preset.refiner_scale, zoom=preset.refiner_zoom, train_cameras=preset.refiner_train_cameras
                ),
                cache_dir=out / "cache" / "visibility",
            )
    with _timed(timings, f"video refiner training (tiny, {preset.refiner_steps} steps)"):
        if not (model_dir / "refiner.json").is_file():
            train_config = RefinerTrainConfig(steps=preset.refiner_steps, lr=2e-3, selection_steps=preset.refiner_euler_steps)
            train_refiner(data_dir, model_dir, train_config)
    sequences = dataset.names("test")
    with _timed(timings, f"video refiner rollout + flicker correction ({len(sequences)} held-out sequences)"):
        summaries = []
        for name in sequences:
            folder = out / "refiner" / "refined" / name
            done = folder / "refine.json"
            if done.is_file() and (folder / "deflickered" / "deflickered.mp4").is_file():  # finished before an interruption
                summaries.append(json.loads(done.read_text()))
                continue
            summaries.append(
                refine_to_folder(model_dir, data_dir, name, folder, steps=preset.refiner_euler_steps, deflicker=DeflickerConfig())
            )
    summary = summaries[0]
    summary["train"] = json.loads((model_dir / "train.json").read_text())
    if summary["train"]["mix"]["chosen"] < 1:  # what the refiner itself makes of the held-out sequence, for the report
        folder = out / "refiner" / "own_output" / summary["sequence"]
        with _timed(timings, "video refiner rollout at mix 1 (its own output, for the report)"):
            if not (folder / "refine.json").is_file():
                refine_to_folder(
                    model_dir, data_dir, summary["sequence"], folder, steps=preset.refiner_euler_steps, mix=1.0, vae_round_trip_psnr=False
                )
        summary["psnr_own_output"] = json.loads((folder / "refine.json").read_text())["psnr_refined"]
    summary["size"] = f"{dataset.height}×{dataset.width}"
    return summary
