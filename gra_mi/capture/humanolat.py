"""HumanOLAT's processed layout (ICCV 2025, MPI Informatics; its tools: the public repository TMT22/HumanOLAT), read
and written file by file as the dataset ships them, and imported (:func:`import_humanolat`: its files into a
:class:`~gra_mi.capture.source.Source`, then the path every format shares):

```
SUBJECT_<id>/POSE_<nn>/images_processed/Cam<01..>/<capture_id>.<image number, 6 digits>.avif   sRGB, masked, undistorted
SUBJECT_<id>/POSE_<nn>/model/{model.obj, material.mtl, model.jpeg}     the mesh with UVs and texture, millimetres
SUBJECT_<id>/POSE_<nn>/segmentations/masks/000/Cam<NN>.png             binary masks
SUBJECT_<id>/shared/cameras.calib                  MPII text calibration: OpenCV camera-to-world in mm, K / image width
SUBJECT_<id>/shared/LSX_light_positions_aligned.pc `v x y z` per LED, metres, the calibration's frame
SUBJECT_<id>/shared/LSX3_light_z_spiral.txt        the OLAT firing order, 1-based LED indices
```

Image numbers: 0 the white frame, 1–2 gradients, 3–12 environment maps (which map lit which is not in the files),
14 and every 21st from 34 on (34, 55, …) full-bright frames, the OLATs in firing order in between from 15. Number 13
is not described by the dataset's readers; the writer here puts a full-bright frame there so that, as in the
dataset's tools, an image's number is its position in sorted order. :func:`write_humanolat` writes a gra-mi capture of
a static pose (``gra-mi capture --preset olat``) in this layout, in a Z-up millimetre frame with an offset stage
centre, so that the import is tested on files as the dataset ships them.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import field_validator

from gra_mi.capture.dataset import Capture, FrameLighting, load_observation
from gra_mi.capture.importer import import_capture
from gra_mi.capture.mesh_frames import MeshFrames
from gra_mi.capture.source import ImportConfig, Source
from gra_mi.capture.source_files import (
    CalibCamera,
    add_numbered,
    image_size,
    read_points,
    resample_columns,
    write_mask,
    write_obj,
    write_points,
)
from gra_mi.core.color import srgb_encode
from gra_mi.core.errors import GraMiInputError, require_positive
from gra_mi.core.io import atomic_path, atomic_write_text, read_exr, read_text
from gra_mi.core.progress import progress
from gra_mi.core.schema import Finite, NonNegative, Positive, Record, intrinsic_matrix, matrix, parse, rigid_rotation
from gra_mi.core.shard import Shard
from gra_mi.stage.lightstage import load_calibration, load_pattern
from gra_mi.subject.sequence import load_sequence

DOOR_LEDS = (178, 179, 208, 209, 210, 237, 238, 239, 240, 267, 268, 269, 270, 271, 295, 296, 297, 298, 319, 320, 321)
"""0-based indices of the LEDs on the stage's door, whose positions the dataset's tools call unreliable."""
OLAT_START = 14  # the first full-bright frame; OLATs follow
OLAT_FB_MODULO = 21  # a full-bright frame every 21st image from 34 on
WHITE, GRADIENTS, ENVMAPS = 0, (1, 2), tuple(range(3, 13))
CALIB, LEDS, SPIRAL = "shared/cameras.calib", "shared/LSX_light_positions_aligned.pc", "shared/LSX3_light_z_spiral.txt"
NUMBER = re.compile(r"\.(\d{6})\.(avif|png|jpe?g)$", re.IGNORECASE)


def olat_numbers(count: int) -> tuple[list[int], list[int]]:
    """(image number of each OLAT firing position, the full-bright image numbers among them)."""
    olats, bright, n = [], [OLAT_START], OLAT_START + 1
    while len(olats) < count:
        if (n - OLAT_START + 1) % OLAT_FB_MODULO == 0:
            bright.append(n)
        else:
            olats.append(n)
        n += 1
    return olats, bright


def camera_name(index: int) -> str:
    return f"Cam{index + 1:02d}"


# --------------------------------------------------------------------------------------------------------------
# cameras.calib
# --------------------------------------------------------------------------------------------------------------


class CalibBlock(Record):
    """One camera block of a ``.calib`` as the schema checks it: K / width a pinhole with positive focal lengths, the
    camera-to-world 3 × 4 rigid and right-handed."""

    intrinsic: matrix(3, 3)
    extrinsic: matrix(3, 4)
    distortion: list[Finite] = []
    focal_length: NonNegative = 0.0
    pixel_aspect: Positive = 1.0

    @field_validator("intrinsic")
    @classmethod
    def _pinhole(cls, k: np.ndarray) -> np.ndarray:
        return intrinsic_matrix(k)

    @field_validator("extrinsic")
    @classmethod
    def _rigid(cls, m: np.ndarray) -> np.ndarray:
        rigid_rotation(m[:, :3], "camera-to-world rotation")
        return m


def write_calib(path: Path, cameras: list[CalibCamera]) -> None:
    lines = []
    for i, cam in enumerate(cameras):
        rows = lambda m: [" ".join(f"{v:.10g}" for v in row) for row in m]  # noqa: E731
        lines += [f"name {camera_name(i)}", "distortionModel opencv", "distortion " + " ".join(f"{d:.10g}" for d in cam.distortion)]
        lines += [f"focalLength {cam.focal_length:.10g}", f"pixelAspect {cam.pixel_aspect:.10g}"]
        lines += ["extrinsic", *rows(cam.extrinsic), "intrinsic", *rows(cam.intrinsic), ""]
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_calib(path: Path) -> list[CalibCamera]:
    """Every camera block, in file order (Cam01 first); a block whose ``intrinsic`` is followed by ``time`` is skipped,
    as the dataset's reader does."""
    if not path.is_file():
        raise GraMiInputError(path, "missing: HumanOLAT's calibration (shared/cameras.calib)")
    lines, cameras, current = path.read_text(errors="replace").splitlines(), [], {}
    i, start = 0, 1
    while i < len(lines):
        line = lines[i].strip()
        words = line.split()
        if line.startswith("name"):
            start = i + 1
        if line.startswith("distortion") and "distortionModel" not in line:
            current["distortion"] = words[1:]
        elif line.startswith("focalLength"):
            current["focal_length"] = words[1] if len(words) > 1 else None
        elif line.startswith("pixelAspect"):
            current["pixel_aspect"] = words[1] if len(words) > 1 else None
        elif "extrinsic" in line:
            current["extrinsic"] = _matrix_rows(path, lines, i + 1, 4, "extrinsic")
            i += 3
        elif "intrinsic" in line:
            if i + 1 < len(lines) and "time" in lines[i + 1]:
                current = {}
            else:
                current["intrinsic"] = _matrix_rows(path, lines, i + 1, 3, "intrinsic")
                i += 3
                if "extrinsic" not in current:
                    raise GraMiInputError(path, f"camera {len(cameras) + 1}: 'intrinsic' before 'extrinsic'", field="extrinsic")
                block = parse(CalibBlock, current, path, f"camera {len(cameras) + 1}", line=start)
                cameras.append(CalibCamera(block.intrinsic, block.extrinsic, block.distortion, block.focal_length, block.pixel_aspect))
                current = {}
        i += 1
    if not cameras:
        raise GraMiInputError(path, "no camera block (expected 'extrinsic' and 'intrinsic' rows per camera)")
    return cameras


def _matrix_rows(path: Path, lines: list[str], start: int, columns: int, what: str) -> np.ndarray:
    rows = []
    for k in range(start, start + 3):
        text = lines[k].strip().lstrip("#") if k < len(lines) else ""
        try:
            row = [float(v) for v in text.split()]
        except ValueError:
            row = []
        if len(row) != columns or not np.isfinite(row).all():
            raise GraMiInputError(path, f"line {k + 1}: expected {columns} finite numbers of the {what} matrix, got '{text}'", field=what)
        rows.append(row)
    return np.array(rows, float)


# --------------------------------------------------------------------------------------------------------------
# LEDs, firing order
# --------------------------------------------------------------------------------------------------------------


def write_spiral(path: Path, order: np.ndarray) -> None:
    atomic_write_text(path, "".join(f"{int(i) + 1}\n" for i in order))


def read_spiral(path: Path, leds: int) -> np.ndarray:
    """The firing order as 0-based LED indices, checked against the LED count."""
    # (read outside the try: its error is a ValueError too)
    text = read_text(path, "HumanOLAT's OLAT firing order (shared/LSX3_light_z_spiral.txt), one LED index per line")
    try:
        order = np.array([int(w) for w in text.split()], int) - 1
    except (ValueError, OverflowError):  # (an index past int64: no LED)
        raise GraMiInputError(path, "expected one 1-based LED index per line") from None
    if len(order) != leds or order.min(initial=0) < 0 or order.max(initial=0) >= leds:
        raise GraMiInputError(path, f"{len(order)} entries with indices in [1, {leds}] expected (the LED file has {leds} LEDs)")
    values, counts = np.unique(order, return_counts=True)
    if (counts > 1).any():  # then some LED never fires, and one image would be labelled with two LEDs
        raise GraMiInputError(path, f"LED {int(values[counts > 1][0]) + 1} fires twice: the firing order must name every LED once")
    return order


# --------------------------------------------------------------------------------------------------------------
# The mesh (OBJ with UVs, millimetres)
# --------------------------------------------------------------------------------------------------------------


# --------------------------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------------------------


def write_avif(path: Path, linear: np.ndarray) -> None:
    """8-bit sRGB AVIF at quality 100 with 4:4:4 chroma (a few levels of error on noise, none on smooth images)."""
    from PIL import Image

    pixels = np.round(srgb_encode(np.clip(linear[..., :3], 0, 1)) * 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(pixels).save(tmp, format="AVIF", quality=100, subsampling="4:4:4")


def images_of(camera_dir: Path) -> dict[int, Path]:
    """Image number → file of one camera's folder; two files with one number (``000012.jpg`` and ``000012.png``) are
    refused naming both, where one would silently win."""
    found = {}
    for path in sorted(camera_dir.iterdir()) if camera_dir.is_dir() else []:
        match = NUMBER.search(path.name)
        if match:
            add_numbered(found, int(match.group(1)), path)
    return found


# --------------------------------------------------------------------------------------------------------------
# Writing a gra-mi capture of a static pose in the layout
# --------------------------------------------------------------------------------------------------------------

Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # gra-mi's Y-up frame → a Z-up one
OFFSET_MM = np.array([412.0, -233.0, 1180.0])  # the stage centre away from the origin, as in Metashape's frame


def source_frame(points_m: np.ndarray) -> np.ndarray:
    """gra-mi world points (metres, Y up) → the written layout's frame (metres, Z up, offset)."""
    return points_m @ Z_UP.T + OFFSET_MM / 1000.0


def write_humanolat(capture, root: Path, subject: str = "SUBJECT_S001", pose: str = "POSE_00", pixel_aspect: float = 1.0) -> Path:
    """Write a static-pose capture (``gra-mi capture --preset olat``) as HumanOLAT ships a pose, under
    ``root/subject``; ``pixel_aspect`` (fx / fy) ≠ 1 stretches the images along x as a camera with non-square
    pixels takes them. The images are scaled by one exposure that puts the white frame's brightest subject pixels
    (99.9th percentile) at 0.9 before 8-bit encoding; ``synthetic.json`` beside the layout (not part of it) records
    it: import with ``--led-intensity`` = the capture's LED intensity × exposure to get the same albedo. Returns the
    subject folder."""

    folder, stage = Path(root) / subject, load_calibration(capture.folder / "rig" / "calibration.json")
    numbers, order = _image_numbers(capture, stage, load_pattern)
    seq = load_sequence(capture.folder / "subject")
    model = folder / pose / "model"
    model.mkdir(parents=True, exist_ok=True)
    texture = read_exr(capture.folder / "gt" / "albedo.exr")[..., :3] if (capture.folder / "gt" / "albedo.exr").is_file() else None
    write_obj(model, source_frame(seq.vertices[0].astype(float)) * 1000.0, seq.uvs, seq.faces, texture)
    write_points(folder / LEDS, source_frame(stage.led_positions))
    write_spiral(folder / SPIRAL, order)
    calib = []
    for cam in stage.cameras:
        width = round(cam.width * pixel_aspect)
        k = np.array([[cam.fx * width / cam.width, 0, cam.cx * width / cam.width], [0, cam.fy, cam.cy], [0, 0, 1]])
        c2w = np.concatenate([Z_UP @ cam.rotation, (source_frame(cam.position[None]) * 1000.0).T], axis=1)
        intrinsic = k / width
        intrinsic[2] = [0, 0, 1]  # K divided by the image width, cy too (the MPII convention)
        calib.append(CalibCamera(intrinsic, c2w, [0.0] * 5, pixel_aspect=pixel_aspect))
    write_calib(folder / CALIB, calib)
    white = [load_observation(capture, cam.name, numbers[WHITE]) for cam in stage.cameras]
    exposure = 0.9 / max(float(np.quantile(np.concatenate([w[..., :3][w[..., 3] > 0.5] for w in white]), 0.999)), 1e-12)
    truth = {"exposure": exposure, "led_intensity": stage.max_led_intensity, "import_led_intensity": stage.max_led_intensity * exposure}
    atomic_write_text(folder / "synthetic.json", json.dumps(truth, indent=1) + "\n")
    capture_id = f"{subject.split('_')[-1]}_{pose.split('_')[-1]}"
    jobs = [(i, cam, n, f) for i, cam in enumerate(stage.cameras) for n, f in numbers.items()]
    for i, cam, number, frame in progress(jobs, description="write HumanOLAT layout"):
        path = folder / pose / "images_processed" / camera_name(i) / f"{capture_id}.{number:06d}.avif"
        if path.is_file():
            continue
        image = load_observation(capture, cam.name, frame) * np.array([exposure] * 3 + [1.0], np.float32)
        image = resample_columns(image, round(cam.width * pixel_aspect)) if pixel_aspect != 1 else image
        write_avif(path, image[..., :3])
        if frame == numbers[WHITE]:
            write_mask(folder / pose / "segmentations" / "masks" / "000" / f"{camera_name(i)}.png", image[..., 3])
    return folder


def _image_numbers(capture, stage, load_pattern) -> tuple[dict[int, int], np.ndarray]:
    """(image number → the capture frame shown there, the OLAT firing order) of a static-pose OLAT capture."""
    named = {Path(f.pattern).stem: f.frame for f in capture.frames if f.kind == "pattern"}
    envmaps = [f.frame for f in capture.frames if f.kind == "envmap"]
    olats = [
        (f.frame, int(np.argmax(load_pattern(stage, capture.folder / f.pattern).max(axis=-1))))
        for f in capture.frames
        if Path(f.pattern or "").stem.startswith("olat_")
    ]
    if "white" not in named or len(olats) != stage.num_leds or len({f.mesh_frame for f in capture.frames}) != 1:
        raise GraMiInputError(
            capture.folder / "capture.json", "not a static-pose OLAT capture (make one with `gra-mi capture --preset olat`)", field="frames"
        )
    numbers = {
        WHITE: named["white"],
        GRADIENTS[0]: named.get("gradient_up", named["white"]),
        GRADIENTS[1]: named.get("gradient_down", named["white"]),
    }
    numbers |= {n: envmaps[k] if k < len(envmaps) else named["white"] for k, n in enumerate(ENVMAPS)}  # numbers stay dense
    olat_at, bright = olat_numbers(len(olats))
    numbers |= {n: named["white"] for n in [13, *bright]}  # full-bright frames: every LED at the maximum, the white frame
    numbers |= {n: frame for n, (frame, _) in zip(olat_at, olats, strict=True)}
    return dict(sorted(numbers.items())), np.array([led for _, led in olats])


# --------------------------------------------------------------------------------------------------------------
# The import: a pose's files into a Source, the frames it imports
# --------------------------------------------------------------------------------------------------------------


@dataclass(kw_only=True)
class HumanolatOptions:
    """Which of a HumanOLAT pose's images are imported (:func:`import_humanolat`)."""

    pose: str = "POSE_00"
    """humanolat: the pose folder under the subject (POSE_00 is the A-pose)."""
    olat_step: int = 1
    """humanolat: import every Nth OLAT of the firing order (1: all)."""
    test_olat_every: int = 10
    """humanolat: every Nth imported OLAT is held out as test lighting (with the white frame); the others train."""
    keep_door_leds: bool = False
    """humanolat: keep the 21 LEDs on the stage's door, whose positions the dataset calls unreliable, in the rig and
    import their OLATs. By default they are left out of both (an environment map is then never driven onto them), and
    so is the white frame, which they lit too."""
    envmap_frames: bool = False
    """humanolat: import the 10 environment-map frames (image numbers 3–12) as held-out lighting, each with its LED
    drive solved from the pose's OLATs on the training cameras (the dataset does not say which map lit which frame).
    A frame its OLATs do not explain is left out (the report says why); the door LEDs' light, when they are left out,
    is subtracted from its images. Reads every OLAT of up to 8 training cameras once more."""
    gradient_frames: bool = False
    """humanolat: import the 2 gradient frames (image numbers 1–2: the stage bright on one side, fading to the other) as
    held-out lighting of their own, their drive solved as --envmap-frames solves an environment map's."""

    def validate(self) -> None:
        require_positive({"olat_step": self.olat_step, "test_olat_every": self.test_olat_every})


def read_humanolat(subject_dir: Path, config: HumanolatOptions) -> Source:
    """Every file of the pose, checked before anything is written: camera count against the image folders, LED count
    against the firing order, the white frame present for every camera."""
    pose = subject_dir / config.pose
    if not (pose / "images_processed").is_dir():
        raise GraMiInputError(pose / "images_processed", "missing: a HumanOLAT pose folder holds images_processed/Cam01 …")
    calib = read_calib(subject_dir / CALIB)
    folders = sorted(p.name for p in (pose / "images_processed").iterdir() if p.is_dir() and p.name.startswith("Cam"))
    if len(folders) != len(calib):
        raise GraMiInputError(
            subject_dir / CALIB, f"{len(calib)} cameras, but {len(folders)} image folders in {pose / 'images_processed'}", field="cameras"
        )
    leds = read_points(subject_dir / LEDS)
    order = read_spiral(subject_dir / SPIRAL, len(leds))
    olat_keys, steady_keys = olat_numbers(len(order))
    names = [camera_name(i) for i in range(len(calib))]
    images = [images_of(pose / "images_processed" / name) for name in names]
    sizes = []
    for name, found in zip(names, images, strict=True):
        if WHITE not in found:
            raise GraMiInputError(pose / "images_processed" / name, f"missing the white frame (image number {WHITE:06d})")
        sizes.append(image_size(found[WHITE]))
    masks = [pose / "segmentations" / "masks" / "000" / f"{name}.png" for name in names]
    source = Source(
        subject_dir, "humanolat", subject_dir / CALIB, names, calib, sizes, images, 0.001, leds,
        MeshFrames([pose / "model" / "model.obj"]), [m if m.is_file() else None for m in masks], white=WHITE, order=order, olat_keys=olat_keys, steady_keys=steady_keys,
        leds_path=subject_dir / LEDS, mesh_files=[pose / "model" / "model.obj"],
    )  # fmt: skip
    source.frames, source.left_out = humanolat_frames(source, config)
    return source


def humanolat_frames(source: Source, config: HumanolatOptions) -> tuple[list, list[int]]:
    """[(image number, frame entry, drive: an LED, "white" or ("solve", image number, what the frame is, the option that
    asks for it))] and the LEDs whose OLATs were left out.
    The white frame is test lighting (sequence 0); every ``test_olat_every``-th imported OLAT is too (sequence 1), the
    environment-map frames (sequence 2) and the gradient frames (sequence 3); the rest train."""
    olat_at, _ = olat_numbers(len(source.order))
    door = set() if config.keep_door_leds else {d for d in DOOR_LEDS if d < len(source.leds)}
    chosen = [
        (n, int(led)) for k, (n, led) in enumerate(zip(olat_at, source.order, strict=True)) if k % config.olat_step == 0 and led not in door
    ]
    left_out = sorted({int(led) for led in source.order} - {led for _, led in chosen})
    rig_index = {old: new for new, old in enumerate(i for i in range(len(source.leds)) if i not in door)}
    plan = [] if door else [(WHITE, FrameLighting(0, "test", 0, "pattern", None, "patterns/white.json", pose=0), "white")]
    for k, (number, led) in enumerate(chosen):
        split, sequence = ("test", 1) if (k + 1) % config.test_olat_every == 0 else ("train", 0)
        index = rig_index[led]  # the LED's index in the rig gra-mi writes (the door's left out)
        plan.append((number, FrameLighting(k + 1, split, sequence, "pattern", None, f"patterns/olat_{index:03d}.json", pose=0), index))
    solved = [(ENVMAPS, "envmap", 2, ("an environment-map frame", "--envmap-frames"))] if config.envmap_frames else []
    solved += [(GRADIENTS, "gradient", 3, ("a gradient frame", "--gradient-frames"))] if config.gradient_frames else []
    for numbers, name, sequence, said in solved:  # held out; the drive is solved from the OLATs at import
        first = 1 + max((entry.frame for _, entry, _ in plan), default=-1)
        plan += [
            (n, FrameLighting(first + k, "test", sequence, "pattern", None, f"patterns/{name}_{n:06d}.json", pose=0), ("solve", n, *said))
            for k, n in enumerate(numbers)
        ]
    if door:  # the rig's LEDs renumbered; --led-gains still names them by the source's numbers
        source.leds, source.led_numbers = source.leds[sorted(rig_index)], sorted(rig_index)
    return plan, left_out


def import_humanolat(
    subject_dir: str | Path,
    out: str | Path,
    config: ImportConfig | None = None,
    options: HumanolatOptions | None = None,
    overwrite: bool = False,
    shard: Shard | None = None,
    estimate_gains=None,
) -> Capture | None:
    """Import one pose of a HumanOLAT subject into ``out``; rerunning resumes (images already written are kept).
    ``estimate_gains``: :func:`~gra_mi.capture.importer.import_capture`'s."""
    config, options = config or ImportConfig(), options or HumanolatOptions()
    config.validate()
    options.validate()
    source = read_humanolat(Path(subject_dir), options)
    record = {"pose": options.pose, "units": "millimetres (calibration, mesh), metres (LEDs)"}
    return import_capture(source, Path(out), config, record, overwrite, options, shard, estimate_gains)
