"""Files every source format shares, read and written as other tools write them: a camera's calibration record, OBJ
and PLY meshes with their texture coordinates, LED point files (``v x y z``), 8/16-bit sRGB, AVIF and EXR images and
mask PNGs. Each source format's own module (:mod:`~gra_mi.capture.humanolat`, :mod:`~gra_mi.capture.transforms`,
:mod:`~gra_mi.capture.easymocap`) reads its layout with these and fills a :class:`~gra_mi.capture.source.Source`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.lens import LensDistortion
from gra_mi.core.color import srgb_decode_levels, srgb_encode
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path, atomic_write_text, read_exr, read_text


@dataclass
class CalibCamera:
    """One camera of an MPII ``.calib``: ``intrinsic`` is K divided by the image width (cy too), ``extrinsic`` the
    OpenCV camera-to-world 3 × 4 in the file's units (millimetres for HumanOLAT). ``distortion``: the coefficients
    the file states (HumanOLAT's images are undistorted already: kept, not applied); ``lens``: a distortion the
    images still have, undone by the import."""

    intrinsic: np.ndarray  # (3, 3)
    extrinsic: np.ndarray  # (3, 4)
    distortion: list[float]
    focal_length: float = 0.0
    pixel_aspect: float = 1.0
    lens: LensDistortion | None = None

    def k_matrix(self, width: int) -> np.ndarray:
        return self.intrinsic * np.array([[width, width, width], [width, width, width], [1, 1, 1]], float)


def image_camera(name: str) -> tuple[str | None, str]:
    """(the folder an image path puts it in, else None; its stem): the names a rig's image path gives its camera
    (COLMAP's image names, a places file's lines). Either separator."""
    parts = Path(name.replace("\\", "/")).parts
    return (parts[-2] if len(parts) > 1 else None), Path(parts[-1]).stem if parts else ""


def write_points(path: Path, positions: np.ndarray) -> None:
    atomic_write_text(path, "".join(f"v {x:.8f} {y:.8f} {z:.8f}\n" for x, y, z in positions))


def read_points(path: Path) -> np.ndarray:
    points = []
    for k, line in enumerate(read_text(path, "lines 'v x y z'").splitlines()):
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


MIN_RELATIVE_GAIN = 0.01  # of the mean: an LED dimmer than this is taken for a mistake, not a calibration


def read_led_gains(path: Path, numbers: list[int]) -> np.ndarray:
    """(L, 3) linear RGB gains of the LEDs the source numbers ``numbers``, from a text file: line k (blank lines and
    ``#`` comments skipped) is LED k's gain, one number for every channel or ``r g b``. Normalised to a mean of 1 over
    those LEDs and channels, so that ``--led-intensity`` stays the mean LED's and only the gains' ratios count."""
    lines = read_text(path, "the LED gains (--led-gains), one line per LED").splitlines()
    gains = []
    for k, line in enumerate(lines):
        words = line.split("#")[0].split()
        if not words:
            continue
        try:
            values = [float(w) for w in words]
        except ValueError:
            values = []
        if len(values) not in (1, 3) or not np.isfinite(values).all() or min(values) < 0:
            raise GraMiInputError(path, f"line {k + 1}: expected one gain or 'r g b', finite and non-negative, got '{line.strip()}'")
        gains.append(values * 3 if len(values) == 1 else values)
    if len(gains) != max(numbers) + 1:
        raise GraMiInputError(path, f"{len(gains)} gains, but the source numbers {max(numbers) + 1} LEDs: one line per LED, in its order")
    return normalised_gains(np.array(gains)[numbers], numbers, path)


def write_led_gains(path: Path, gains: np.ndarray, numbers: list[int], measured: np.ndarray, source: Path) -> None:
    """(L, 3) gains of the LEDs numbered ``numbers`` as :func:`read_led_gains` reads them: a line per LED of the
    source's numbering, those the rig lacks (HumanOLAT's door LEDs) and those not ``measured`` 1, said in comments."""
    by_number = dict(zip(numbers, range(len(numbers)), strict=True))
    lines = [f"# LED gains (linear r g b, mean 1) estimated by gra-mi import --estimate-led-gains from {source}", "# line k: LED k"]
    for number in range(max(numbers) + 1):
        k = by_number.get(number)
        note = "  # not in the rig" if k is None else ("" if measured[k] else "  # not measured")
        r, g, b = (1.0, 1.0, 1.0) if k is None else gains[k]
        lines.append(f"{r:.6f} {g:.6f} {b:.6f}{note}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def normalised_gains(gains: np.ndarray, numbers: list[int], path: Path) -> np.ndarray:
    """(L, 3) gains of the LEDs numbered ``numbers`` over their mean; an LED below 1 % of the mean is refused."""
    mean = float(gains.mean())
    if mean <= 0:
        raise GraMiInputError(path, "every gain is 0: no LED lights")
    dim = np.flatnonzero(gains.min(axis=1) < MIN_RELATIVE_GAIN * mean)
    if dim.size:  # an envmap's share of such an LED would need a drive no stage has
        raise GraMiInputError(
            path, f"LED {numbers[dim[0]]}'s gain {gains[dim[0]].tolist()} is below {MIN_RELATIVE_GAIN:.0%} of the mean {mean:.4g}: "
            "an LED that barely lights cannot stand in for its share of an environment map; check the file",
        )  # fmt: skip
    return gains / mean


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
    positions, uvs, faces, face_uvs = [], [], [], []
    for k, line in enumerate(read_text(path, "a Wavefront OBJ mesh").splitlines()):
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


def read_image(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(linear RGB float32, saturated pixels, alpha in [0, 1] or None): AVIF, PNG or JPEG, 8 or 16 bit, decoded with
    the exact sRGB curve (a pixel is saturated where a channel is at the top of its range); EXR as linear radiance
    (nothing saturates)."""
    from PIL import Image

    if path.suffix.lower() == ".exr":
        image = read_exr(path)
        rgb = np.repeat(image, 3, axis=-1) if image.shape[2] == 1 else image[..., :3]  # a grey (Y) EXR: every channel
        bad = ~np.isfinite(rgb) | (rgb < 0)
        if bad.any():  # the source's, named here: a written capture would refuse it with no word of where it came from
            raise GraMiInputError(
                path, f"{int(bad.any(axis=-1).sum())} pixels are NaN, infinite or negative: captured radiance must be finite and "
                ">= 0 (clamp after black-level subtraction)",
            )  # fmt: skip
        alpha = image[..., 3] if image.shape[2] == 4 else None
        if alpha is not None and not (np.isfinite(alpha).all() and 0 <= alpha.min() and alpha.max() <= 1):
            raise GraMiInputError(path, "its alpha must be a coverage in [0, 1] (finite)")
        return rgb, np.zeros(image.shape[:2], bool), alpha
    if path.suffix.lower() == ".png" and _png_bit_depth(path) == 16:
        pixels = _read_png16(path)  # Pillow reads a 16-bit colour PNG as 8-bit: half its bits would be lost unsaid
    else:
        try:
            with Image.open(path) as image:
                pixels = np.asarray(image if image.mode in ("I;16", "I;16B", "RGB", "RGBA") else image.convert("RGBA"))
        except (OSError, SyntaxError, ValueError) as exc:
            raise GraMiInputError(path, f"not a readable image ({exc})") from None
    top = 65535 if pixels.dtype == np.uint16 else 255
    alpha = pixels[..., 3].astype(np.float32) / top if pixels.ndim == 3 and pixels.shape[2] == 4 else None
    pixels = pixels[..., :3] if pixels.ndim == 3 else np.repeat(pixels[..., None], 3, axis=-1)
    rgb = srgb_decode_levels(pixels.astype(pixels.dtype.newbyteorder("="), copy=False))  # exact: srgb_decode of level / top
    return rgb, (pixels >= top).any(axis=-1), None if alpha is None or alpha.min() == 1 else alpha


def _png_bit_depth(path: Path) -> int | None:
    """The bit depth a PNG's header states (None: not a PNG)."""
    with open(path, "rb") as fh:
        head = fh.read(26)  # signature (8), IHDR length and type (8), width, height (8), bit depth, colour type
    return head[24] if len(head) == 26 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR" else None


def _read_png16(path: Path) -> np.ndarray:
    """A 16-bit PNG's levels, every bit kept (OpenCV; its BGR order undone): (H, W) grey, (H, W, 3) or (H, W, 4)."""
    import cv2

    pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise GraMiInputError(path, "not a readable 16-bit PNG")
    if pixels.ndim == 3:  # BGR, BGRA (grey with alpha comes as BGRA too)
        pixels = pixels[..., [2, 1, 0, 3][: pixels.shape[2]]]
    return pixels


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


EXIF_ORIENTATIONS = {
    2: "mirrored",
    3: "rotated 180°",
    4: "flipped upside down",
    5: "mirrored and rotated 90° counter-clockwise",
    6: "rotated 90° clockwise",
    7: "mirrored and rotated 90° clockwise",
    8: "rotated 90° counter-clockwise",
}  # what a viewer does to the stored pixels before showing them, by EXIF's Orientation tag (1: nothing)


def exif_orientation(path: Path) -> int:
    """The EXIF Orientation tag of a JPEG, PNG or AVIF (1: none, or not one of its values). gra-mi reads pixels as
    stored, as COLMAP and OpenCV's calibration do; this says how a viewer would turn them."""
    from PIL import Image

    if path.suffix.lower() == ".exr":
        return 1
    try:
        with Image.open(path) as image:
            value = image.getexif().get(0x0112, 1)
    except (OSError, SyntaxError, ValueError):
        return 1  # read_image names an unreadable file
    return value if value in EXIF_ORIENTATIONS else 1


def orientation_hint(path: Path) -> str:
    """What to say of ``path``'s EXIF orientation where its pixels do not fit the calibration ('' if it has none)."""
    value = exif_orientation(path)
    if value == 1:
        return ""
    return (
        f"; {path.name} carries EXIF orientation {value} (shown {EXIF_ORIENTATIONS[value]}): gra-mi reads the pixels as stored, "
        "as COLMAP does; if the calibration was made on the images as shown, turn their pixels first (`mogrify -auto-orient`)"
    )


def read_mask(path: Path) -> np.ndarray:
    """A mask image as (H, W) bool: the subject where a pixel's grey level is above half its range, 8- or 16-bit
    (Pillow's own conversion to 8 bits clips 16-bit levels, so a level of 200 in 65,535 would count as the subject)."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            if image.mode in ("I;16", "I;16B", "I;16L", "I"):  # a 16-bit grey PNG
                return np.asarray(image) > 32767
            return np.asarray(image.convert("L")) > 127
    except (OSError, SyntaxError, ValueError) as exc:
        raise GraMiInputError(path, f"not a readable mask ({exc})") from None


def write_mask(path: Path, mask: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray((mask > 0.5).astype(np.uint8) * 255).save(tmp, format="PNG")


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
