"""Image files: linear HDR EXR for data, sRGB PNG / MP4 for people.

Conventions (docs/conventions.md): images are ``(H, W, C)`` float32 arrays of linear Rec.709 radiance, row 0 at
the top. The sRGB transfer function (from colour-science) is applied only when writing previews.
Every writer is atomic: it writes a temporary file beside the target and renames it, so an interrupted run never
leaves a truncated file that a later run would mistake for a finished one.
"""

from __future__ import annotations

import contextlib
import logging
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from gra_mi.core.color import display_exposure, to_display
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.guard import check_output_path

logger = logging.getLogger(__name__)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds. A path outside the
    running command's output folders is refused first (:func:`gra_mi.core.guard.check_output_path`)."""
    path = Path(path)
    check_output_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)  # mkstemp makes 0600 files; give the usual permissions
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def read_text(path: Path, what: str) -> str:
    """A text file a source gives (UTF-8, a leading BOM dropped: a spreadsheet's export); a binary file (an image or an
    archive under a text file's name), a folder or nothing there is a :class:`GraMiInputError` naming it and ``what`` was
    expected."""
    if not path.is_file():
        raise GraMiInputError(path, f"{'a folder' if path.is_dir() else 'missing'}: expected {what}")
    try:
        return path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise GraMiInputError(path, f"not a text file ({exc.reason} at byte {exc.start}): expected {what}") from None


def read_json(path: str | Path, hint: str = ""):
    """Parse a JSON file; a missing, malformed or binary file, or an object with one key given twice with two values
    (which one was meant? Python's parser keeps the last unsaid), is a :class:`GraMiInputError` naming it."""
    import json

    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, f"file not found{hint}")

    def one_value_per_key(pairs: list) -> dict:
        found: dict = {}
        for key, value in pairs:
            if key in found and found[key] != value:
                raise GraMiInputError(path, f"malformed JSON: the key '{key}' is given twice, with two values")
            found[key] = value
        return found

    try:
        return json.loads(path.read_text(), object_pairs_hook=one_value_per_key)
    except json.JSONDecodeError as exc:
        raise GraMiInputError(path, f"malformed JSON ({exc})") from None
    except UnicodeDecodeError as exc:  # an image or an archive named .json
        raise GraMiInputError(path, f"malformed JSON: not UTF-8 text ({exc.reason} at byte {exc.start})") from None


def pyplot():
    """matplotlib's pyplot on the file-only Agg backend (no display needed): the one place that chooses it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 110) -> None:
    """Write a matplotlib figure as PNG atomically and close it."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    pyplot().close(fig)


def json_field(path: str | Path, data: dict, key: str, kind: type, low: float | None = None, where: str = ""):
    """``data[key]`` checked: present, of ``kind`` (int: not a bool or float; float: any finite number), >= ``low``.
    Errors name the file and the field (``where`` prefixes nested fields: ``sequences[3].``)."""
    import math

    if not isinstance(data, dict):
        raise GraMiInputError(path, f"expected a JSON object, got {type(data).__name__}", field=where.rstrip(".") or None)
    if key not in data:
        raise GraMiInputError(path, "missing", field=where + key)
    value = data[key]
    if kind is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    elif kind is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, kind)
    if not ok or (low is not None and value < low):
        expected = {float: "a finite number", int: "an integer", str: "a string", list: "a list"}.get(kind, kind.__name__)
        raise GraMiInputError(path, f"expected {expected}{f' >= {low}' if low is not None else ''}, got {value!r}", field=where + key)
    return value


def check_config_types(cls, fields: dict, path: str | Path) -> None:
    """Fields of a config dataclass read from JSON have their defaults' types (17 where an int is expected, not
    "17"), so a hand-edited file fails here, naming the field, not deep inside the model."""
    import dataclasses

    for f in dataclasses.fields(cls):
        if f.name not in fields:
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            continue
        if default is not None:
            json_field(path, fields, f.name, float if isinstance(default, float) else type(default))


def read_checkpoint_npz(path: str | Path) -> dict:
    """A checkpoint's arrays; a truncated or foreign file is named with how to start over (not a traceback)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            return dict(data)
    except Exception as exc:  # BadZipFile, EOFError, ValueError: cut short by a full disk or a killed copy
        raise GraMiInputError(path, f"unreadable checkpoint ({str(exc)[:100]}); rerun with --overwrite to start over") from None


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


# --------------------------------------------------------------------------------------------------------------
# EXR
# --------------------------------------------------------------------------------------------------------------


def write_exr(path: str | Path, image: np.ndarray, channel_names: list[str] | None = None) -> None:
    """Write an ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)`` float array as a float32 EXR; channels are
    Y, RGB or RGBA unless ``channel_names`` names them (data that is not a colour, e.g. a confidence map)."""
    import OpenEXR

    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in (1, 3, 4):
        raise ValueError(f"write_exr expects (H, W[, 1|3|4]), got {image.shape}")
    if channel_names is not None and len(channel_names) != image.shape[2]:
        raise ValueError(f"write_exr: {len(channel_names)} channel names for {image.shape[2]} channels")
    names = channel_names or {1: "Y", 3: "RGB", 4: "RGBA"}[image.shape[2]]
    channels = {name: np.ascontiguousarray(image[..., i]) for i, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))


def read_exr_channels(path: str | Path) -> dict[str, np.ndarray]:
    """Every channel of an EXR by name, as float32 (H, W) arrays: data that is not a colour (``confidence.exr``'s
    views, highlights, information)."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            return {name: np.asarray(ch.pixels, np.float32) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises plain RuntimeError on a damaged file
        raise GraMiInputError(path, f"not a readable OpenEXR file ({exc})") from None


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR as float32 ``(H, W, C)`` with C = 1, 3 or 4 (Y, RGB or RGBA).

    Any compression OpenEXR reads (ZIP, PIZ, DWAA, DWAB, ...), half or float pixels, R,G,B stored as separate
    channels or as the interleaved ``RGB``/``RGBA`` channel of OpenEXR's Python API, and layered files (Blender's
    ``ViewLayer.Combined.R``): the first layer with R, G, B is read.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "file not found")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}
    except Exception as exc:  # OpenEXR raises bare RuntimeErrors on corrupt files
        raise GraMiInputError(path, f"not a readable OpenEXR file ({exc})") from None
    layers = sorted({name.rsplit(".", 1)[0] + "." if "." in name else "" for name in channels}, key=len)
    for prefix in layers:
        for names in (("R", "G", "B", "A"), ("R", "G", "B"), ("Y",)):
            if all(prefix + n in channels for n in names):
                return np.stack([channels[prefix + n] for n in names], axis=-1).astype(np.float32)
    for name in ("RGBA", "RGB"):  # a file whose interleaved channel kept its name
        if name in channels and channels[name].ndim == 3:
            return channels[name].astype(np.float32)
    raise GraMiInputError(path, f"expected channels R,G,B[,A] or Y, found {sorted(channels)}")


def read_rgbe(path: str | Path) -> np.ndarray:
    """Read a Radiance ``.hdr``/``.pic`` file (RGBE, flat or run-length encoded scanlines) as float32 (H, W, 3).

    Only the standard ``-Y H +X W`` orientation (rows top to bottom) is accepted; other orientations name themselves.
    """
    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "file not found")
    data = path.read_bytes()
    if not data.startswith((b"#?RADIANCE", b"#?RGBE")):
        raise GraMiInputError(path, "not a Radiance HDR file (no '#?RADIANCE' signature)")
    end = data.find(b"\n\n")
    if end < 0:
        raise GraMiInputError(path, "truncated header")
    header = data[:end].decode("latin-1")
    if "FORMAT=" in header and "FORMAT=32-bit_rle_rgbe" not in header:
        raise GraMiInputError(path, "only FORMAT=32-bit_rle_rgbe is supported (not XYZE)")
    eol = data.find(b"\n", end + 2)
    size = data[end + 2 : eol].decode("latin-1").split()
    if len(size) != 4 or size[0] != "-Y" or size[2] != "+X":
        raise GraMiInputError(path, f"expected the resolution line '-Y H +X W', got {' '.join(size)!r}")
    try:
        height, width = int(size[1]), int(size[3])
    except ValueError:
        raise GraMiInputError(path, f"the resolution line '-Y H +X W' needs integer sizes, got {' '.join(size)!r}") from None
    if height < 1 or width < 1:
        raise GraMiInputError(path, f"the resolution line declares a {width}x{height} image; sizes must be >= 1")
    body = np.frombuffer(data, dtype=np.uint8, offset=eol + 1)
    row_bytes = min(4 * width, 4 + 4 * 2 * -(-width // 127))  # flat, or run-length encoded: 4 channels of 127-pixel runs
    if height * row_bytes > len(body):  # checked before the pixels are allocated (a corrupt header can declare terabytes)
        raise GraMiInputError(path, f"declares a {width}x{height} image but holds only {len(body)} bytes of pixels: corrupt or truncated")
    pixels = np.empty((height, width, 4), dtype=np.uint8)
    pos = 0
    try:
        for row in range(height):
            rle = (
                width >= 8
                and width < 32768
                and body[pos] == 2
                and body[pos + 1] == 2
                and (int(body[pos + 2]) << 8 | body[pos + 3]) == width
            )
            if not rle:  # flat scanline (old-style run lengths are not written by any current tool)
                pixels[row] = body[pos : pos + 4 * width].reshape(width, 4)
                pos += 4 * width
                continue
            pos += 4
            for channel in range(4):
                x = 0
                while x < width:
                    count = int(body[pos])
                    pos += 1
                    if count > 128:  # a run
                        count -= 128
                        pixels[row, x : x + count, channel] = body[pos]
                        pos += 1
                    else:
                        pixels[row, x : x + count, channel] = body[pos : pos + count]
                        pos += count
                    if count == 0 or x + count > width:
                        raise ValueError("bad run length")
                    x += count
    except (IndexError, ValueError) as exc:
        raise GraMiInputError(path, f"corrupt or truncated pixel data at row {row} ({exc})") from None
    exponent = pixels[..., 3].astype(np.int32)
    scale = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0)  # (mantissa + 0.5) / 256 * 2^(e - 128)
    return ((pixels[..., :3].astype(np.float64) + 0.5) * scale[..., None] * (exponent[..., None] > 0)).astype(np.float32)


def write_rgbe(path: str | Path, image: np.ndarray) -> None:
    """Write float RGB as a flat (uncompressed) Radiance ``.hdr`` file, atomically."""
    rgb = np.maximum(np.asarray(image, dtype=np.float64)[..., :3], 0.0)
    peak = rgb.max(axis=-1)
    mantissa, exponent = np.frexp(peak)
    scale = np.where(peak > 1e-32, mantissa * 256.0 / np.maximum(peak, 1e-300), 0.0)
    out = np.zeros(rgb.shape[:2] + (4,), dtype=np.uint8)
    out[..., :3] = np.clip(rgb * scale[..., None], 0, 255).astype(np.uint8)
    out[..., 3] = np.where(peak > 1e-32, exponent + 128, 0).astype(np.uint8)
    header = f"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y {rgb.shape[0]} +X {rgb.shape[1]}\n".encode("latin-1")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(header + out.tobytes())


HDR_SUFFIXES = (".exr", ".hdr", ".pic")


def read_hdr_image(path: str | Path) -> np.ndarray:
    """An HDR image from an OpenEXR or Radiance file, chosen by the suffix."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return read_exr(path)
    if path.suffix.lower() in (".hdr", ".pic"):
        return read_rgbe(path)
    what = "a folder" if path.is_dir() else f"of type '{path.suffix}'"
    raise GraMiInputError(path, f"{what}: expected an HDR image file ({', '.join(HDR_SUFFIXES)})")


# --------------------------------------------------------------------------------------------------------------
# Previews
# --------------------------------------------------------------------------------------------------------------


def to_srgb8(image: np.ndarray, exposure: float = 1.0) -> np.ndarray:
    """Linear Rec.709 radiance → 8-bit sRGB preview (:func:`gra_mi.core.color.to_display`: clipped, NaN black, +Inf
    white; alpha passed through linearly)."""

    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    out = [to_display(image, exposure)]
    if image.shape[2] == 4:
        out.append(np.clip(np.nan_to_num(image[..., 3:4]), 0.0, 1.0))
    return (np.concatenate(out, axis=2) * 255.0 + 0.5).astype(np.uint8)


def auto_exposure(image: np.ndarray) -> float:
    """Exposure that maps the 99th percentile of the (finite, positive) luminance to 1
    (:func:`gra_mi.core.color.display_exposure` at level 1)."""

    return display_exposure(image, level=1.0)


def write_png(path: str | Path, image: np.ndarray, exposure: float | None = 1.0) -> None:
    """Write an sRGB preview of a linear image; ``exposure=None`` picks one from the 99th percentile."""
    import imageio.v3 as iio

    if exposure is None:
        exposure = auto_exposure(image)
    with atomic_path(path) as tmp:
        iio.imwrite(tmp, to_srgb8(image, exposure), extension=".png")


def write_mp4(path: str | Path, frames: Sequence[np.ndarray], fps: float = 24.0, exposure: float = 1.0) -> bool:
    """Write linear frames as an H.264 MP4 preview (sizes padded to even numbers for the codec); False: not made
    (no ffmpeg, :data:`PREVIEWS_NOT_MADE`)."""
    return write_mp4_srgb8(path, (to_srgb8(frame, exposure)[..., :3] for frame in frames), fps)


# MP4 previews not written because this machine cannot encode them: path → why (a run's report lists them).
PREVIEWS_NOT_MADE: dict[str, str] = {}


def _ffmpeg_missing(path: Path) -> bool:
    """True where no ffmpeg can be found. An MP4 is a preview of frames that are always written as EXR and PNG, so
    the run goes on without it, saying so once and recording the file in :data:`PREVIEWS_NOT_MADE`."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as missing:
        if not PREVIEWS_NOT_MADE:
            logger.warning("MP4 previews are not written: no ffmpeg (%s); install imageio-ffmpeg to have them", missing)
        PREVIEWS_NOT_MADE[str(path)] = "no ffmpeg (pip install imageio-ffmpeg)"
        return True
    return False


def write_mp4_srgb8(path: str | Path, frames, fps: float = 24.0) -> bool:
    """Write 8-bit sRGB frames (H, W, 3), e.g. the PNG previews read back, as an H.264 MP4; False: not made."""
    with Mp4Stream(path, fps) as stream:
        for rgb in frames:
            stream.append_srgb8(rgb)
    return stream.made


class Mp4Stream:
    """An MP4 written frame by frame (long videos never sit in memory); renamed into place on a clean close. Where
    no ffmpeg can be found, nothing is written (:func:`_ffmpeg_missing`)."""

    def __init__(self, path: str | Path, fps: float = 24.0):
        import imageio.v2 as iio2

        self._writer = None
        if _ffmpeg_missing(Path(path)):
            return
        self._atomic = atomic_path(path)
        tmp = self._atomic.__enter__()
        self._writer = iio2.get_writer(str(tmp), format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)

    def append(self, frame: np.ndarray, exposure: float = 1.0) -> None:
        self.append_srgb8(to_srgb8(frame, exposure)[..., :3])

    def append_srgb8(self, rgb: np.ndarray) -> None:
        h, w = rgb.shape[:2]
        if self._writer is not None:
            self._writer.append_data(np.pad(rgb[..., :3], ((0, h % 2), (0, w % 2), (0, 0)), mode="edge"))

    @property
    def made(self) -> bool:
        """False where no ffmpeg could be found (nothing is written)."""
        return self._writer is not None

    def __enter__(self) -> Mp4Stream:
        return self

    def __exit__(self, *exc) -> None:
        if self._writer is None:
            return
        self._writer.close()
        self._atomic.__exit__(*exc)
