"""A calibrated rig with a tracked mesh sequence, as EasyMocap (zju3dv) lays one out, into gra-mi's capture layout
through the import every source shares (:func:`gra_mi.capture.importer.import_capture`): the paper's kind of data
(a moving subject, interleaved uniformly lit and environment-lit frames).

```
DIR/intri.yml, DIR/extri.yml    OpenCV FileStorage YAML: names; K_<cam>, dist_<cam>; Rot_<cam> (or R_<cam>, Rodrigues)
                                and T_<cam>: world-to-camera, x_cam = Rot · x_world + T
DIR/images/<cam>/<frame, 6 digits>.{jpg,png,avif,exr}   undistorted (distortion is refused), masked or with alpha
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

import numpy as np

from gra_mi.capture.dataset import FrameLighting
from gra_mi.capture.humanolat import CalibCamera, image_size, read_points
from gra_mi.capture.importer import ImportConfig, Source, import_capture
from gra_mi.capture.transforms import UNITS, TransformsOptions, read_meshes
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import read_json

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".avif", ".exr")


@dataclass(kw_only=True)
class EasymocapOptions:
    """What an EasyMocap rig needs besides its calibration and images (:func:`import_easymocap`)."""

    lighting: Path | None = None
    """easymocap: JSON with each frame's split and lighting (uniform, led, envmap or pattern; docs/data-format.md).
    --mesh, --leds, --units and --mesh-units are read as for transforms."""

    def validate(self) -> None:
        if self.lighting is None:
            raise GraMiParameterError("lighting", "an EasyMocap rig needs each frame's lighting (--lighting FILE.json)")


def read_opencv_yaml(path: Path) -> dict:
    """An OpenCV FileStorage YAML file: ``!!opencv-matrix`` entries as arrays, ``names`` as a list, numbers as floats."""
    if not path.is_file():
        raise GraMiInputError(path, "missing: EasyMocap's calibration (intri.yml and extri.yml)")
    text, values = path.read_text(), {}
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


def _camera(intri: dict, extri: dict, name: str, images: dict[int, Path], folder: Path) -> tuple[CalibCamera, tuple[int, int]]:
    for source, key in ((folder / "intri.yml", f"K_{name}"), (folder / "extri.yml", f"T_{name}")):
        if key not in (intri if "intri" in source.name else extri):
            raise GraMiInputError(source, f"camera {name}: missing", field=key)
    dist = intri.get(f"dist_{name}", np.zeros(5)).ravel()
    if np.abs(dist).max() > 0:
        raise GraMiInputError(
            folder / "intri.yml", f"camera {name}: distortion {dist.tolist()}: undistort the images first", field=f"dist_{name}"
        )
    rot = extri[f"Rot_{name}"] if f"Rot_{name}" in extri else _rodrigues(extri.get(f"R_{name}", np.zeros(3)))
    c2w = np.concatenate([rot.T, -rot.T @ extri[f"T_{name}"].reshape(3, 1)], axis=1)
    width, height = image_size(next(iter(images.values())))
    intrinsic = intri[f"K_{name}"] / width
    intrinsic[2] = [0, 0, 1]
    return CalibCamera(intrinsic, c2w, dist.tolist()), (width, height)


def _images(folder: Path, name: str, kind: str = "images", required: bool = True) -> dict[int, Path]:
    """Frame number → file of one camera (``images/<cam>/`` or ``mask/<cam>/``)."""
    found = {}
    for path in sorted((folder / kind / name).glob("*")):
        if path.suffix.lower() in IMAGE_SUFFIXES and path.stem.isdigit():
            found[int(path.stem)] = path
    if not found and required:
        raise GraMiInputError(folder / kind / name, "no images (expected <frame, 6 digits>.jpg/.png/.avif/.exr)")
    return found


def _lighting(path: Path, i: int, entry: dict, leds: int) -> tuple[str, object]:
    """(FrameLighting kind, the importer's drive) of one entry of the lighting file."""
    where = f"frames[{i}]"
    if "uniform" in entry:
        return "pattern", ("uniform", float(entry["uniform"]))
    if "led" in entry:
        led = int(entry["led"])
        if not 0 <= led < leds:
            raise GraMiInputError(path, f"LED {led} out of range [0, {leds}) of --leds", field=f"{where}.led")
        return "pattern", led
    for kind in ("envmap", "pattern"):
        if kind in entry:
            file = path.parent / entry[kind]
            if not file.is_file():
                raise GraMiInputError(path, f"{file} not found", field=f"{where}.{kind}")
            return kind, ("pattern", file) if kind == "pattern" else file
    raise GraMiInputError(path, "expected one of uniform, led, envmap or pattern", field=where)


def read_easymocap(folder: Path, options: EasymocapOptions, files: TransformsOptions) -> Source:
    intri, extri = read_opencv_yaml(folder / "intri.yml"), read_opencv_yaml(folder / "extri.yml")
    names = intri.get("names") or extri.get("names")
    if not names:
        raise GraMiInputError(folder / "intri.yml", "no camera names", field="names")
    if files.mesh is None or files.leds is None:
        raise GraMiParameterError("mesh" if files.mesh is None else "leds", "an EasyMocap rig needs --mesh (a folder of OBJ) and --leds")
    units = UNITS[files.units]
    leds = read_points(files.leds) * units
    images = [_images(folder, n) for n in names]
    cameras = [_camera(intri, extri, n, found, folder) for n, found in zip(names, images, strict=True)]
    lighting = read_json(options.lighting)
    entries = lighting.get("frames") if isinstance(lighting, dict) else None
    if not isinstance(entries, list) or not entries:
        raise GraMiInputError(options.lighting, "expected an object with a non-empty 'frames' list", field="frames")
    frames = []
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict) or not isinstance(entry.get("frame"), int) or entry["frame"] < 0:
            raise GraMiInputError(
                options.lighting, "expected an object with the image's frame number (an integer >= 0)", field=f"frames[{i}].frame"
            )
        number, split = entry["frame"], entry.get("split", "train")
        if split not in ("train", "test"):
            raise GraMiInputError(options.lighting, f"expected train or test, got {split!r}", field=f"frames[{i}].split")
        kind, drive = _lighting(options.lighting, i, entry, len(leds))
        pose, sequence = int(entry.get("mesh_frame", number)), int(entry.get("sequence", 0))
        if kind == "envmap":
            lit = FrameLighting(i, split, sequence, "envmap", f"envmaps/{Path(drive).name}", pose=pose)
        else:
            lit = FrameLighting(i, split, sequence, "pattern", None, f"patterns/frame_{number:06d}.json", pose=pose)
        frames.append((number, lit, drive))
    meshes = read_meshes(files.mesh, max(f.mesh_frame for _, f, _ in frames) + 1)
    return Source(
        folder, "easymocap", folder / "extri.yml", [f"cam{n}" for n in names], [c for c, _ in cameras], [s for _, s in cameras],
        images, units, leds, meshes, [None] * len(names), frames, mesh_units=UNITS[files.mesh_units],
        frame_masks=[_images(folder, n, "mask", required=False) for n in names],
    )  # fmt: skip


def import_easymocap(
    folder: str | Path,
    out: str | Path,
    config: ImportConfig,
    options: EasymocapOptions,
    files: TransformsOptions,
    overwrite: bool = False,
    shard=None,
):
    config.validate()
    options.validate()
    source = read_easymocap(Path(folder), options, files)
    return import_capture(source, Path(out), config, {"units": files.units, "mesh_units": files.mesh_units}, overwrite, files, shard)
