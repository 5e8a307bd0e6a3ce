"""``gra-mi import``: the path every source format shares, from a :class:`Source` to a capture in the layout every
stage reads (docs/data-format.md), in gra-mi's world frame, with an import report a user reads first.

One module per source format reads its files into a :class:`Source` (:mod:`~gra_mi.capture.humanolat`,
:mod:`~gra_mi.capture.transforms`, :mod:`~gra_mi.capture.easymocap`, :mod:`~gra_mi.capture.colmap`, with the files they share in
:mod:`~gra_mi.capture.source_files`); the format's quirks stay there. Then, here, for every format:
:meth:`Source.check` (what gra-mi's readers would refuse, named against the source's files) → the frame
(:func:`world_frame`: units to metres, the up axis, the LED sphere's centre, the floor) → the mesh reprojected over
every camera's mask (what spoils it, or a convention mistake, stops here, named) → written into a staging folder (rig,
subject, scene, patterns, images streamed one at a time, capture.json, import_report.{md,json}) → loaded back by
gra-mi's own readers → published by rename (:func:`import_capture`).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture
from gra_mi.capture.import_report import write_report
from gra_mi.capture.lens import held_fraction
from gra_mi.capture.mask_fit import check_images_fit_masks
from gra_mi.capture.olat_drive import apply_solved_drives, plot_solved_drives
from gra_mi.capture.placement import (
    CameraPlan,
    SubjectPlan,
    WorldFrame,
    build_stage,
    mask_at_source,
    plan_camera,
    plan_subject,
    resample_image,
    world_frame,
)
from gra_mi.capture.reprojection import frame_mask, reprojection_checks
from gra_mi.capture.scene_stage import write_set
from gra_mi.capture.source import ImportConfig, Source
from gra_mi.capture.source_files import (
    MIN_RELATIVE_GAIN,
    exif_orientation,
    image_size,
    orientation_hint,
    read_image,
    resample_columns,
    write_led_gains,
    write_mask,
)
from gra_mi.core.config import changed_options
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import staging_folder
from gra_mi.core.io import atomic_write_text, write_exr
from gra_mi.core.limits import MEMORY_SHARE, machine_memory, require_memory, require_memory_for
from gra_mi.core.progress import thread_count, threaded
from gra_mi.core.provenance import PROVENANCE, claim_output, release_folder, run_differences, run_record
from gra_mi.core.shard import Shard
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.lightstage import Lightstage, load_pattern, olat_pattern, uniform_pattern
from gra_mi.stage.scene import subject_scene_xml, write_rig

logger = logging.getLogger(__name__)
IMAGE_BYTES_PER_PIXEL = 4 * 4 * 8  # RGBA float32: the decoded source, its resampling and mask, the written EXR
LENS_BYTES_PER_PIXEL = 256  # of a source image, undistorted: its maps (kept for two cameras), samples and weights


def check_images_present(source: Source, plans: list[CameraPlan], skip: bool) -> dict[int, list[str]]:
    """Every camera's image of every frame, of the camera's size; with ``skip``, the gaps (frame key → cameras)."""
    missing: dict[int, list[str]] = {}
    for plan in plans:
        for key, _, drive in source.frames:
            path = source.images[plan.index].get(key)
            if path is None and skip:
                missing.setdefault(key, []).append(plan.camera.name)
                continue
            if path is None:
                what = _lighting_said(drive)
                raise GraMiInputError(
                    source.folder,
                    f"camera {plan.camera.name} has no image of frame {key:06d} ({what}); --missing-images skip imports the rest",
                )
            if image_size(path) != plan.source_size:
                said = f"is {image_size(path)}, the calibration's (and other images') size of {plan.camera.name} is {plan.source_size}"
                raise GraMiInputError(path, said + orientation_hint(path))
    for plan in plans:
        if all(plan.camera.name in missing.get(key, []) for key, _, _ in source.frames):
            raise GraMiInputError(source.folder, f"camera {plan.camera.name} has no image of any frame: leave it out (--cameras)")
    complete = [key for key, _, _ in source.frames if key not in missing]
    if missing and not complete:  # the mesh is checked against every camera's mask on one frame
        raise GraMiInputError(source.folder, "no frame has an image from every camera: the reprojection check needs one")
    return missing


def _lighting_said(drive) -> str:
    if drive == "white":
        return "the white frame"
    if isinstance(drive, tuple) and drive[0] == "solve":
        return f"{drive[2]}: import without {drive[3]}"
    return f"the OLAT of LED {drive + 1}" if isinstance(drive, int) else "its lighting"


# --------------------------------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------------------------------


def import_capture(
    source: Source, out: Path, config: ImportConfig, record: dict, overwrite: bool = False, options=None, shard: Shard | None = None,
    estimate_gains=None,
) -> Capture | None:  # fmt: skip
    """The import, whatever the source: its checks, frame, cameras, the reprojection check, then the files.

    Everything is built in a staging folder beside ``out`` (:func:`gra_mi.core.guard.staging_folder`; an interrupted
    import resumes there), loaded back with gra-mi's own readers, and published by renaming it to ``out`` only when
    they accept it: a failure leaves nothing at ``out``. ``shard``: import only its frames' images (every shard writes
    the rig and subject alike); the shard that finds every shard's images done checks and publishes the capture and
    returns it, the others return None. ``estimate_gains``: what measures the LEDs' gains on the written capture
    (``config.estimate_led_gains``; :func:`gra_mi.fit.led_gains.estimate_led_gains`, a layer above this one)."""

    if config.estimate_led_gains and estimate_gains is None:
        raise GraMiParameterError(
            "estimate_led_gains", "needs estimate_gains=gra_mi.fit.led_gains.estimate_led_gains (gra-mi import passes it)"
        )
    source.check()
    gains = source.led_gains(config.led_gains, config.estimate_led_gains)
    ensure_mitsuba()
    frame = world_frame(source, config.up)
    plans = _camera_plans(source, frame, config)
    largest = max(p.camera.width * p.camera.height for p in plans)
    require_memory("scale", largest * IMAGE_BYTES_PER_PIXEL, f"images of {largest:,} pixels at --scale {config.scale:g}")
    if distorted := [p.source_size[0] * p.source_size[1] for p in plans if p.lens is not None]:
        require_memory_for(
            source.calib_path, "distortion", max(distorted) * LENS_BYTES_PER_PIXEL, f"undistorting images of {max(distorted):,} pixels"
        )
    eval_cameras = config.eval_cameras or _held_out(plans)
    train_cameras = [p.camera.name for p in plans if p.camera.name not in eval_cameras]
    if not train_cameras:
        raise GraMiParameterError("eval_cameras", "holds every imported camera: at least one camera must be left to fit on")
    missing = check_images_present(source, plans, config.missing_images == "skip")
    check_envmaps(source)
    subject = plan_subject(source, config.uv_resolution)
    # the frame every camera's mask is checked on: the first that every camera has
    key, pose = next((k, f.mesh_frame) for k, f, _ in source.frames if k not in missing)
    masks = [frame_mask(source, plan, key) for plan in plans]
    checks = reprojection_checks(source, frame, subject.posed(source, frame, pose), plans, masks, config.min_iou, 0)
    check_images_fit_masks(source, plans, key)
    said = asdict(config) | (asdict(options) if options is not None else {})
    shard, command = shard or Shard(), f"import {source.format}"
    inputs = {"source": source.folder, "files outside the source": files_read_outside(source), "LED gains": config.led_gains}
    if (done := _already_published(out, run_record(command, inputs, said), overwrite)) is not None:
        return done
    staging = staging_folder(out)
    # a changed source restarts the staging (its images would mix two exports); --overwrite empties it too
    claim_output(staging, command, inputs, said, overwrite=overwrite, shard=shard, restart=shard.whole)
    solved = apply_solved_drives(source, [p for p in plans if p.camera.name in train_cameras], staging / "import" / "solved_drives.json")
    stage = build_stage(source, frame, plans, led_intensity(source, config), gains)
    if config.estimate_led_gains and not any(_lit_alone(stage, entry, drive) for _, entry, drive in source.frames):
        raise GraMiParameterError(
            "estimate_led_gains", f"{source.folder} has no frame lit by one LED alone (an OLAT): gains are measured on OLATs"
        )
    _write_stage_files(staging, stage, source, frame, subject)
    plot_solved_drives(stage, source.frames, staging / "import" / "solved_drives.png")
    record = {"format": source.format, "folder": str(source.folder), "transform": frame.matrix(), "solved_frames": solved, **record}
    record |= _lights_said(source, config, stage, gains) | {"left_out_leds": source.left_out, "uv_atlas": subject.atlas, "images": {}}
    record["checked_frame"] = next(f.frame for k, f, _ in source.frames if k == key)  # the masks' overlays show it
    frames = [replace(f, missing=missing.get(k, [])) for k, f, _ in source.frames]
    capture = Capture(staging, source.format, "captured", config.uv_resolution, train_cameras, eval_cameras, frames, source=record)
    mine = shard.take(source.frames)
    workers = import_workers(max(p.source_size[0] * p.source_size[1] for p in plans) * IMAGE_BYTES_PER_PIXEL)
    saturated = {plan.camera.name: _import_camera(source, plan, capture, mine, workers) for plan in plans}
    if not shard.whole:
        saturated = _merge_shards(staging, shard, saturated)
        if saturated is None:
            return None  # other shards' images are still being written: the last shard checks and publishes
    for plan in plans:
        gaps = {"missing_frames": [f.frame for f in frames if plan.camera.name in f.missing]}
        record["images"][plan.camera.name] = _camera_summary(source, plan, saturated[plan.camera.name]) | gaps
    capture.save()
    if config.estimate_led_gains:  # on the written images, before the report that says what came of it
        record["gains"], record["gain_estimate"] = _measured_gains(estimate_gains, capture, stage, source)
        capture.save()
    write_report(staging, source, frame, plans, checks, record, workers)
    shutil.rmtree(staging / "parts", ignore_errors=True)
    check_loadable(staging, source)
    publish(staging, out)
    return Capture.load(out)


def files_read_outside(source: Source) -> list[Path]:
    """Every file the import reads that lies outside the source folder (a mesh, LED file, lighting file, envmaps or
    images reached through ``../``): the run's provenance covers them by content, so an edited one is another run."""
    folder = source.folder.resolve()
    found = {source.calib_path, source.leds_path, *(p for images in source.images for p in images.values())}
    found |= {p for p in source.masks if p is not None} | {Path(d) for _, f, d in source.frames if f.kind == "envmap"}
    found |= {p for masks in source.frame_masks or [] for p in masks.values()}
    found |= {Path(d[1]) for _, _, d in source.frames if isinstance(d, tuple) and d[0] == "pattern"}
    found |= set(source.mesh_files) | set(source.calib_files)
    return sorted(p for p in found if p is not None and folder not in Path(p).resolve().parents)


def check_envmaps(source: Source) -> None:
    """Every environment map a frame names, read as the HDR image it claims to be (finite, non-negative, 2:1), before
    anything is written: a text file, a NaN map or a file reached through ``../`` by mistake stops here, by name."""
    from gra_mi.stage.envmap import load_envmap

    for path in sorted({Path(d) for _, f, d in source.frames if f.kind == "envmap"}):
        load_envmap(path)


def _already_published(out: Path, record: dict, overwrite: bool) -> Capture | None:
    """The capture at ``out`` when this same import already finished there; None when ``out`` is new or empty (or
    ``overwrite``: it is replaced on publishing); otherwise the difference is named."""
    if not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return None
    if not out.is_dir():
        raise GraMiInputError(out, "is a file; expected an output folder")
    differences = run_differences(out, record)
    if differences is None:
        raise GraMiInputError(out, "is not empty and was not made by gra-mi (no provenance.json); choose an empty or new output folder")
    if overwrite:
        return None
    if differences:
        raise GraMiInputError(
            out / PROVENANCE,
            f"this folder was made by another run ({'; '.join(differences)}). Use --overwrite to start over, or choose another output folder",
        )
    capture = Capture.load(out)
    cameras = capture.train_cameras + capture.eval_cameras
    if all(capture.image_path(c, f.frame).is_file() for c in cameras for f in capture.frames if capture.has_image(c, f)):
        logger.info("%s: this import is already complete", out)
        return capture
    logger.info("%s: images are missing; the import resumes", out)
    staging = staging_folder(out)
    shutil.rmtree(staging, ignore_errors=True)  # a leftover of an older attempt: the published images are newer
    os.replace(out, staging)  # back into staging: published again once complete and checked
    return None


def check_loadable(staging: Path, source: Source) -> None:
    """gra-mi's own readers on the staged capture: the capture record, its calibration, the subject, every frame's
    lighting and every image. What they refuse is a fault of the import (its source passed every check), said so."""
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    try:
        capture = Capture.load(staging)
        stage = load_calibration(staging / "rig" / "calibration.json")
        load_sequence(staging / "subject")
        for entry in capture.frames:
            capture.lighting(stage, entry)
        capture.check_images()
    except GraMiInputError as exc:
        raise GraMiInputError(source.folder, f"the import of this source would not load in gra-mi ({exc}); please report it") from None


def publish(staging: Path, out: Path) -> None:
    """Rename the checked staging folder to ``out`` (replacing an older import there: ``--overwrite``). Two shards that
    finish together may both get here: the second finds the capture published."""
    release_folder(staging)
    if not staging.exists() and (out / "capture.json").is_file():
        return
    if out.exists():
        shutil.rmtree(out)
    os.replace(staging, out)


def _merge_shards(out: Path, shard: Shard, saturated: dict[str, list[float]]) -> dict[str, list[float]] | None:
    """Record this shard's per-camera saturation; every shard's, once all are recorded (else None)."""
    parts = [out / "parts" / f"import-shard-{i}-of-{shard.count}.json" for i in range(shard.count)]
    atomic_write_text(parts[shard.index], json.dumps(saturated) + "\n")
    if not all(p.is_file() for p in parts):
        return None
    merged: dict[str, list[float]] = {}
    for part in parts:
        for cam, values in json.loads(part.read_text()).items():
            merged.setdefault(cam, []).extend(values)
    return merged


def _held_out(plans: list[CameraPlan]) -> list[str]:
    """Two cameras spread over the rig for novel-view evaluation (one with 3 or fewer; none with one)."""
    if len(plans) < 2:
        return []
    picks = [len(plans) // 4, (3 * len(plans)) // 4] if len(plans) > 3 else [len(plans) - 1]
    return [plans[k].camera.name for k in dict.fromkeys(picks)]


def _camera_plans(source: Source, frame: WorldFrame, config: ImportConfig) -> list[CameraPlan]:
    names = source.names
    chosen = config.cameras or names
    unknown = [c for c in chosen + (config.eval_cameras or []) if c not in names]
    if unknown:
        raise GraMiParameterError("cameras", f"no camera {', '.join(unknown)} in {source.calib_path} (it has {names[0]} … {names[-1]})")
    if config.eval_cameras and not set(config.eval_cameras) <= set(chosen):
        raise GraMiParameterError("eval_cameras", "held-out cameras must be among the imported ones (--cameras)")
    return [plan_camera(source, names.index(c), frame, config.scale) for c in chosen]


def led_intensity(source: Source, config: ImportConfig) -> float:
    """A fully driven LED's W/sr: --led-intensity where given, else what the source states (a Mitsuba scene's point
    emitters), else the option's default."""
    given = bool(changed_options(config, ("led_intensity",)))
    return config.led_intensity if given or source.stated_intensity is None else source.stated_intensity


def _lights_said(source: Source, config: ImportConfig, stage: Lightstage, gains: np.ndarray | None) -> dict:
    """The report's words for where the LEDs' intensity and gains come from."""
    given = changed_options(config, ("led_intensity",)) or source.stated_intensity is None
    where = "--led-intensity" if given else f"the mean of the source's {source.gains_field}"
    said = {"led_intensity": f"{stage.max_led_intensity:.4g} W/sr ({where})"}
    if gains is None:
        return said | {"gains": "assumed equal (none given: --led-gains)"}
    stated = config.led_gains or f"the source's {source.gains_field}"
    return said | {"gains": f"from {stated}, normalised to a mean of 1 (from {gains.min():.3f} to {gains.max():.3f})"}


def _lit_alone(stage: Lightstage, entry, drive) -> bool:
    """Whether a source frame is lit by one LED alone."""
    return entry.kind != "envmap" and int(np.count_nonzero(_drive(stage, drive).max(axis=1))) == 1


def _measured_gains(estimate_gains, capture: Capture, stage: Lightstage, source: Source) -> tuple[str, dict]:
    """The LEDs' gains ``estimate_gains`` measures on the imported OLATs, written into the rig, as a --led-gains file
    in the source's numbering and as a plot; (what the report says of them, the estimate's summary)."""
    try:
        estimate = estimate_gains(capture)
    except GraMiInputError as exc:  # said of the source: the capture being written is the import's own staging folder
        raise GraMiParameterError("estimate_led_gains", f"{source.folder}: {exc.problem}") from None
    numbers = source.led_numbers or list(range(len(source.leds)))
    dark = np.flatnonzero(estimate.gains.min(axis=1) < MIN_RELATIVE_GAIN)
    if dark.size:  # as a given gain that low is refused: no drive could give such an LED an environment map's share
        raise GraMiParameterError(
            "estimate_led_gains", f"{source.folder}: LED {numbers[dark[0]]}'s OLATs are dark (measured gain "
            f"{np.round(estimate.gains[dark[0]], 4).tolist()}, below {MIN_RELATIVE_GAIN:.0%} of the mean): a dead LED, or its OLAT "
            "images mixed up with another's?",
        )  # fmt: skip
    stage.led_gains = estimate.gains
    write_rig(stage, capture.folder / "rig")
    write_led_gains(capture.folder / "import" / "led_gains.txt", estimate.gains, numbers, estimate.measured, source.folder)
    _plot_gains(estimate, numbers, capture.folder / "import" / "led_gains.png")
    summary = estimate.summary() | {  # in the source's numbers
        "unmeasured_leds": [numbers[k] for k in np.flatnonzero(~estimate.measured)],
        "suspect_leds": [numbers[k] for k in np.flatnonzero(estimate.suspect)],
    }
    if summary["suspect_leds"]:
        logger.warning("LEDs %s: their OLATs are lit elsewhere than their positions say (import_report.md)", summary["suspect_leds"])
    said = (
        f"estimated from the OLATs on the training cameras ({summary['measured_leds']} of {stage.num_leds} LEDs measured, "
        f"from {summary['range'][0]:.3f} to {summary['range'][1]:.3f}; the others 1): import/led_gains.txt"
    )
    return said, summary


def _plot_gains(estimate, numbers: list[int], path: Path) -> None:
    """Each LED's measured gain per channel against its number in the source; LEDs not measured hollow."""
    from gra_mi.core.io import pyplot, save_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(min(4 + 0.03 * len(numbers), 14), 3.4))
    x, measured = np.asarray(numbers), estimate.measured
    for c, colour in enumerate(("tab:red", "tab:green", "tab:blue")):
        ax.plot(x[measured], estimate.gains[measured, c], ".", color=colour, ms=4)
    if not measured.all():
        ax.plot(x[~measured], np.ones((~measured).sum()), "o", mfc="none", color="grey", ms=5, label="not measured (1)")
        ax.legend(fontsize=8)
    ax.axhline(1.0, color="k", lw=0.5)
    ax.set_xlabel("LED (the source's number)")
    ax.set_ylabel("gain (each channel's mean 1)")
    ax.set_title("LED gains measured on the OLATs (red, green, blue)")
    fig.tight_layout()
    save_figure(fig, path)


def _write_stage_files(out: Path, stage: Lightstage, source: Source, frame: WorldFrame, subject: SubjectPlan) -> None:
    write_rig(stage, out / "rig")
    if not (out / "subject" / "sequence.npz").is_file():
        subject.write(source, frame, out / "subject")
    scale = np.diag([*[source.mesh_units or source.units] * 3, 1.0])  # the set is in the meshes' units
    set_xml = write_set(source.set_shapes, out / "set", np.array(frame.matrix()) @ scale)
    atomic_write_text(out / "scene.xml", subject_scene_xml("rig", "subject", set_xml=set_xml))
    for _, entry, drive in source.frames:
        if entry.kind == "envmap":  # the source's map, copied in so the capture stands on its own
            target = out / entry.envmap
            if not target.is_file():
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(drive, target)
            continue
        atomic_write_text(out / entry.pattern, json.dumps({"intensities": _drive(stage, drive).tolist()}) + "\n")


def _drive(stage: Lightstage, drive) -> np.ndarray:
    """LED intensities of a frame's lighting: "white" (every LED at the maximum), an LED index (its OLAT),
    ("uniform", fraction of the maximum), ("pattern", a drive file of the source) or ("solved", the drive in OLATs)."""
    if isinstance(drive, tuple) and drive[0] == "solved":  # 1: as its OLAT drove the LED
        return np.asarray(drive[1], float) * stage.max_led_intensity
    if drive == "white":
        return uniform_pattern(stage, 1.0)
    if isinstance(drive, tuple) and drive[0] == "uniform":
        return uniform_pattern(stage, drive[1])
    if isinstance(drive, tuple) and drive[0] == "pattern":
        return load_pattern(stage, drive[1])
    return olat_pattern(stage, drive)


def import_workers(image_bytes: float) -> int:
    """Threads that import a camera's images (:func:`thread_count`), no more than memory holds: each holds one
    image's arrays."""
    return thread_count(int(MEMORY_SHARE * machine_memory() // max(image_bytes, 1.0)))


def _import_camera(source: Source, plan: CameraPlan, capture: Capture, frames: list, workers: int = 1) -> list[float]:
    """The ``frames`` of one camera: each image decoded, resampled and written by one of ``workers`` threads (decoding
    and EXR compression release the GIL). The first goes alone, so the camera's mask and lens tables are made once.
    Returns each frame's fraction of saturated subject pixels, in order."""
    jobs = [(key, entry) for key, entry, _ in frames if key in source.images[plan.index]]  # gaps --missing-images skip let through
    if not jobs:
        return []
    less = _subtracted_light(source, plan, [key for key, _ in jobs if key in source.subtracted], workers)
    first = _import_image(source, plan, capture, *jobs[0], less)
    rest = threaded(lambda job: _import_image(source, plan, capture, *job, less), jobs[1:], f"import {plan.camera.name}", workers)
    return [first, *rest]


def _import_image(source: Source, plan: CameraPlan, capture: Capture, key: int, entry, less: dict) -> float:
    """One source image: sRGB → linear, less the light ``less`` holds for it (floored at 0: the 8-bit steps of the
    images subtracted), onto the planned grid, its mask as alpha; its saturated share of the subject. An image
    already written (a resumed import) is only read for that share."""
    name = plan.camera.name
    path, image_path = capture.image_path(name, entry.frame), source.images[plan.index][key]
    rgb, clipped, alpha = read_image(image_path)
    mask = frame_mask(source, plan, key, (rgb, alpha))  # the image decoded once
    if key in less:
        rgb, clipped = np.maximum(rgb - less[key][0], 0.0), clipped | less[key][1]
    saturated = float((clipped & (mask_at_source(mask, plan) > 0.5)).mean()) if clipped.any() else 0.0
    if path.is_file():
        return saturated
    if clipped.any():  # a planned pixel any clipped source pixel contributes to is left out of the fit
        write_mask(capture.saturation_path(name, entry.frame), resample_image(clipped[..., None].astype(np.float32), plan)[..., 0] > 0)
    rgb = resample_image(rgb, plan)
    if alpha is None:  # a binary mask: the background is cut away
        rgb = rgb * (mask[..., None] > 0.5)
    elif image_path.suffix.lower() != ".exr":  # straight alpha (PNG, AVIF) → premultiplied, as EXR holds it
        rgb = rgb * mask[..., None]
    write_exr(path, np.concatenate([rgb, mask[..., None]], axis=-1).astype(np.float32))
    return saturated


def _subtracted_light(source: Source, plan: CameraPlan, keys: list[int], workers: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per frame of ``keys``: (the light ``source.subtracted`` names for it, LEDs the rig leaves out: each one's OLAT
    image times its drive; the pixels saturated in any of those images), each OLAT image read once for every frame."""
    olats = sorted({olat for key in keys for olat, _ in source.subtracted[key]})
    less: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    if not olats:  # most imports: no frame has light to take off (no threads, no progress line per camera)
        return less
    read = threaded(lambda olat: read_image(source.images[plan.index][olat])[:2], olats, f"light to subtract {plan.camera.name}", workers)
    for olat, (light, saturated) in zip(olats, read, strict=True):  # summed in order: the same sums whatever the threads
        for key in keys:
            for weight in (w for o, w in source.subtracted[key] if o == olat):
                rgb, clipped = less.get(key, (np.zeros_like(light), np.zeros_like(saturated)))
                less[key] = (rgb + light * np.asarray(weight, np.float32), clipped | saturated)
    return less


def _camera_summary(source: Source, plan: CameraPlan, saturated: list[float]) -> dict:
    """What the report says of a camera's images: saturation, the square-pixel resampling's error, the lens undone,
    how many carry an EXIF orientation tag (read as stored)."""
    paths = list(source.images[plan.index].values())
    first = read_image(paths[0])[0]
    lens = None
    if plan.lens is not None:
        lens = {"model": plan.lens.describe(), "held": held_fraction(plan.source_k, plan.lens, *plan.source_size)}
    return {
        "saturated_fraction": max(saturated),
        "resampling_error": _resampling_error(first, plan),
        "anisotropy": plan.anisotropy,
        "lens": lens,
        "exif_turned": sum(exif_orientation(p) != 1 for p in paths),
    }


def _resampling_error(image: np.ndarray, plan: CameraPlan) -> float | None:
    """Relative RMSE of the white frame taken to square pixels and back, over lit pixels (None: already square)."""
    if plan.square_width == plan.source_size[0]:
        return None
    there = resample_columns(image, plan.square_width)
    back = resample_columns(there, plan.source_size[0])
    lit = image.max(axis=-1) > 0
    return float(np.sqrt(np.mean((back - image)[lit] ** 2)) / max(float(np.sqrt(np.mean(image[lit] ** 2))), 1e-12))
