"""A rig calibrated with COLMAP (its sparse model, text or binary, as COLMAP writes it) with a tracked mesh sequence,
into gra-mi's capture layout through the import every source shares (:func:`gra_mi.capture.importer.import_capture`).

```
DIR/sparse/0/cameras.{bin,txt}, images.{bin,txt}   the model (--colmap-model names another folder); nothing else of
                                                   it is read (points3D, rigs, frames)
DIR/images/<cam>/<frame, 6 digits>.{jpg,png,avif,exr}   every frame of each camera, as it took them
DIR/mask/<cam>/<frame, 6 digits>.png                     optional masks
```

Each registered image of the model names its camera: the folder it is in (``cam01/000000.jpg``, or
``images/cam01/000000.jpg`` where COLMAP was given the parent folder), or its stem where it has none (``cam01.jpg``).
A camera registered more than once (several frames of a fixed rig) must be at one place and of one COLMAP camera. The
model's poses are world-to-camera (x_cam = R(q) x_world + t, OpenCV's axes) and its K puts pixel centres at (column +
½, row + ½), as gra-mi's does. Its camera models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV
and OPENCV_FISHEYE, whose distortion is undone at import; the others are refused by name. A binary model is read where
both are there, as COLMAP reads one. What the model does not hold comes from the user as for EasyMocap: ``--mesh``,
``--leds``, ``--lighting``, in the model's frame and ``--units`` (or moved into the LEDs' frame by
``--align-cameras``, :mod:`gra_mi.capture.alignment`).
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import field_validator, model_validator

from gra_mi.capture.easymocap import EasymocapOptions, camera_images, needs_mesh_and_leds, rig_source
from gra_mi.capture.importer import import_capture
from gra_mi.capture.lens import LensDistortion
from gra_mi.capture.source import ImportConfig, Source
from gra_mi.capture.source_files import CalibCamera, image_camera, image_size
from gra_mi.capture.transforms import TransformsOptions
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.guard import path_component
from gra_mi.core.io import read_text
from gra_mi.core.schema import Finite, PositiveCount, Record, matrix, parse

# COLMAP's camera models by the id its binary files hold: (name, number of parameters)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5), 4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5), 8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12), 11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4), 13: ("DIVISION", 5), 14: ("SIMPLE_FISHEYE", 3), 15: ("FISHEYE", 4), 16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}  # fmt: skip
READ_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
SAME_PLACE_DEG = 0.05  # one camera registered twice: its two rotations within this …
SAME_PLACE_SHARE = 1e-4  # … and its two centres within this share of the rig's size


class ColmapCamera(Record):
    """One camera of cameras.txt / .bin: its model, its image's size and the model's parameters."""

    camera_id: int
    model: str
    width: PositiveCount
    height: PositiveCount
    params: list[Finite]

    @model_validator(mode="after")
    def _as_many_as_its_model(self) -> ColmapCamera:
        counts = dict(CAMERA_MODELS.values())
        if self.model not in counts:
            raise ValueError(f"camera model {self.model!r} is not one of COLMAP's")
        if len(self.params) != counts[self.model]:
            raise ValueError(f"{self.model} has {counts[self.model]} parameters, got {len(self.params)}")
        return self


class ColmapImage(Record):
    """One registered image of images.txt / .bin: its world-to-camera pose, its camera and its name."""

    image_id: int
    quaternion: matrix(4)  # (w, x, y, z): world-to-camera
    translation: matrix(3)
    camera_id: int
    name: str

    @field_validator("quaternion")
    @classmethod
    def _a_rotation(cls, q: np.ndarray) -> np.ndarray:
        largest = np.max(np.abs(q))
        if not largest > 0:
            raise ValueError("a rotation's quaternion cannot be 0")
        q = q / largest  # (first: the norm of components near 1e300 would overflow to inf, and q / inf to 0)
        return q / np.linalg.norm(q)

    def camera_to_world(self) -> np.ndarray:
        """(3, 4) OpenCV camera-to-world."""
        w, x, y, z = self.quaternion
        rot = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])  # fmt: skip
        return np.concatenate([rot.T, -rot.T @ self.translation.reshape(3, 1)], axis=1)


@dataclass(kw_only=True)
class ColmapOptions:
    """Where a COLMAP rig's model is (:func:`import_colmap`)."""

    colmap_model: Path | None = None
    """colmap: the folder of the sparse model (cameras.bin/.txt, images.bin/.txt). Default: DIR/sparse/0, else
    DIR/sparse, else DIR itself, the first that holds one."""


def model_folder(folder: Path, options: ColmapOptions) -> Path:
    tried = [options.colmap_model] if options.colmap_model else [folder / "sparse" / "0", folder / "sparse", folder]
    for place in tried:
        if any((place / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return place
    raise GraMiInputError(tried[0], f"no COLMAP model: expected cameras.bin or cameras.txt (and images) in {', '.join(map(str, tried))}")


def model_file(place: Path, kind: str) -> Path:
    """The model's ``kind`` file (cameras, images): binary where cameras.bin is there, as COLMAP reads a model."""
    return place / f"{kind}.{'bin' if (place / 'cameras.bin').is_file() else 'txt'}"


def read_model(place: Path) -> tuple[dict[int, ColmapCamera], list[ColmapImage]]:
    """The model's cameras by id and its registered images, binary where cameras.bin is there."""
    paths = [model_file(place, kind) for kind in ("cameras", "images")]
    binary = paths[0].suffix == ".bin"
    for path in paths:
        if not path.is_file():
            raise GraMiInputError(path, "missing: a COLMAP model holds cameras and images in one format (bin or txt)")
    cameras = _cameras_bin(paths[0]) if binary else _cameras_txt(paths[0])
    images = _images_bin(paths[1]) if binary else _images_txt(paths[1])
    for image in images:
        if image.camera_id not in cameras:
            raise GraMiInputError(paths[1], f"image {image.name!r} names camera {image.camera_id}, which {paths[0].name} has not")
    if not images:
        raise GraMiInputError(paths[1], "no registered images")
    return cameras, images


def _cameras_txt(path: Path) -> dict[int, ColmapCamera]:
    cameras = {}
    for number, line in enumerate(read_text(path, "COLMAP's cameras.txt").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split()
        if len(fields) < 4:
            raise GraMiInputError(path, "expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS…", field=f"line {number}")
        record = dict(zip(("camera_id", "model", "width", "height"), fields, strict=False)) | {"params": fields[4:]}
        camera = parse(ColmapCamera, record, path, f"camera {fields[0]}", line=number)
        cameras[camera.camera_id] = camera
    return cameras


def _images_txt(path: Path) -> list[ColmapImage]:
    """Two lines per image (its pose, then its 2D points, which may be empty), as COLMAP reads them."""
    lines, images, k = read_text(path, "COLMAP's images.txt").splitlines(), [], 0
    while k < len(lines):
        line, k = lines[k], k + 1
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split(maxsplit=9)
        if len(fields) < 10:
            raise GraMiInputError(path, "expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", field=f"line {k}")
        record = {
            "image_id": fields[0],
            "quaternion": fields[1:5],
            "translation": fields[5:8],
            "camera_id": fields[8],
            "name": fields[9].strip(),
        }
        images.append(parse(ColmapImage, record, path, f"image {fields[9].strip()!r}", line=k))
        k += 1  # (its 2D points)
    return images


class _Reader:
    """Little-endian values from a binary model file; a file that ends early says so."""

    def __init__(self, path: Path):
        self.path, self.data, self.at = path, path.read_bytes(), 0

    def take(self, fmt: str):
        size = struct.calcsize("<" + fmt)
        if self.at + size > len(self.data):
            raise GraMiInputError(self.path, f"truncated: it ends at byte {len(self.data)}, inside a record")
        values = struct.unpack_from("<" + fmt, self.data, self.at)
        self.at += size
        return values

    def name(self) -> str:
        end = self.data.find(b"\0", self.at)
        if end < 0:
            raise GraMiInputError(self.path, "truncated: an image name without its end")
        text, self.at = self.data[self.at : end].decode("utf-8", "replace"), end + 1
        return text


def _cameras_bin(path: Path) -> dict[int, ColmapCamera]:
    reader, cameras = _Reader(path), {}
    for _ in range(reader.take("Q")[0]):
        camera_id, model_id, width, height = reader.take("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise GraMiInputError(
                path, f"camera model id {model_id} is not one COLMAP wrote when gra-mi was made", field=f"camera {camera_id}"
            )
        model, count = CAMERA_MODELS[model_id]
        record = {"camera_id": camera_id, "model": model, "width": width, "height": height, "params": reader.take(f"{count}d")}
        cameras[camera_id] = parse(ColmapCamera, record, path, f"camera {camera_id}")
    return cameras


def _images_bin(path: Path) -> list[ColmapImage]:
    reader, images = _Reader(path), []
    for _ in range(reader.take("Q")[0]):
        image_id, *pose, camera_id = reader.take("I7dI")
        name = reader.name()
        points = reader.take("Q")[0]
        reader.at += points * struct.calcsize("<ddq")  # (its 2D points: x, y, the 3D point's id)
        if reader.at > len(reader.data):
            raise GraMiInputError(path, f"truncated: image {name!r}'s 2D points end past the file")
        record = {"image_id": image_id, "quaternion": pose[:4], "translation": pose[4:], "camera_id": camera_id, "name": name}
        images.append(parse(ColmapImage, record, path, f"image {name!r}"))
    return images


def camera_name(path: Path, image: ColmapImage) -> str:
    """The rig camera an image of the model belongs to: the folder its name puts it in, else its stem."""
    folder, stem = image_camera(image.name)
    return path_component(folder or stem, path, f"image {image.name!r}")


def rig_cameras(path: Path, images: list[ColmapImage]) -> dict[str, ColmapImage]:
    """One registered image per camera (its first); one registered twice must be of one COLMAP camera, in one place."""
    found: dict[str, ColmapImage] = {}
    for image in images:
        found.setdefault(camera_name(path, image), image)
    size = max(np.ptp(np.array([i.camera_to_world()[:, 3] for i in found.values()]), axis=0).max(), 1e-9)
    for image in images:
        first = found[camera_name(path, image)]
        a, b = first.camera_to_world(), image.camera_to_world()
        turned = math.degrees(math.acos(np.clip((np.trace(a[:, :3].T @ b[:, :3]) - 1) / 2, -1.0, 1.0)))
        moved = float(np.linalg.norm(a[:, 3] - b[:, 3]))
        if image.camera_id != first.camera_id or turned > SAME_PLACE_DEG or moved > SAME_PLACE_SHARE * size:
            raise GraMiInputError(
                path,
                f"{image.name!r} and {first.name!r} are one rig camera by their names, but of COLMAP cameras "
                f"{first.camera_id} and {image.camera_id}, {turned:.3g}° and {moved:.3g} apart: a rig's camera stays "
                "still (register one image per camera, or name each camera's images by its own folder)",
            )
    return found


def calib_camera(path: Path, camera: ColmapCamera, image: ColmapImage) -> CalibCamera:
    """gra-mi's camera of a model camera and one of its registered images (K as the model's: pixel centres at +½)."""
    if camera.model not in READ_MODELS:
        raise GraMiInputError(path, f"camera model {camera.model} is not one gra-mi reads: expected one of {', '.join(READ_MODELS)}",
                              field=f"camera {camera.camera_id}")  # fmt: skip
    params, where = camera.params, f"camera {camera.camera_id}"
    one_focal = camera.model.startswith("SIMPLE") or camera.model == "RADIAL"
    fx, fy = (params[0], params[0]) if one_focal else params[:2]
    cx, cy = params[1:3] if one_focal else params[2:4]
    if fx <= 0 or fy <= 0:
        raise GraMiInputError(path, f"its focal length must be positive, got {fx}, {fy}", field=where)
    rest = params[3:] if one_focal else params[4:]
    lens = {
        "SIMPLE_RADIAL": lambda: LensDistortion.of("radial-tangential", path, where, k1=rest[0]),
        "RADIAL": lambda: LensDistortion.of("radial-tangential", path, where, k1=rest[0], k2=rest[1]),
        "OPENCV": lambda: LensDistortion.opencv(rest, path, where),
        "FULL_OPENCV": lambda: LensDistortion.opencv(rest, path, where),  # (k4…k6: OpenCV's rational divisor)
        "OPENCV_FISHEYE": lambda: LensDistortion.of("fisheye", path, where, **dict(zip(("k1", "k2", "k3", "k4"), rest, strict=True))),
    }.get(camera.model, lambda: None)()
    intrinsic = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, camera.width]]) / camera.width
    return CalibCamera(intrinsic, image.camera_to_world(), list(rest), lens=lens)


def read_colmap(folder: Path, options: ColmapOptions, lighting: EasymocapOptions, files: TransformsOptions) -> Source:
    needs_mesh_and_leds(files, "a COLMAP rig")
    place = model_folder(folder, options)
    cameras, registered = read_model(place)
    found = rig_cameras(model_file(place, "images"), registered)
    names = sorted(found)
    unregistered = sorted(p.name for p in (folder / "images").glob("*") if p.is_dir() and p.name not in found)
    if unregistered:
        raise GraMiInputError(folder / "images", f"{', '.join(unregistered)}: no image of the model names these cameras (register "
                              "them, or move their folders out)")  # fmt: skip
    images = [camera_images(folder, name) for name in names]
    stated = [cameras[found[name].camera_id] for name in names]
    for name, files_of, camera in zip(names, images, stated, strict=True):
        size = image_size(next(iter(files_of.values())))
        if size != (camera.width, camera.height):
            raise GraMiInputError(folder / "images" / name, f"its images are {size[0]}×{size[1]}, its COLMAP camera "
                                  f"{camera.camera_id} {camera.width}×{camera.height}: resize them together")  # fmt: skip
    calib = [calib_camera(model_file(place, "cameras"), camera, found[name]) for name, camera in zip(names, stated, strict=True)]
    calibrated = (names, calib, [(c.width, c.height) for c in stated])
    return rig_source(
        folder, "colmap", model_file(place, "images"), names, calibrated, images, lighting.lighting, files, (model_file(place, "cameras"),)
    )


def import_colmap(folder, out, config: ImportConfig, options: ColmapOptions, lighting: EasymocapOptions, files: TransformsOptions,
                  overwrite: bool = False, shard=None, estimate_gains=None):  # fmt: skip
    config.validate()
    lighting.validate()
    source = read_colmap(Path(folder), options, lighting, files)
    return import_capture(
        source, Path(out), config, {"units": files.units, "mesh_units": files.mesh_units}, overwrite, files, shard, estimate_gains
    )


# --------------------------------------------------------------------------------------------------------------
# A capture written as a rig calibrated with COLMAP (`gra-mi capture --layout colmap`): the route tried end to end
# --------------------------------------------------------------------------------------------------------------

RECONSTRUCTION_FRAME = (0.37, (0.6, -1.1, 0.4), (2.5, -1.0, 0.7))  # (scale, rotation vector, shift) of the written model


def _numbers(values) -> str:
    return " ".join(f"{float(v):.17g}" for v in values)


def _lit(capture, stage, frame, root: Path) -> dict:
    """A capture frame's lighting as the lighting file states it: uniform, an OLAT (``led``: one LED at the stage's
    maximum), or its envmap or LED pattern copied beside the file."""
    import shutil

    from gra_mi.capture.dataset import UNIFORM_FRACTION
    from gra_mi.stage.lightstage import load_pattern

    if frame.kind == "uniform":
        return {"uniform": UNIFORM_FRACTION}  # as the capture lit it
    if frame.kind == "pattern":
        drive = load_pattern(stage, capture.folder / frame.pattern)
        lit = np.flatnonzero(drive.max(axis=1) > 0)
        if len(lit) == 1 and np.all(drive[lit[0]] == stage.max_led_intensity):
            return {"led": int(lit[0])}
    kind, file = ("envmap", frame.envmap) if frame.kind == "envmap" else ("pattern", frame.pattern)
    (root / f"{kind}s").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(capture.folder / file, root / f"{kind}s" / Path(file).name)
    return {kind: f"{kind}s/{Path(file).name}"}


def write_colmap_rig(capture, root: Path) -> Path:
    """A capture (``gra-mi capture``) as a rig calibrated with COLMAP comes to gra-mi, under ``root``: the sparse model
    (text; PINHOLE cameras) in a frame and scale of its own, as a reconstruction's is (:data:`RECONSTRUCTION_FRAME`),
    with ``places.txt`` (every camera's place in the LEDs' frame: ``--align-cameras``); each camera's frames as linear
    EXR and their masks; the mesh frames (``meshes/frame_NNNN.obj``), the LEDs (``leds.pc``), the lighting file
    (``lighting.json``, its envmaps and LED patterns beside it; ``led_gains.txt`` where the stage has gains), all in the
    capture's frame, in metres. Files already there are kept (an interrupted write resumes). Returns ``root``."""
    from scipy.spatial.transform import Rotation

    from gra_mi.capture.dataset import load_observation
    from gra_mi.capture.source_files import write_mask, write_obj, write_points
    from gra_mi.core.io import atomic_write_text, write_exr
    from gra_mi.core.progress import progress
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    stage, seq = load_calibration(capture.folder / "rig" / "calibration.json"), load_sequence(capture.folder / "subject")
    scale, turn, shift = (
        RECONSTRUCTION_FRAME[0],
        Rotation.from_rotvec(RECONSTRUCTION_FRAME[1]).as_matrix(),
        np.array(RECONSTRUCTION_FRAME[2]),
    )
    first = capture.frames[0].frame
    cameras, images = ["# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"], ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then its 2D points"]
    for k, cam in enumerate(stage.cameras, 1):
        cameras.append(f"{k} PINHOLE {cam.width} {cam.height} {_numbers([cam.fx, cam.fy, cam.cx, cam.cy])}")
        rotation = (turn @ cam.rotation).T  # world-to-camera, the model's frame
        x, y, z, w = Rotation.from_matrix(rotation).as_quat()
        t = -rotation @ (scale * turn @ cam.position + shift)
        images += [f"{k} {_numbers([w, x, y, z, *t])} {k} {cam.name}/{first:06d}.exr", ""]
    for name, lines in (("cameras", cameras), ("images", images), ("points3D", ["# (no points: gra-mi reads cameras and images)"])):
        atomic_write_text(root / "sparse" / "0" / f"{name}.txt", "\n".join(lines) + "\n")
    atomic_write_text(root / "places.txt", "# NAME X Y Z: each camera's place in the LEDs' frame (metres)\n"
                      + "".join(f"{c.name} {' '.join(f'{v:.9f}' for v in c.position)}\n" for c in stage.cameras))  # fmt: skip
    write_points(root / "leds.pc", stage.led_positions)
    if stage.led_gains is not None:  # (--led-gains led_gains.txt)
        atomic_write_text(root / "led_gains.txt", "".join(f"{r:.6g} {g:.6g} {b:.6g}\n" for r, g, b in stage.led_gains))
    for k in range(seq.num_frames):
        if not (root / "meshes" / f"frame_{k:04d}.obj").is_file():
            write_obj(root / "meshes", seq.vertices[k].astype(np.float64), seq.uvs, seq.faces, None)
            (root / "meshes" / "model.obj").replace(root / "meshes" / f"frame_{k:04d}.obj")
    entries = [{"frame": f.frame, "split": f.split, "sequence": f.sequence, "mesh_frame": f.mesh_frame} | _lit(capture, stage, f, root)
               for f in capture.frames]  # fmt: skip
    atomic_write_text(root / "lighting.json", json.dumps({"frames": entries}, indent=1) + "\n")
    jobs = [(cam, f.frame) for f in capture.frames for cam in stage.cameras]
    for cam, frame in progress(jobs, description="write COLMAP rig"):
        if not (root / "images" / cam.name / f"{frame:06d}.exr").is_file():
            image = load_observation(capture, cam.name, frame)
            write_mask(root / "mask" / cam.name / f"{frame:06d}.png", image[..., 3])
            write_exr(root / "images" / cam.name / f"{frame:06d}.exr", image[..., :3])  # last: its presence says both are done
    return root
