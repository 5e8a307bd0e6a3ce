"""The main job: the pipeline as far as it exists, on a small preset, into a folder a person can open.

Stages now: lightstage rig → procedural envmaps (train / held-out test) → animated subject → Mitsuba scene file →
envmap→LED integration (with its energy check) → coarse one-bounce relighting in UV space under training and test
envmaps and an OLAT pattern, composited over the camera's background plate, with Mitsuba's stock ``direct``
integrator beside it for comparison → plots, MP4 and report.md. Later stages (capture + fit, RelightNet, video
refiner) are listed in the report as not built yet.

Finished files are kept: rerunning after an interruption skips what exists.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.errors import GraMiInputError
from gra_mi.imageio import atomic_write_text, read_exr, write_exr, write_mp4, write_png

logger = logging.getLogger(__name__)


@dataclass
class DemoPreset:
    name: str
    num_leds: int
    num_cameras: int
    width: int
    height: int
    subject: str  # "anny" or "tiny"
    clips: list[str]
    frames_per_clip: int
    envmap_height: int
    num_train_envmaps: int
    num_test_envmaps: int
    cameras: list[int]  # which cameras to render
    frames: list[int]  # which frames to render for the contact sheets
    spp: int
    uv_resolution: int  # UV texture size of the one-bounce stage
    olat_led: int = 0
    stages_not_built: list[str] = field(
        default_factory=lambda: [
            "capture generator + material fit (issue 4)",
            "RelightNet (issue 6)",
            "video refiner (issue 7)",
        ]
    )


PRESETS = {
    "tiny": DemoPreset("tiny", 64, 4, 96, 64, "tiny", [], 8, 32, 2, 1, [0, 1], [0, 4], 16, 128),
    "small": DemoPreset(
        "small", 331, 40, 512, 270, "anny", ["walk", "arm_raise", "turn", "squat"], 8, 128, 4, 2, [0, 10, 25], [0, 9, 18, 27], 64, 512
    ),
}


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_led_mapping(envmap: np.ndarray, stage, drive: np.ndarray, path: Path, title: str) -> None:
    """The envmap with each LED drawn at its (u, v), coloured by its drive: shows the convention at a glance."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gra_mi.envmap import direction_to_uv
    from gra_mi.imageio import auto_exposure, to_srgb8

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
    fig.savefig(path, dpi=100)
    plt.close(fig)


def contact_sheet(images: list[list[np.ndarray]]) -> np.ndarray:
    rows = [np.concatenate(row, axis=1) for row in images]
    return np.concatenate(rows, axis=0)


# --------------------------------------------------------------------------------------------------------------


def energy_table(envmap: np.ndarray, stage) -> list[dict]:
    """Irradiance at the stage centre from the envmap and from its LEDs, for the six axis normals."""
    from gra_mi.envmap import envmap_irradiance, envmap_to_leds, led_irradiance

    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    lighting = envmap_to_leds(envmap, stage, normalize=False)
    e_env = envmap_irradiance(envmap, normals).mean(axis=1)
    e_led = led_irradiance(stage, lighting.radiant_intensity(stage), normals).mean(axis=1)
    names = ["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    return [
        {"normal": n, "envmap": float(a), "leds": float(b), "rel_error": float(abs(b - a) / max(a, 1e-12))}
        for n, a, b in zip(names, e_env, e_led, strict=True)
    ]


def run_demo(preset_name: str, out: Path, spp: int | None = None, variant: str | None = None) -> Path:
    from gra_mi.envmap import background_plate, envmap_to_leds, load_envmap
    from gra_mi.envmap_library import write_envmap_set
    from gra_mi.lightstage import default_lightstage, olat_pattern
    from gra_mi.progress import progress
    from gra_mi.scene import LightstageScene, composite_over, render, subject_scene_xml, write_rig
    from gra_mi.subject import save_sequence, tiny_subject
    from gra_mi.variant import choose_variant

    if preset_name not in PRESETS:
        raise GraMiInputError("--preset", f"unknown preset '{preset_name}', expected one of {sorted(PRESETS)}")
    preset = PRESETS[preset_name]
    if spp is not None:
        if spp < 1:
            raise GraMiInputError("--spp", f"must be >= 1, got {spp}")
        preset.spp = spp
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    chosen = choose_variant(variant)
    atomic_write_text(out / "config.json", json.dumps({"preset": asdict(preset), "variant": chosen}, indent=1) + "\n")

    # 1. Rig -----------------------------------------------------------------------------------------------
    with _timed(timings, "rig"):
        stage = default_lightstage(preset.num_leds, num_cameras=preset.num_cameras, width=preset.width, height=preset.height)
        write_rig(stage, out / "rig")
        (out / "plots").mkdir(exist_ok=True)
        plot_rig(stage, out / "plots" / "rig.png")

    # 2. Envmaps -------------------------------------------------------------------------------------------
    with _timed(timings, "envmaps"):
        train = write_envmap_set(out / "envmaps", "train", preset.num_train_envmaps, preset.envmap_height)
        test = write_envmap_set(out / "envmaps", "test", preset.num_test_envmaps, preset.envmap_height)

    # 3. Subject -------------------------------------------------------------------------------------------
    with _timed(timings, "subject"):
        subject_dir = out / "subject"
        if not (subject_dir / "sequence.npz").is_file():
            if preset.subject == "tiny":
                seq = tiny_subject(preset.frames_per_clip)
            else:
                from gra_mi.anny_body import anny_sequence

                seq = anny_sequence(preset.clips, preset.frames_per_clip)
            save_sequence(seq, subject_dir)
        atomic_write_text(out / "scene.xml", subject_scene_xml("rig", "subject", spp=preset.spp))
        ls = LightstageScene.load(out / "scene.xml")

    # 4. Lighting: envmaps onto LEDs, with the energy check ------------------------------------------------
    lights = {p.stem: load_envmap(p) for p in [train[0], test[0]]}
    energy = {}
    with _timed(timings, "envmap→LED"):
        for name, env in lights.items():
            energy[name] = energy_table(env, stage)
            plot_led_mapping(env, stage, envmap_to_leds(env, stage).drive, out / "plots" / f"leds_{name}.png", name)

    # 5. Coarse relighting: one-bounce GGX in UV space with cached per-LED visibility (issue 3) ---------------
    from gra_mi.plugins import register_plugins
    from gra_mi.relight import Relighter

    register_plugins()
    frames = [f for f in preset.frames if f < ls.sequence.num_frames]
    light_names = [*lights, f"olat{preset.olat_led:03d}"]

    def intensities_of(light: str) -> tuple[np.ndarray, float]:
        if light in lights:
            lighting = envmap_to_leds(lights[light], stage)
            return lighting.radiant_intensity(stage), lighting.scale
        return olat_pattern(stage, preset.olat_led) * stage.gains, 1.0

    def shown_image(light: str, cam, image: np.ndarray) -> np.ndarray:
        if light in lights:
            return composite_over(image, background_plate(lights[light], cam) * intensities_of(light)[1])
        return image[..., :3]

    relighter = Relighter(ls, preset.uv_resolution, cache_dir=out / "cache" / "visibility")
    jobs = [(f, light, c) for f in frames for light in light_names for c in preset.cameras]  # frame-major: one trace per frame
    sheets: dict[str, dict[int, list[np.ndarray]]] = {}
    with _timed(timings, "relight (one-bounce, UV space)"):
        for frame, light, cam_index in progress(jobs, description="relight"):
            cam = stage.cameras[cam_index]
            stem = out / "renders" / "onebounce" / light / f"{cam.name}_f{frame:04d}"
            if stem.with_suffix(".exr").is_file():
                image = read_exr(stem.with_suffix(".exr"))
            else:
                image = relighter.render(frame, cam.name, intensities_of(light)[0]).image
                write_exr(stem.with_suffix(".exr"), image)
            shown = shown_image(light, cam, image)
            write_png(stem.with_suffix(".png"), shown, exposure=0.9)
            sheets.setdefault(light, {}).setdefault(frame, []).append(shown)
        for light, rows in sheets.items():
            write_png(out / f"contact_{light}.png", contact_sheet(list(rows.values())), exposure=0.9)

    # 6. The generic peer: Mitsuba's direct integrator on the same scene file (first frame only) ------------
    comparison = []
    with _timed(timings, f"Mitsuba direct, {preset.spp} spp (frame {frames[0]} only)"):
        ls.set_frame(frames[0])
        for light in light_names:
            cam = stage.cameras[preset.cameras[0]]
            stem = out / "renders" / "direct" / light / f"{cam.name}_f{frames[0]:04d}"
            if stem.with_suffix(".exr").is_file():
                image = read_exr(stem.with_suffix(".exr"))
            else:
                ls.set_led_intensities(intensities_of(light)[0])
                image = render(ls, cam.name, "direct", preset.spp, seed=0)
                write_exr(stem.with_suffix(".exr"), image)
            write_png(stem.with_suffix(".png"), shown_image(light, cam, image), exposure=0.9)
            comparison.append([shown_image(light, cam, image), sheets[light][frames[0]][0]])
        write_png(out / "contact_direct_vs_onebounce.png", contact_sheet(comparison), exposure=0.9)

    # 7. Video: one camera through every frame under the held-out envmap ---------------------------------
    with _timed(timings, "video (one-bounce)"):
        video_light = test[0].stem
        cam = stage.cameras[preset.cameras[0]]
        video_path = out / "videos" / f"{cam.name}_{video_light}.mp4"
        if not video_path.is_file():
            intensities = intensities_of(video_light)[0]
            video = [
                shown_image(video_light, cam, relighter.render(frame, cam.name, intensities).image)
                for frame in progress(range(ls.sequence.num_frames), description="video")
            ]
            write_mp4(video_path, video, fps=ls.sequence.fps / 2, exposure=0.9)

    report = out / "report.md"
    atomic_write_text(report, _report(preset, chosen, stage, ls, energy, timings, sheets, video_path, out))
    return report


def _report(preset, variant, stage, ls, energy, timings, sheets, video_path, out) -> str:
    lines = [
        f"# gra-mi demo — preset `{preset.name}`",
        "",
        f"Mitsuba variant `{variant}`; {stage.num_leds} LEDs on a {stage.radius:.1f} m sphere, {len(stage.cameras)} cameras "
        f"({stage.cameras[0].width}×{stage.cameras[0].height}); subject: {ls.sequence.num_vertices} vertices, "
        f"{len(ls.sequence.faces)} triangles, {ls.sequence.num_frames} frames ({', '.join(dict.fromkeys(ls.sequence.frame_labels))}).",
        "",
        "## Pipeline stages",
        "",
        "| stage | status | time (s) |",
        "|---|---|---|",
    ]
    for name, seconds in timings.items():
        lines.append(f"| {name} | done | {seconds:.1f} |")
    for name in preset.stages_not_built:
        lines.append(f"| {name} | not built yet | – |")
    lines += ["", "Rig: ![rig](plots/rig.png)", "", "## Envmap → LED energy check (irradiance at the stage centre)", ""]
    for name, rows in energy.items():
        lines += [
            f"### {name}",
            "",
            f"![LED mapping](plots/leds_{name}.png)",
            "",
            "| normal | envmap | LEDs | rel. error |",
            "|---|---|---|---|",
        ]
        lines += [f"| {r['normal']} | {r['envmap']:.4g} | {r['leds']:.4g} | {100 * r['rel_error']:.2f} % |" for r in rows]
        lines.append("")
    lines += [
        "## Coarse relighting (one-bounce GGX, per-LED visibility, UV space)",
        "",
        "Composited over each camera's background plate. Rows: frames; columns: cameras. Material: the subject's base",
        "colours baked to UV as albedo, roughness 0.5 (fitted maps arrive with issue 4).",
        "",
    ]
    for light in sheets:
        lines += [f"### {light}", "", f"![{light}](contact_{light}.png)", ""]
    lines += [
        "### Mitsuba `direct` (left, the scene file's diffuse material, Monte Carlo) vs gra-mi one-bounce (right)",
        "",
        "![direct vs one-bounce](contact_direct_vs_onebounce.png)",
        "",
    ]
    lines += [
        f"Video: [{video_path.name}]({video_path.relative_to(out)})",
        "",
        "Data: `renders/{onebounce,direct}/*/*.exr` (linear RGBA), `envmaps/*/*.exr`, `subject/`, `rig/calibration.json`, `scene.xml` (loads in plain Mitsuba).",
        "",
    ]
    return "\n".join(lines)
