"""HumanOLAT's processed layout (ICCV 2025, MPI Informatics; its tools: the public repository TMT22/HumanOLAT), read
and written file by file as the dataset ships them:

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
centre, so that the importer (:mod:`gra_mi.capture.importer`) is tested on files as the dataset ships them.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import field_validator

from gra_mi.capture.dataset import load_observation
from gra_mi.core.color import srgb_decode, srgb_encode
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path, atomic_write_text, read_exr
from gra_mi.core.progress import progress
from gra_mi.core.schema import Finite, NonNegative, Positive, Record, intrinsic_matrix, matrix, parse, rigid_rotation
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


@dataclass
class CalibCamera:
    """One camera of an MPII ``.calib``: ``intrinsic`` is K divided by the image width (cy too), ``extrinsic`` the
    OpenCV camera-to-world 3 × 4 in the file's units (millimetres for HumanOLAT)."""

    intrinsic: np.ndarray  # (3, 3)
    extrinsic: np.ndarray  # (3, 4)
    distortion: list[float]
    focal_length: float = 0.0
    pixel_aspect: float = 1.0

    def k_matrix(self, width: int) -> np.ndarray:
        return self.intrinsic * np.array([[width, width, width], [width, width, width], [1, 1, 1]], float)


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


def write_points(path: Path, positions: np.ndarray) -> None:
    atomic_write_text(path, "".join(f"v {x:.8f} {y:.8f} {z:.8f}\n" for x, y, z in positions))


def read_points(path: Path) -> np.ndarray:
    if not path.is_file():
        raise GraMiInputError(path, "missing: HumanOLAT's LED positions (shared/LSX_light_positions_aligned.pc)")
    points = []
    for k, line in enumerate(path.read_text().splitlines()):
        words = line.split()
        if words[:1] != ["v"]:
            continue
        try:
            point = [float(w) for w in words[1:4]]
        except ValueError:
            point = []
        if len(point) != 3 or not np.isfinite(point).all():
            raise GraMiInputError(path, f"line {k + 1}: expected 'v x y z' with finite numbers, got '{line.strip()}'")
        points.append(point)
    if not points:
        raise GraMiInputError(path, "no 'v x y z' line")
    return np.array(points, float)


def write_spiral(path: Path, order: np.ndarray) -> None:
    atomic_write_text(path, "".join(f"{int(i) + 1}\n" for i in order))


def read_spiral(path: Path, leds: int) -> np.ndarray:
    """The firing order as 0-based LED indices, checked against the LED count."""
    if not path.is_file():
        raise GraMiInputError(path, "missing: HumanOLAT's OLAT firing order (shared/LSX3_light_z_spiral.txt)")
    try:
        order = np.array([int(w) for w in path.read_text().split()], int) - 1
    except ValueError:
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


def write_obj(folder: Path, positions: np.ndarray, uvs: np.ndarray, faces: np.ndarray, texture: np.ndarray | None) -> None:
    """model.obj (one ``vt`` per vertex; OBJ's v points up the image, so it is 1 − gra-mi's v), material.mtl and
    model.jpeg (the texture, row 0 at the top)."""
    from PIL import Image

    lines = ["mtllib material.mtl", "usemtl material0"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in positions]
    lines += [f"vt {u:.8f} {1.0 - v:.8f}" for u, v in uvs]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in faces]
    atomic_write_text(folder / "model.obj", "\n".join(lines) + "\n")
    atomic_write_text(folder / "material.mtl", "newmtl material0\nKd 1 1 1\nmap_Kd model.jpeg\n")
    if texture is not None:
        with atomic_path(folder / "model.jpeg") as tmp:
            Image.fromarray(np.round(srgb_encode(np.clip(texture, 0, 1)) * 255).astype(np.uint8)).save(tmp, format="JPEG", quality=95)


@dataclass
class ObjMesh:
    positions: np.ndarray  # (P, 3) in the file's units
    uvs: np.ndarray  # (T, 2) gra-mi's v (row 0 at the top)
    faces: np.ndarray  # (F, 3) position indices
    face_uvs: np.ndarray | None  # (F, 3) UV indices; None: the file has no UVs (the import generates an atlas)


def read_obj(path: Path) -> ObjMesh:
    """Triangles and polygons (fanned) with their ``vt`` corners; a mesh without faces is refused, one without UVs
    read with ``face_uvs`` None."""
    if not path.is_file():
        raise GraMiInputError(path, "missing: the pose's mesh (model/model.obj)")
    positions, uvs, faces, face_uvs = [], [], [], []
    for k, line in enumerate(path.read_text().splitlines()):
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "v":
                positions.append(_finite_numbers(words[1:4], 3))
            elif words[0] == "vt":
                uvs.append(_finite_numbers(words[1:3], 2))
            elif words[0] == "f":
                corners = [w.split("/") for w in words[1:]]
                # OBJ indices are 1-based; negative ones count back from the last defined (-1: the newest)
                p = [_obj_index(int(c[0]), len(positions)) for c in corners]
                t = [_obj_index(int(c[1]), len(uvs)) if len(c) > 1 and c[1] else 0 for c in corners]
                for j in range(1, len(p) - 1):
                    faces.append([p[0], p[j], p[j + 1]])
                    face_uvs.append([t[0], t[j], t[j + 1]])
        except (ValueError, IndexError):
            raise GraMiInputError(path, f"line {k + 1}: cannot read '{line.strip()}'") from None
    if not faces:
        raise GraMiInputError(path, "no faces: the pose's mesh must be a surface with UVs")
    f, ft = np.array(faces) - 1, np.array(face_uvs) - 1
    if not uvs and ft.max() < 0:
        return ObjMesh(np.array(positions, float), np.zeros((0, 2)), _checked_faces(path, f, len(positions)), None)
    if ft.min() < 0:
        raise GraMiInputError(path, "some faces have texture coordinates (f v/vt) and some none: give all or none")
    if ft.max() >= len(uvs):
        raise GraMiInputError(path, "a face refers to a texture coordinate the file does not define")
    st = one_uv_tile(path, np.array(uvs, float))
    return ObjMesh(np.array(positions, float), np.stack([st[:, 0], 1.0 - st[:, 1]], 1), _checked_faces(path, f, len(positions)), ft)


def _finite_numbers(words: list[str], count: int) -> list[float]:
    values = [float(w) for w in words]
    if len(values) != count or not np.isfinite(values).all():
        raise ValueError(f"expected {count} finite numbers")
    return values


def _obj_index(index: int, defined: int) -> int:
    return defined + index + 1 if index < 0 else index


def one_uv_tile(path: Path, st: np.ndarray) -> np.ndarray:
    """Texture coordinates (s, t) in [0, 1]², by gra-mi's rule for a mesh whose UVs lie outside it: UVs that all lie in
    one unit tile ([i, i + 1] × [j, j + 1], a UDIM tile) are moved into [0, 1]² (exact: nothing is lost); UVs spread
    over several tiles are refused (gra-mi's atlas is one tile) — never clamped, which would collapse the charts."""
    if st.size == 0:
        return st
    low = np.floor(st.min(axis=0))
    if np.any(st.max(axis=0) > low + 1):
        span = ", ".join(f"{a} {lo:g} … {hi:g}" for a, lo, hi in zip("st", st.min(axis=0), st.max(axis=0), strict=True))
        raise GraMiInputError(
            path,
            f"texture coordinates span several unit tiles ({span}); gra-mi's UV atlas is one [0, 1]² tile: repack the "
            "UVs into it (e.g. Blender's Pack Islands), or remove them and gra-mi generates an atlas",
            field="vt",
        )
    return st - low


def _checked_faces(path: Path, faces: np.ndarray, count: int) -> np.ndarray:
    if faces.min() < 0 or faces.max() >= count:
        raise GraMiInputError(path, "a face refers to a vertex the file does not define")
    return faces


# --------------------------------------------------------------------------------------------------------------
# Images
# --------------------------------------------------------------------------------------------------------------


def read_image(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(linear RGB float32, saturated pixels, alpha in [0, 1] or None): AVIF, PNG or JPEG, 8 or 16 bit, decoded with
    the exact sRGB curve (a pixel is saturated where a channel is at the top of its range); EXR as linear radiance
    (nothing saturates)."""
    from PIL import Image

    if path.suffix.lower() == ".exr":
        image = read_exr(path)
        return image[..., :3], np.zeros(image.shape[:2], bool), image[..., 3] if image.shape[2] == 4 else None
    try:
        with Image.open(path) as image:
            pixels = np.asarray(image if image.mode in ("I;16", "I;16B", "RGB", "RGBA") else image.convert("RGBA"))
    except (OSError, SyntaxError, ValueError) as exc:
        raise GraMiInputError(path, f"not a readable image ({exc})") from None
    top = 65535 if pixels.dtype == np.uint16 else 255
    alpha = pixels[..., 3].astype(np.float32) / top if pixels.ndim == 3 and pixels.shape[2] == 4 else None
    pixels = pixels[..., :3] if pixels.ndim == 3 else np.repeat(pixels[..., None], 3, axis=-1)
    rgb = srgb_decode(pixels.astype(np.float32) / top).astype(np.float32)
    return rgb, (pixels >= top).any(axis=-1), None if alpha is None or alpha.min() == 1 else alpha


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) from the file's header."""
    from PIL import Image

    if path.suffix.lower() == ".exr":
        import OpenEXR

        try:
            with OpenEXR.File(str(path), header_only=True) as exr:
                (x0, y0), (x1, y1) = exr.header()["dataWindow"]
            return int(x1 - x0 + 1), int(y1 - y0 + 1)
        except Exception as exc:  # OpenEXR raises several kinds for a damaged file
            raise GraMiInputError(path, f"not a readable EXR ({exc})") from None
    try:
        with Image.open(path) as image:
            return image.size
    except (OSError, SyntaxError, ValueError) as exc:
        raise GraMiInputError(path, f"not a readable image ({exc})") from None


def write_avif(path: Path, linear: np.ndarray) -> None:
    """8-bit sRGB AVIF at quality 100 with 4:4:4 chroma (a few levels of error on noise, none on smooth images)."""
    from PIL import Image

    pixels = np.round(srgb_encode(np.clip(linear[..., :3], 0, 1)) * 255).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(pixels).save(tmp, format="AVIF", quality=100, subsampling="4:4:4")


def write_mask(path: Path, mask: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray((mask > 0.5).astype(np.uint8) * 255).save(tmp, format="PNG")


def images_of(camera_dir: Path) -> dict[int, Path]:
    """Image number → file of one camera's folder; two files with one number (``000012.jpg`` and ``000012.png``) are
    refused naming both, where one would silently win."""
    found = {}
    for path in sorted(camera_dir.iterdir()) if camera_dir.is_dir() else []:
        match = NUMBER.search(path.name)
        if match:
            add_numbered(found, int(match.group(1)), path)
    return found


def add_numbered(found: dict[int, Path], number: int, path: Path) -> None:
    """``found[number] = path``, refusing a second file with the same number."""
    if number in found:
        raise GraMiInputError(path, f"has the image number {number} of {found[number].name} too: one image per number (remove one)")
    found[number] = path


def resample_columns(image: np.ndarray, width: int) -> np.ndarray:
    """Resample an image along x to ``width`` columns (area-weighted: each output column averages the input it
    covers), for cameras whose pixels are not square (fx ≠ fy)."""
    w = image.shape[1]
    edges = np.linspace(0.0, w, width + 1)
    weights = np.clip(np.minimum(edges[1:, None], np.arange(1, w + 1)[None]) - np.maximum(edges[:-1, None], np.arange(w)[None]), 0, None)
    weights /= weights.sum(axis=1, keepdims=True)
    return np.moveaxis(np.tensordot(weights, image, axes=([1], [1])), 0, 1).astype(image.dtype)  # BLAS, not an einsum loop


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
