"""A calibrated rig with a tracked mesh sequence, as EasyMocap (zju3dv) lays one out, into gra-mi's capture layout
through the import every source shares (:func:`gra_mi.capture.importer.import_capture`): the paper's kind of data
(a moving subject, interleaved uniformly lit and environment-lit frames).

```
DIR/intri.yml, DIR/extri.yml    OpenCV FileStorage YAML: names; K_<cam> (OpenCV's: pixel centres on integers),
                                dist_<cam>; Rot_<cam> (or R_<cam>, Rodrigues) and T_<cam>: world-to-camera,
                                x_cam = Rot · x_world + T
DIR/images/<cam>/<frame, 6 digits>.{jpg,png,avif,exr}   as the cameras took them (dist_<cam> is undone), masked or with alpha
DIR/mask/<cam>/<frame, 6 digits>.png                      optional masks
```

What EasyMocap does not hold comes from the user: ``--lighting`` (JSON: per frame its split and lighting, below),
``--leds`` (the rig's LED positions, ``v x y z``), ``--mesh`` (a folder of one OBJ per mesh frame, one topology; an
image frame shows the mesh of its index unless its lighting entry names ``mesh_frame``)::

    {"frames": [{"frame": 0, "split": "train", "uniform": 0.5},
                {"frame": 1, "split": "train", "envmap": "envmaps/sky.exr"},
                {"frame": 2, "split": "test", "led": 17},
                {"frame": 3, "split": "test", "pattern": "patterns/key.json"}]}
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BeforeValidator, Field, field_validator, model_validator

from gra_mi.capture.alignment import aligned
from gra_mi.capture.dataset import FrameLighting
from gra_mi.capture.importer import import_capture
from gra_mi.capture.lens import LensDistortion
from gra_mi.capture.mesh_frames import read_meshes
from gra_mi.capture.source import ImportConfig, Source
from gra_mi.capture.source_files import CalibCamera, add_numbered, image_size, read_points
from gra_mi.capture.transforms import UNITS, TransformsOptions
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import read_json, read_text
from gra_mi.core.schema import Count, Record, intrinsic_matrix, matrix, parse, rigid_rotation

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".avif", ".exr")


@dataclass(kw_only=True)
class EasymocapOptions:
    """What an EasyMocap rig needs besides its calibration and images (:func:`import_easymocap`)."""

    lighting: Path | None = None
    """easymocap, colmap, mitsuba: JSON with each frame's split and lighting (uniform, led, envmap or pattern;
    docs/data-format.md). easymocap reads --mesh, --leds, --units and --mesh-units as transforms does."""

    def validate(self) -> None:
        if self.lighting is None:
            raise GraMiParameterError("lighting", "the capture needs each frame's lighting (--lighting FILE.json)")


def read_opencv_yaml(path: Path) -> dict:
    """An OpenCV FileStorage YAML file: ``!!opencv-matrix`` entries as arrays, ``names`` as a list, numbers as floats."""
    text, values = read_text(path, "EasyMocap's calibration (intri.yml, extri.yml), an OpenCV FileStorage YAML file"), {}
    names = re.search(r"^names:\s*\n((?:\s+-\s*.*\n?)+)", text, re.MULTILINE)
    if names:
        values["names"] = [n.strip().strip("\"'") for n in re.findall(r"-\s*(.+)", names.group(1))]
    for key, rows, cols, data in re.findall(
        r"^(\w+):\s*!!opencv-matrix\s*\n\s*rows:\s*(\d+)\s*\n\s*cols:\s*(\d+)\s*\n\s*dt:\s*\w+\s*\n\s*data:\s*\[([^\]]*)\]",
        text,
        re.MULTILINE,
    ):
        try:
            numbers = [float(v) for v in data.replace("\n", " ").split(",") if v.strip()]
        except ValueError:
            raise GraMiInputError(path, "expected numbers in the matrix's data", field=key) from None
        if len(numbers) != int(rows) * int(cols):
            raise GraMiInputError(path, f"{len(numbers)} numbers for a {rows} × {cols} matrix", field=key)
        values[key] = np.array(numbers).reshape(int(rows), int(cols))
    return values


def _rodrigues(r: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(r))
    if theta < 1e-12:
        return np.eye(3)
    k = r.ravel() / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(theta) * kx + (1 - math.cos(theta)) * kx @ kx


class OpenCVIntrinsics(Record):
    """One camera of intri.yml: ``K_<cam>`` (a pinhole K) and ``dist_<cam>`` (OpenCV's distCoeffs, up to its rational
    and thin-prism terms: undone at import)."""

    K: matrix(3, 3)
    dist: Annotated[np.ndarray, BeforeValidator(lambda v: np.asarray(v, float).ravel())] | None = None

    @field_validator("K")
    @classmethod
    def _pinhole(cls, k: np.ndarray) -> np.ndarray:
        return intrinsic_matrix(k)


class OpenCVExtrinsics(Record):
    """One camera of extri.yml: world-to-camera ``Rot_<cam>`` (3 × 3) or ``R_<cam>`` (Rodrigues), and ``T_<cam>``."""

    Rot: matrix(3, 3) | None = None
    R: matrix(3) | None = None
    T: matrix(3)

    @field_validator("Rot")
    @classmethod
    def _rigid(cls, rot: np.ndarray | None) -> np.ndarray | None:
        return None if rot is None else rigid_rotation(rot, "world-to-camera rotation")

    @model_validator(mode="after")
    def _has_rotation(self) -> OpenCVExtrinsics:
        if self.Rot is None and self.R is None:  # it would otherwise be read as the identity, silently
            raise ValueError("the camera has no rotation (Rot_<cam> as 3 × 3, or R_<cam> as a Rodrigues vector)")
        return self


def _per_camera(values: dict, name: str, keys: tuple[str, ...]) -> dict:
    """The ``<key>_<cam>`` entries of one camera, keyed by ``key`` (what its schema names)."""
    return {key: values[f"{key}_{name}"] for key in keys if f"{key}_{name}" in values}


def _camera(intri: dict, extri: dict, name: str, images: dict[int, Path], folder: Path) -> tuple[CalibCamera, tuple[int, int]]:
    k = parse(OpenCVIntrinsics, _per_camera(intri, name, ("K", "dist")), folder / "intri.yml", key_suffix=f"_{name}")
    pose = parse(OpenCVExtrinsics, _per_camera(extri, name, ("Rot", "R", "T")), folder / "extri.yml", key_suffix=f"_{name}")
    dist = k.dist if k.dist is not None else np.zeros(5)
    lens = LensDistortion.opencv(dist, folder / "intri.yml", f"dist_{name}")  # undone at import
    rot = pose.Rot if pose.Rot is not None else _rodrigues(pose.R)
    c2w = np.concatenate([rot.T, -rot.T @ pose.T.reshape(3, 1)], axis=1)
    width, height = image_size(next(iter(images.values())))
    intrinsic = k.K / width
    intrinsic[:2, 2] += 0.5 / width  # OpenCV's pixel centres are on integers (EasyMocap projects with it), gra-mi's at +½
    intrinsic[2] = [0, 0, 1]
    return CalibCamera(intrinsic, c2w, dist.tolist(), lens=lens), (width, height)


def camera_images(folder: Path, name: str, kind: str = "images", required: bool = True) -> dict[int, Path]:
    """Frame number → file of one camera (``images/<cam>/`` or ``mask/<cam>/``)."""
    found = {}
    for path in sorted((folder / kind / name).glob("*")):
        if path.suffix.lower() in IMAGE_SUFFIXES and path.stem.isdigit():
            add_numbered(found, int(path.stem), path)
    if not found and required:
        raise GraMiInputError(folder / kind / name, "no images (expected <frame, 6 digits>.jpg/.png/.avif/.exr)")
    return found


class LightingEntry(Record):
    """One entry of the lighting file: the image's frame number, its split, and exactly one lighting."""

    frame: Count
    split: Literal["train", "test"] = "train"
    mesh_frame: Count | None = None
    sequence: Count = 0
    uniform: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] | None = None  # a fraction of the LEDs' maximum
    led: Count | None = None
    envmap: str | None = None
    pattern: str | None = None

    @model_validator(mode="after")
    def _one_lighting(self) -> LightingEntry:
        given = [k for k in ("uniform", "led", "envmap", "pattern") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(f"expected exactly one of uniform, led, envmap or pattern, got {given or 'none'}")
        return self


def _lighting(path: Path, i: int, entry: LightingEntry, leds: int) -> tuple[str, object]:
    """(FrameLighting kind, the importer's drive) of one entry of the lighting file."""
    where = f"frames[{i}]"
    if entry.uniform is not None:
        return "pattern", ("uniform", entry.uniform)
    if entry.led is not None:
        if entry.led >= leds:
            raise GraMiInputError(
                path, f"LED {entry.led} out of range: the stage has {leds} LEDs, numbered 0 to {leds - 1}", field=f"{where}.led"
            )
        return "pattern", entry.led
    kind = "envmap" if entry.envmap is not None else "pattern"
    file = path.parent / getattr(entry, kind)
    if not file.is_file():
        raise GraMiInputError(path, f"{file} not found", field=f"{where}.{kind}")
    return kind, ("pattern", file) if kind == "pattern" else file


def lighting_frames(path: Path, leds: int, default_pose: int | None = None) -> list:
    """The source's frames as a lighting file lists them: (image number, FrameLighting, the importer's drive). An entry
    without ``mesh_frame`` shows ``default_pose``, or the mesh frame of its own number (None)."""
    lighting = read_json(path)
    entries = lighting.get("frames") if isinstance(lighting, dict) else None
    if not isinstance(entries, list) or not entries:
        raise GraMiInputError(path, "expected an object with a non-empty 'frames' list", field="frames")
    frames, listed = [], {}
    for i, raw in enumerate(entries):
        entry = parse(LightingEntry, raw, path, f"frames[{i}]")
        number, split = entry.frame, entry.split
        if number in listed:  # one image, two lightings: one would relabel the other
            raise GraMiInputError(path, f"frame {number} is listed twice (entries {listed[number]} and {i})", field=f"frames[{i}].frame")
        listed[number] = i
        kind, drive = _lighting(path, i, entry, leds)
        pose = entry.mesh_frame if entry.mesh_frame is not None else number if default_pose is None else default_pose
        sequence = entry.sequence
        if kind == "envmap":
            lit = FrameLighting(i, split, sequence, "envmap", f"envmaps/{Path(drive).name}", pose=pose)
        else:
            lit = FrameLighting(i, split, sequence, "pattern", None, f"patterns/frame_{number:06d}.json", pose=pose)
        frames.append((number, lit, drive))
    return frames


def read_easymocap(folder: Path, options: EasymocapOptions, files: TransformsOptions) -> Source:
    intri, extri = read_opencv_yaml(folder / "intri.yml"), read_opencv_yaml(folder / "extri.yml")
    names = intri.get("names") or extri.get("names")
    if not names:
        raise GraMiInputError(folder / "intri.yml", "no camera names", field="names")
    needs_mesh_and_leds(files, "an EasyMocap rig")
    images = [camera_images(folder, n) for n in names]
    cameras = [_camera(intri, extri, n, found, folder) for n, found in zip(names, images, strict=True)]
    calibrated = ([f"cam{n}" for n in names], [c for c, _ in cameras], [s for _, s in cameras])
    return rig_source(folder, "easymocap", folder / "extri.yml", names, calibrated, images, options.lighting, files)


def needs_mesh_and_leds(files: TransformsOptions, rig: str) -> None:
    if files.mesh is None or files.leds is None:
        raise GraMiParameterError("mesh" if files.mesh is None else "leds", f"{rig} needs --mesh (a folder of OBJ) and --leds")


def rig_source(folder: Path, source: str, calib_path: Path, folders: list[str], calibrated: tuple, images: list, lighting: Path,
               files: TransformsOptions, calib_files: tuple = ()) -> Source:  # fmt: skip
    """The Source of a calibrated rig (EasyMocap's, COLMAP's) whose cameras are read: ``calibrated`` = (their names in the
    capture, CalibCameras, image sizes), each camera's ``images/<folder>/`` frames; what the rig does not hold from the
    user: the LEDs (--leds, --units), each frame's lighting (``lighting``), the mesh frames they show (--mesh), and the
    per-frame masks of ``mask/<folder>/``."""
    names, calib, sizes = calibrated
    calib, moved = aligned(files, names, calib, dict(zip(folders, names, strict=True)))
    units = UNITS[files.units]
    leds = read_points(files.leds) * units
    frames = lighting_frames(lighting, len(leds))
    meshes = read_meshes(files.mesh, max(f.mesh_frame for _, f, _ in frames) + 1)
    return Source(
        folder, source, calib_path, names, calib, sizes, images, units, leds, meshes, [None] * len(names), frames,
        mesh_units=UNITS[files.mesh_units], frame_masks=[camera_images(folder, n, "mask", required=False) for n in folders],
        leds_path=files.leds, mesh_files=[files.mesh], **moved,
        calib_files=[*calib_files, *([files.align_cameras] if files.align_cameras else [])],
    )  # fmt: skip


def import_easymocap(
    folder: str | Path,
    out: str | Path,
    config: ImportConfig,
    options: EasymocapOptions,
    files: TransformsOptions,
    overwrite: bool = False,
    shard=None,
    estimate_gains=None,
):
    config.validate()
    options.validate()
    source = read_easymocap(Path(folder), options, files)
    return import_capture(
        source, Path(out), config, {"units": files.units, "mesh_units": files.mesh_units}, overwrite, files, shard, estimate_gains
    )
