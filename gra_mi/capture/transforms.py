"""NeRF-style ``transforms.json`` captures (nerfstudio's and the original NeRF's layout, and the per-OLAT JSON
HumanOLAT's tools write) into gra-mi's capture layout, through the same import as every source
(:func:`gra_mi.capture.importer.import_capture`).

Read: ``transforms.json``, or ``transforms_train.json`` / ``transforms_test.json`` (``_val`` counts as test: held-out
lighting). Per frame: ``file_path`` (relative to the JSON, with or without its extension), ``transform_matrix``
(camera-to-world, OpenGL/Blender axes: x right, y up, z backwards), intrinsics either as nerfstudio spells them
(``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h``, at the top or per frame), as HumanOLAT's tools do
(``camera_intrinsics = [cx, cy, fx, fy]``) or as the original NeRF does (``camera_angle_x``); its lighting: an LED
(``light_idx`` with its position ``pl_pos`` and ``pl_intensity``), or an environment map (``envmap``, a path). Frames
of the same lighting (and ``mesh_frame``, for a mesh sequence) are one capture frame seen by every camera; a camera is
a ``cam_idx``, or else one pose and intrinsics. Masks: nerfstudio's ``mask_path`` (a static pose: one per camera), else
the images' alpha, else the pixels the subject covers. Lens distortion (``camera_model`` ``OPENCV`` with ``k1`` …
``k4``, ``p1``, ``p2`` as nerfstudio reads them, or ``OPENCV_FISHEYE`` with ``k1`` … ``k4``) is undone at import
(:mod:`~gra_mi.capture.lens`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, field_validator

from gra_mi.capture.alignment import aligned
from gra_mi.capture.dataset import FrameLighting
from gra_mi.capture.importer import import_capture
from gra_mi.capture.lens import LensDistortion
from gra_mi.capture.mesh_frames import read_meshes
from gra_mi.capture.source import ImportConfig, Source
from gra_mi.capture.source_files import CalibCamera, image_size, read_points
from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import read_json
from gra_mi.core.schema import Count, Finite, Positive, PositiveCount, Record, matrix, parse, rigid_rotation

SUFFIXES = ("", ".png", ".jpg", ".jpeg", ".avif", ".exr")
DISTORTION = ("k1", "k2", "k3", "k4", "p1", "p2")
CAMERA_MODELS = {"OPENCV": "radial-tangential", "OPENCV_FISHEYE": "fisheye", "PINHOLE": None, "SIMPLE_PINHOLE": None}
UNITS = {"m": 1.0, "mm": 0.001}


@dataclass(kw_only=True)
class TransformsOptions:
    """What a transforms.json capture needs besides its JSON (:func:`import_transforms`)."""

    mesh: Path | None = None
    """transforms, easymocap, colmap: the subject's mesh (OBJ or PLY; without UVs an atlas is generated), or a folder of one
    per mesh frame (a tracked sequence, one topology, in the names' numbered order: frame_2 before frame_10; frames
    name theirs with `mesh_frame`)."""
    units: str = field(default="m", metadata=option(choices=tuple(UNITS)))
    """transforms, easymocap, colmap: the unit of the calibration's positions (camera translations, `pl_pos`, --leds)."""
    mesh_units: str = field(default="m", metadata=option(choices=tuple(UNITS)))
    """transforms, easymocap, colmap: the unit of the mesh (HumanOLAT's model.obj: mm)."""
    leds: Path | None = None
    """transforms, easymocap, colmap: the rig's LED positions (`v x y z` per line, in --units; light_idx indexes them). Default: the
    LEDs the frames name with light_idx and pl_pos."""
    align_cameras: Path | None = field(default=None, metadata=option(metavar="PLACES"))
    """transforms, easymocap, colmap: where some cameras are in the LEDs' frame (--units), a line `NAME X Y Z` each (COLMAP
    model_aligner's ref_images; NAME a camera, by its name or the source's own, or an image path whose folder names one): the calibration, in a frame
    and scale of its own, is moved there by the similarity that fits them (3 cameras or more, not in a line). Default:
    the calibration is in the LEDs' frame already."""
    mesh_frame: str = field(default="leds", metadata=option(choices=("leds", "calibration")))
    """transforms, easymocap, colmap, with --align-cameras: the frame --mesh is in. leds: the LEDs' (the stage's);
    calibration: the calibration's own (a mesh tracked or reconstructed with it: EasyMocap's, COLMAP's), moved with
    the cameras."""

    def validate(self) -> None:
        if self.mesh_frame != "leds" and self.align_cameras is None:  # the two frames are one without it
            raise GraMiParameterError("mesh_frame", "moves the mesh with --align-cameras: give it, or leave the mesh in the LEDs' frame")
        if self.mesh is None:
            raise GraMiParameterError(
                "mesh",
                "the import needs the subject's mesh in the calibration's frame (--mesh FILE.obj|.ply, or a folder of one per frame)",
            )


def import_transforms(
    folder: str | Path,
    out: str | Path,
    config: ImportConfig | None = None,
    options: TransformsOptions | None = None,
    overwrite: bool = False,
    shard=None,
    estimate_gains=None,
):
    config, options = config or ImportConfig(), options or TransformsOptions()
    config.validate()
    options.validate()
    source = read_transforms(Path(folder), options)
    units = {"units": options.units, "mesh_units": options.mesh_units}
    return import_capture(source, Path(out), config, units, overwrite, options, shard, estimate_gains)


@dataclass
class _Frame:
    path: Path
    camera: str
    lighting: tuple  # ("led", index) or ("envmap", path)
    pose: int
    split: str


def read_transforms(folder: Path, options: TransformsOptions) -> Source:
    files = _json_files(folder)
    calib, sizes, frames, unnamed, masks, file_paths = {}, {}, [], {}, {}, []
    leds = {} if options.leds is None else dict(enumerate(read_points(options.leds)))
    stated: dict[int, np.ndarray] = {}  # LED → its pl_intensity
    for path, split in files:
        data = _read(path)
        shared = parse(TransformsCamera, {k: v for k, v in data.items() if k != "frames"}, path)
        for i, raw in enumerate(data["frames"]):
            where = f"frames[{i}]"
            entry = parse(TransformsFrame, raw, path, where)
            image = _image_path(path, entry.file_path, where)
            camera, intrinsic, c2w, size, lens = _camera(path, shared, entry, where, image)
            if not isinstance(camera, str):  # named by its first appearance
                camera = unnamed.setdefault(camera, f"cam{len(unnamed):02d}")
            if camera in calib and not np.allclose(calib[camera].extrinsic, c2w, atol=1e-6):
                raise GraMiInputError(path, f"camera {camera} appears with two different poses", field=f"{where}.transform_matrix")
            if camera in calib and calib[camera].lens != lens:
                raise GraMiInputError(path, f"camera {camera} appears with two different lens distortions", field=where)
            calib.setdefault(camera, CalibCamera(intrinsic, c2w, [], lens=lens))
            sizes.setdefault(camera, size)
            frames.append(_Frame(image, camera, _lighting(path, entry, where, leds, stated), entry.mesh_frame, split))
            file_paths.append(entry.file_path)  # (a camera's other name, for --align-cameras)
            if entry.mask_path is not None and camera not in masks:  # nerfstudio's per-frame mask; a static pose needs one per camera
                masks[camera] = _image_path(path, entry.mask_path, f"{where}.mask_path")
    if not leds:
        raise GraMiInputError(files[0][0], "no LEDs: frames with light_idx and pl_pos, or --leds: gra-mi fits materials under known lights")
    names = sorted(calib)
    cameras, moved = aligned(options, names, [calib[n] for n in names], {raw: f.camera for raw, f in zip(file_paths, frames, strict=True)})
    led_index = {k: n for n, k in enumerate(sorted(leds))}
    groups: dict[tuple, dict] = {}
    for f in frames:
        groups.setdefault((f.lighting, f.pose, f.split), {})[f.camera] = f.path
    meshes = read_meshes(options.mesh, max(f.pose for f in frames) + 1)
    source_frames, images = [], [{} for _ in names]
    for key, ((lighting, pose, split), seen) in enumerate(groups.items()):
        for k, name in enumerate(names):
            if name in seen:
                images[k][key] = seen[name]
        source_frames.append(_frame_entry(key, lighting, pose, split, led_index))
    return Source(
        folder, "transforms", files[0][0], names, cameras, [sizes[n] for n in names], images, UNITS[options.units],
        np.array([leds[k] for k in sorted(leds)]) * UNITS[options.units], meshes,
        [masks.get(n) if len(meshes) == 1 else None for n in names], source_frames,
        mesh_units=UNITS[options.mesh_units], leds_path=options.leds or files[0][0], mesh_files=[options.mesh], led_numbers=sorted(leds),
        stated_gains=_stated_gains(stated, sorted(leds)), **moved,
        calib_files=[options.align_cameras] if options.align_cameras else [],
    )  # fmt: skip


def _stated_gains(stated: dict[int, np.ndarray], numbers: list[int]) -> np.ndarray | None:
    """The LEDs' pl_intensity in ``numbers`` order (1 where no frame states one), or None where every one is 1."""
    if all(np.allclose(g, 1.0) for g in stated.values()):
        return None
    return np.array([stated.get(k, np.ones(3)) for k in numbers], float)


def _json_files(folder: Path) -> list[tuple[Path, str]]:
    if (folder / "transforms.json").is_file():
        return [(folder / "transforms.json", "train")]
    found = [(folder / f"transforms_{s}.json", "test" if s != "train" else "train") for s in ("train", "val", "test")]
    found = [(p, s) for p, s in found if p.is_file()]
    if not found:
        raise GraMiInputError(folder, "no transforms.json (or transforms_train.json / transforms_test.json)")
    return found


def _read(path: Path) -> dict:

    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise GraMiInputError(path, "expected an object with a non-empty 'frames' list", field="frames")
    return data


def _image_path(path: Path, file_path: str, where: str) -> Path:
    base = Path(file_path) if Path(file_path).is_absolute() else path.parent / file_path
    for suffix in SUFFIXES:
        candidate = base.with_name(base.name + suffix) if suffix else base
        if candidate.is_file():
            return candidate
    raise GraMiInputError(path, f"image {base} not found", field=f"{where}.file_path")


class TransformsCamera(Record):
    """Intrinsics a frame holds or shares from the file's top level (nerfstudio's and NeRF's spellings)."""

    w: PositiveCount | None = None
    h: PositiveCount | None = None
    fl_x: Positive | None = None
    fl_y: Positive | None = None
    cx: Finite | None = None
    cy: Finite | None = None
    camera_angle_x: Annotated[float, Field(gt=0, lt=math.pi, allow_inf_nan=False)] | None = None
    camera_model: str | None = None
    k1: Finite | None = None
    k2: Finite | None = None
    k3: Finite | None = None
    k4: Finite | None = None
    p1: Finite | None = None
    p2: Finite | None = None


class TransformsFrame(TransformsCamera):
    """One entry of ``frames``."""

    file_path: str
    transform_matrix: matrix(4, 4)
    camera_intrinsics: matrix(4) | None = None  # HumanOLAT's tools: [cx, cy, fx, fy]
    cam_idx: Count | None = None
    light_idx: Count | None = None
    pl_pos: matrix(3) | None = None
    pl_intensity: matrix(3) | None = None  # the LED's RGB gain (HumanOLAT's tools write [1, 1, 1])
    mesh_frame: Count = 0
    envmap: str | None = None
    mask_path: str | None = None

    @field_validator("transform_matrix")
    @classmethod
    def _rigid(cls, m: np.ndarray) -> np.ndarray:
        if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError(f"the last row must be (0, 0, 0, 1), got {m[3].tolist()}")
        rigid_rotation(m[:3, :3], "camera-to-world rotation")
        return m

    @field_validator("pl_intensity")
    @classmethod
    def _gain(cls, v: np.ndarray | None) -> np.ndarray | None:
        if v is not None and v.min() < 0:
            raise ValueError(f"an LED's intensity must be non-negative, got {v.tolist()}")
        return v

    @field_validator("camera_intrinsics")
    @classmethod
    def _focal(cls, v: np.ndarray | None) -> np.ndarray | None:
        if v is not None and (v[2] <= 0 or v[3] <= 0):
            raise ValueError(f"[cx, cy, fx, fy] needs fx, fy > 0, got {v.tolist()}")
        return v


def _camera(path: Path, shared: TransformsCamera, entry: TransformsFrame, where: str, image: Path):
    """(camera name, K / width, camera-to-world 3 × 4 with OpenCV axes, (width, height), lens distortion or None)."""
    value = lambda key: getattr(entry, key) if getattr(entry, key) is not None else getattr(shared, key)  # noqa: E731
    lens = _lens(path, value, where)
    width, height = value("w"), value("h")
    if width is None or height is None:
        width, height = image_size(image)
    if entry.camera_intrinsics is not None:
        cx, cy, fx, fy = (float(v) for v in entry.camera_intrinsics)
    elif value("fl_x") is not None:
        fx, fy = value("fl_x"), value("fl_y") or value("fl_x")
        cx, cy = (value("cx") if value("cx") is not None else width / 2), (value("cy") if value("cy") is not None else height / 2)
    elif value("camera_angle_x") is not None:
        fx = fy = 0.5 * width / math.tan(0.5 * value("camera_angle_x"))
        cx, cy = width / 2, height / 2
    else:
        raise GraMiInputError(path, "no intrinsics: expected fl_x/fl_y/cx/cy, camera_intrinsics or camera_angle_x", field=where)
    m = entry.transform_matrix.copy()
    m[:3, 1:3] *= -1  # OpenGL / Blender → OpenCV camera axes (two axes: still right-handed)
    intrinsic = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, width]], float) / width
    intrinsic[2] = [0, 0, 1]
    # a camera without cam_idx is its pose and intrinsics (rounded to 0.1 mm and 0.01 px)
    name = (
        f"Cam{entry.cam_idx + 1:02d}"
        if entry.cam_idx is not None
        else tuple(np.round(m[:3].ravel(), 4)) + tuple(np.round((fx, fy, cx, cy), 2)) + (lens,)
    )
    return name, intrinsic, m[:3], (int(width), int(height)), lens


def _lens(path: Path, value, where: str) -> LensDistortion | None:
    """The frame's lens distortion as nerfstudio reads it: ``camera_model`` (default OPENCV) and its terms."""
    model = value("camera_model") or "OPENCV"
    if model not in CAMERA_MODELS:
        raise GraMiInputError(path, f"camera_model {model!r} is not one gra-mi reads: expected one of {sorted(CAMERA_MODELS)}", field=where)
    terms = {key: value(key) for key in DISTORTION}
    if CAMERA_MODELS[model] is None:
        if any(terms.values()):
            raise GraMiInputError(path, f"camera_model {model} has no distortion, but the frame gives {terms}", field=where)
        return None
    return LensDistortion.of(CAMERA_MODELS[model], path, where, **terms)


def _lighting(path: Path, entry: TransformsFrame, where: str, leds: dict, stated: dict) -> tuple:
    if entry.light_idx is not None:
        index = entry.light_idx
        gain = np.ones(3) if entry.pl_intensity is None else entry.pl_intensity
        if index in stated and not np.allclose(stated[index], gain, rtol=1e-6):
            raise GraMiInputError(path, f"LED {index} appears with two intensities", field=f"{where}.pl_intensity")
        stated[index] = gain
        position = entry.pl_pos if entry.pl_pos is not None else leds.get(index)
        if position is None:
            raise GraMiInputError(path, f"LED {index} needs its position (3 finite numbers, or --leds)", field=f"{where}.pl_pos")
        if index in leds and not np.allclose(leds[index], position, atol=1e-6):
            raise GraMiInputError(path, f"LED {index} appears at two positions", field=f"{where}.pl_pos")
        leds[index] = np.asarray(position, float)
        return ("led", index)
    if entry.envmap is not None:
        envmap = Path(entry.envmap) if Path(entry.envmap).is_absolute() else path.parent / entry.envmap
        if not envmap.is_file():
            raise GraMiInputError(path, f"environment map {envmap} not found", field=f"{where}.envmap")
        return ("envmap", envmap)
    raise GraMiInputError(path, "no lighting: expected light_idx (with pl_pos, or --leds), or envmap", field=where)


def _frame_entry(key: int, lighting: tuple, pose: int, split: str, led_index: dict) -> tuple:
    sequence = 0 if split == "train" else (1 if lighting[0] == "led" else 0)
    if lighting[0] == "led":
        led = led_index[lighting[1]]
        return (key, FrameLighting(key, split, sequence, "pattern", None, f"patterns/olat_{led:03d}.json", pose=pose), led)
    name = f"envmaps/{lighting[1].name}"
    return (key, FrameLighting(key, split, sequence, "envmap", name, pose=pose), lighting[1])
