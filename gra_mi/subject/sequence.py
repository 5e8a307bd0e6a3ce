"""Tracked mesh sequences: fixed topology and UVs, per-frame vertex positions and normals.

This is the paper's ``M_t`` (a person-specific tracked template mesh). On disk a sequence is a folder:

    sequence.npz        faces (F,3) int32, uvs (V,2) float32, vertices (T,V,3) float32, normals (T,V,3) float32,
                        vertex_colors (V,3) float32 (optional base albedo), fps, frame_labels (T,)
    frames/frame_0000.ply ... one binary PLY per frame (positions, normals, UVs, colours) for Mitsuba scenes

UVs follow docs/conventions.md: (u, v) ∈ [0,1]², as Mitsuba stores them; vertices are split along UV seams.
:func:`validate_sequence` rejects NaN vertices, changing vertex counts, out-of-range UVs and bad faces.

The per-frame arrays are stored uncompressed, so :func:`load_sequence` maps them from the file (``np.memmap``, read
only) instead of reading them: a frame is read from disk when it is used, and a sequence of tens of thousands of
frames costs no more memory than one of ten. Archives whose arrays are compressed (written before, or by another
tool's ``np.savez_compressed``) are read whole, as they must be.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import struct
import tempfile
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path
from gra_mi.core.progress import progress
from gra_mi.subject.geometry import split_uv_seams, vertex_normals  # noqa: F401  (part of this module's interface)
from gra_mi.subject.interchange import is_interchange_file, read_interchange

ALIGN = 64  # bytes: where a mapped array's data starts in its file (NumPy's own allocations are aligned so)
CHUNK_BYTES = 8 << 20  # a long sequence is validated (and read, where it is mapped) about this much at a time


@dataclass
class MeshSequence:
    faces: np.ndarray  # (F, 3) int32
    uvs: np.ndarray  # (V, 2) float32
    vertices: np.ndarray  # (T, V, 3) float32, metres, world frame
    normals: np.ndarray  # (T, V, 3) float32, unit
    fps: float = 24.0
    frame_labels: list[str] = field(default_factory=list)  # e.g. the motion clip of each frame
    vertex_colors: np.ndarray | None = None  # (V, 3) float32 base albedo for stock-BSDF previews
    origin: str = field(default="<sequence>", compare=False, repr=False)  # the file it was read from: what errors name

    @property
    def num_frames(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])


def validate_sequence(seq: MeshSequence, source: str = "<sequence>", every_frame: bool = True) -> None:
    """Raise :class:`GraMiInputError` unless the sequence is a well-formed tracked mesh. ``every_frame``: also read
    every frame's positions and normals (a chunk at a time); without, a command checks the frames it uses
    (:func:`check_frames`)."""
    arrays = {"vertices": seq.vertices, "normals": seq.normals, "uvs": seq.uvs, "faces": seq.faces}
    if seq.vertex_colors is not None:
        arrays["vertex_colors"] = seq.vertex_colors
    for name, array in arrays.items():
        kinds = "iu" if name == "faces" else "fiu"
        if np.asarray(array).dtype.kind not in kinds:
            raise GraMiInputError(
                source, f"expected {'integers' if name == 'faces' else 'numbers'}, got dtype {np.asarray(array).dtype}", field=name
            )
    v = seq.vertices
    if v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 1:
        raise GraMiInputError(source, f"expected (frames, vertices, 3), got {v.shape}", field="vertices")
    if seq.normals.shape != v.shape:
        raise GraMiInputError(source, f"normals {seq.normals.shape} do not match vertices {v.shape}", field="normals")
    if every_frame:
        for (start, vertices), (_, normals) in zip(frame_chunks(v), frame_chunks(seq.normals), strict=True):
            _check_frames(vertices, normals, start, source)
    if seq.uvs.shape != (v.shape[1], 2):
        raise GraMiInputError(source, f"expected ({v.shape[1]}, 2) UVs, got {seq.uvs.shape}", field="uvs")
    if not np.isfinite(seq.uvs).all() or seq.uvs.min() < 0 or seq.uvs.max() > 1:
        raise GraMiInputError(source, "UVs must be finite and in [0, 1]", field="uvs")
    f = np.asarray(seq.faces)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] < 1:
        raise GraMiInputError(source, f"expected (faces, 3) triangles, got {f.shape}", field="faces")
    if f.min() < 0 or f.max() >= v.shape[1]:
        raise GraMiInputError(source, f"face indices must lie in [0, {v.shape[1]})", field="faces")
    if seq.frame_labels and len(seq.frame_labels) != v.shape[0]:
        raise GraMiInputError(source, "one label per frame expected", field="frame_labels")
    if seq.vertex_colors is not None and seq.vertex_colors.shape != (v.shape[1], 3):
        raise GraMiInputError(source, f"expected ({v.shape[1]}, 3) colours", field="vertex_colors")


def check_frames(seq: MeshSequence, frames: list[int]) -> None:
    """The positions and normals of the ``frames`` a command uses (a sequence loaded without ``every_frame``): a
    clip of a long sequence reads its own frames only."""
    if len(set(frames)) * 8 > seq.num_frames:  # most of them: the chunked pass over every frame reads faster
        validate_sequence(seq, seq.origin)
        return
    for t in sorted(set(frames)):
        _check_frames(np.asarray(seq.vertices[t : t + 1]), np.asarray(seq.normals[t : t + 1]), t, seq.origin)


def check_frame(vertices: np.ndarray, normals: np.ndarray, frame: int, source: str) -> None:
    """One frame's positions and normals, (V, 3) each, already read: checked as :func:`check_frames` checks them."""
    _check_frames(vertices[None], normals[None], frame, source)


def _check_frames(vertices: np.ndarray, normals: np.ndarray, start: int, source: str) -> None:
    """Frames ``start``… of a sequence: finite positions, finite non-zero normals."""
    bad = ~np.isfinite(vertices).all(axis=(1, 2))
    if bad.any():
        raise GraMiInputError(source, f"non-finite (NaN/Inf) vertex positions in frame {start + int(np.argmax(bad))}", field="vertices")
    if not np.isfinite(normals).all():
        raise GraMiInputError(
            source, f"non-finite normals in frame {start + int(np.argmax(~np.isfinite(normals).all(axis=(1, 2))))}", field="normals"
        )
    flat = np.linalg.norm(normals, axis=-1) < 1e-6
    if flat.any():  # a zero normal shades black and turns no LED's light towards the surface
        frame = start + int(np.argmax(flat.any(axis=1)))
        raise GraMiInputError(
            source, f"{int(flat.sum())} zero-length vertex normals (first in frame {frame}); recompute them from the faces", field="normals"
        )


def frame_chunks(array: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """(first frame, frames) of a (T, ...) array, about :data:`CHUNK_BYTES` at a time. A mapped array's chunks are
    read from its file, not through the map: pages touched through a map stay in the process's resident memory until
    the system needs them back, so one pass over a long sequence would look like holding it whole."""
    frame = int(np.prod(array.shape[1:]))
    step = max(1, CHUNK_BYTES // max(frame * array.itemsize, 1))
    if not isinstance(array, np.memmap):
        yield from ((k, array[k : k + step]) for k in range(0, len(array), step))
        return
    with open(array.filename, "rb") as fh:
        for k in range(0, len(array), step):
            count = min(step, len(array) - k)
            fh.seek(array.offset + k * frame * array.itemsize)
            chunk = np.fromfile(fh, array.dtype, count * frame)
            if chunk.size != count * frame:
                raise GraMiInputError(array.filename, f"the file ends inside frame {k + chunk.size // frame} (truncated?)")
            yield k, chunk.reshape((count, *array.shape[1:]))


def extent(vertices: np.ndarray, source: str = "<sequence>") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lowest corner, highest corner, mean) of every position of a (T, V, 3) sequence, in float64, read a chunk of
    frames at a time (a mapped sequence is never read whole); a non-finite position is named (``source``: its file)."""
    low, high, total = np.full(3, np.inf), np.full(3, -np.inf), np.zeros(3)
    for start, chunk in frame_chunks(vertices):
        bad = ~np.isfinite(chunk).all(axis=(1, 2))
        if bad.any():
            raise GraMiInputError(source, f"non-finite (NaN/Inf) vertex positions in frame {start + int(np.argmax(bad))}", field="vertices")
        low = np.minimum(low, chunk.min(axis=(0, 1)))
        high = np.maximum(high, chunk.max(axis=(0, 1)))
        total += chunk.sum(axis=(0, 1), dtype=np.float64)
    return low, high, total / (vertices.shape[0] * vertices.shape[1])


# --------------------------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------------------------


def ply_name(frame: int) -> str:
    return f"frame_{frame:04d}.ply"


def write_ply(
    path: str | Path, positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray, colors: np.ndarray | None = None
) -> None:
    """Binary little-endian PLY that Mitsuba's ``ply`` shape reads (x y z nx ny nz u v [r g b])."""
    n = positions.shape[0]
    props = ["x", "y", "z", "nx", "ny", "nz", "u", "v"] + (["r", "g", "b"] if colors is not None else [])
    columns = [positions, normals, uvs] + ([colors] if colors is not None else [])
    vertex = np.ascontiguousarray(np.concatenate(columns, axis=1).astype("<f4"))
    face = np.empty(faces.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, faces
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {n}\n"
    header += "".join(f"property float {p}\n" for p in props)
    header += f"element face {faces.shape[0]}\nproperty list uchar int vertex_indices\nend_header\n"
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(vertex.tobytes())
            fh.write(face.tobytes())


def save_sequence(seq: MeshSequence, folder: str | Path, write_plys: bool = True) -> Path:
    """Write ``sequence.npz`` (and per-frame PLYs for scene files); returns the folder."""
    validate_sequence(seq)
    frames = ((seq.vertices[t], seq.normals[t]) for t in range(seq.num_frames))
    return write_sequence(folder, SequenceLayout.of(seq), frames, write_plys, seq.origin)


@dataclass
class SequenceLayout:
    """What every frame of a sequence shares: :func:`write_sequence` takes the frames themselves one at a time."""

    faces: np.ndarray  # (F, 3)
    uvs: np.ndarray  # (V, 2)
    num_frames: int
    fps: float = 24.0
    frame_labels: list[str] = field(default_factory=list)
    vertex_colors: np.ndarray | None = None

    @classmethod
    def of(cls, seq: MeshSequence) -> SequenceLayout:
        return cls(seq.faces, seq.uvs, seq.num_frames, seq.fps, seq.frame_labels, seq.vertex_colors)


def write_sequence(
    folder: str | Path,
    layout: SequenceLayout,
    frames: Iterable[tuple[np.ndarray, np.ndarray | None]],
    write_plys: bool = True,
    source: str = "<sequence>",
) -> Path:
    """Write ``sequence.npz`` (and per-frame PLYs) from ``frames``, (vertices, normals or None: computed from the
    faces) one at a time: a sequence of any length is written holding one frame (the vertices go straight into the
    archive, the normals through a file beside it). Each frame is checked as it comes; returns the folder."""
    folder = Path(folder)
    count, faces = layout.num_frames, np.asarray(layout.faces, np.int32)
    _checked_layout(layout, source)
    shape = (count, len(layout.uvs), 3)
    extra = {} if layout.vertex_colors is None else {"vertex_colors": np.asarray(layout.vertex_colors, np.float32)}
    with atomic_path(folder / "sequence.npz") as tmp, tempfile.TemporaryDirectory(dir=tmp.parent, prefix=".normals.") as scratch:
        # Stored, not compressed, so that load_sequence can map the frames (they compress by ~15 % only)
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as archive:
            _add_aligned(archive, "faces", faces)
            _add_aligned(archive, "uvs", np.asarray(layout.uvs, np.float32))
            normals_path = Path(scratch) / "normals.npy"
            with _aligned_member(archive, "vertices") as out, open(normals_path, "wb") as normals_out:
                for fh in (out, normals_out):
                    np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": shape})
                written = 0
                for t, (vertices, normals) in enumerate(progress(frames, "writing the subject", count)):
                    vertices, normals = _checked_frame(vertices, normals, faces, shape[1], t, count, source)
                    out.write(vertices.tobytes())
                    normals_out.write(normals.tobytes())
                    if write_plys:
                        write_ply(folder / "frames" / ply_name(t), vertices, normals, layout.uvs, faces, layout.vertex_colors)
                    written += 1
            if written != count:
                raise GraMiInputError(source, f"{written} frames given for a sequence of {count}", field="vertices")
            with _aligned_member(archive, "normals") as out, open(normals_path, "rb") as fh:
                shutil.copyfileobj(fh, out, 1 << 18)  # bounded: a long sequence copies in many small reads
            _add_aligned(archive, "fps", np.float32(layout.fps))
            _add_aligned(archive, "frame_labels", np.array(layout.frame_labels or [""] * count))
            for name, array in extra.items():
                _add_aligned(archive, name, array)
    return folder


def _checked_layout(layout: SequenceLayout, source: str) -> None:
    """The shared arrays checked as :func:`validate_sequence` checks them (on a stand-in frame)."""
    if layout.num_frames < 1:
        raise GraMiInputError(source, "a sequence needs at least one frame", field="vertices")
    if layout.frame_labels and len(layout.frame_labels) != layout.num_frames:
        raise GraMiInputError(source, "one label per frame expected", field="frame_labels")
    stand_in = np.zeros((1, len(layout.uvs), 3), np.float32)
    validate_sequence(
        MeshSequence(layout.faces, np.asarray(layout.uvs), stand_in, stand_in + 1, 1.0, [], layout.vertex_colors), source, False
    )


def _checked_frame(
    vertices, normals, faces: np.ndarray, num_vertices: int, t: int, num_frames: int, source: str
) -> tuple[np.ndarray, np.ndarray]:
    """Frame ``t`` as written: float32 little-endian, its normals computed from the faces where not given, checked."""
    if t >= num_frames:
        raise GraMiInputError(source, f"more frames given than the sequence's {num_frames}", field="vertices")
    vertices = np.asarray(vertices, np.float32)
    if vertices.shape != (num_vertices, 3):
        raise GraMiInputError(source, f"frame {t}: expected ({num_vertices}, 3) vertices, got {vertices.shape}", field="vertices")
    if not np.isfinite(vertices).all():
        check_frame(vertices, vertices, t, source)
    normals = vertex_normals(vertices, faces) if normals is None else np.asarray(normals, np.float32)
    if normals.shape != vertices.shape:
        raise GraMiInputError(source, f"frame {t}: normals {normals.shape} do not match vertices {vertices.shape}", field="normals")
    check_frame(vertices, normals, t, source)
    return np.ascontiguousarray(vertices, "<f4"), np.ascontiguousarray(normals, "<f4")


@contextlib.contextmanager
def _aligned_member(archive: zipfile.ZipFile, name: str) -> Iterator:
    """A stored ZIP64 entry ``name.npy`` whose data starts on a 64-byte boundary of the file, as NumPy aligns its own
    allocations: a mapped frame goes straight to Embree, which refuses vertex data that is not 4-byte aligned. The
    local header gets a padding record in its extra field (0xD935, as Android's zipalign writes); NumPy pads each
    .npy header to a multiple of 64 bytes itself."""
    info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    # the entry's data follows 30 bytes, its name, the padding record and the 20-byte ZIP64 record zipfile adds
    pad = -(archive.fp.tell() + 30 + len(info.filename) + 4 + 20) % ALIGN
    info.extra = struct.pack("<HH", 0xD935, pad) + bytes(pad)
    with archive.open(info, "w", force_zip64=True) as out:
        yield out


def _add_aligned(archive: zipfile.ZipFile, name: str, array: np.ndarray) -> None:
    with _aligned_member(archive, name) as out:
        np.lib.format.write_array(out, np.asanyarray(array), allow_pickle=False)


def _mapped_member(path: Path, archive: zipfile.ZipFile, name: str) -> np.ndarray | None:
    """The array ``name`` of an .npz mapped read-only from the file, or None where it cannot be (compressed, not
    little-endian float32 in C order, not aligned as :func:`_aligned_member` aligns it): a stored zip member is the
    .npy file's bytes as they are."""
    info = archive.getinfo(f"{name}.npy")
    if info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:  # compressed or encrypted
        return None
    with open(path, "rb") as fh:
        fh.seek(info.header_offset)
        local = fh.read(30)  # the local file header: its name and extra field lengths are at bytes 26–29
        if len(local) < 30 or local[:4] != b"PK\x03\x04":
            raise GraMiInputError(path, f"the zip entry {info.filename} has no local header", field=name)
        start = info.header_offset + 30 + int.from_bytes(local[26:28], "little") + int.from_bytes(local[28:30], "little")
        fh.seek(start)
        version = np.lib.format.read_magic(fh)
        reader = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
        shape, fortran_order, dtype = reader(fh)
        offset = fh.tell()
    if fortran_order or dtype != np.dtype("<f4"):
        return None
    held = start + info.file_size - offset  # a map is not bounded by the member: its header must match its size
    if held != int(np.prod(shape)) * dtype.itemsize:
        raise GraMiInputError(
            path, f"the array's header says {shape} float32 ({int(np.prod(shape)) * 4} bytes) but its entry holds {held}", field=name
        )
    if offset % ALIGN:  # mapped unaligned, a frame would reach Embree unaligned: read whole instead
        return None
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape)


def _frame_arrays(path: Path, data) -> dict[str, np.ndarray]:
    """vertices and normals of an opened .npz: mapped where stored, else read."""
    with zipfile.ZipFile(path) as archive:
        mapped = {key: _mapped_member(path, archive, key) for key in ("vertices", "normals")}
    return {key: data[key] if value is None else value for key, value in mapped.items()}


def load_sequence(folder: str | Path, every_frame: bool = True) -> MeshSequence:
    """Load and validate a sequence folder (or a ``sequence.npz`` path, or an avatar exported as USD / .glb).
    ``every_frame`` False: check the frames' positions and normals later, those a command uses (:func:`check_frames`)."""
    path = Path(folder)
    if is_interchange_file(path):
        seq = MeshSequence(**read_interchange(path), origin=str(path))
        validate_sequence(seq, str(path), every_frame)
        return seq
    if path.is_dir():
        path = path / "sequence.npz"
    elif path.is_file() and path.suffix.lower() != ".npz":
        raise GraMiInputError(path, "not a subject: expected a sequence folder, its sequence.npz, or an exported avatar (.usd*, .glb)")
    if not path.is_file():
        raise GraMiInputError(path, "file not found (generate a subject with `gra-mi subject`)")
    try:
        data = np.load(path, allow_pickle=False)
        for key in ("faces", "uvs", "vertices", "normals"):
            if key not in data:
                raise GraMiInputError(path, "missing array", field=key)
        seq = MeshSequence(
            faces=data["faces"],
            uvs=data["uvs"],
            **_frame_arrays(path, data),
            fps=float(data["fps"]) if "fps" in data else 24.0,
            frame_labels=[str(x) for x in data["frame_labels"]] if "frame_labels" in data else [],
            vertex_colors=data["vertex_colors"] if "vertex_colors" in data else None,
            origin=str(path),
        )
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:  # truncated or not an .npz at all
        if isinstance(exc, GraMiInputError):
            raise
        raise GraMiInputError(path, f"not a readable sequence archive ({exc})") from None
    validate_sequence(seq, str(path), every_frame)
    return seq


def sequence_from_frames(frames: list[np.ndarray], faces: np.ndarray, uvs: np.ndarray, source: str = "<frames>", **kwargs) -> MeshSequence:
    """Stack per-frame vertex arrays into a sequence, checking that the vertex count never changes."""
    counts = {np.asarray(f).shape[0] for f in frames}
    if len(counts) != 1:
        first = np.asarray(frames[0]).shape[0]
        bad = next(i for i, f in enumerate(frames) if np.asarray(f).shape[0] != first)
        raise GraMiInputError(
            source,
            f"vertex count changes across frames ({first} in frame 0, {np.asarray(frames[bad]).shape[0]} in frame {bad})",
            field="vertices",
        )
    vertices = np.stack([np.asarray(f, dtype=np.float32) for f in frames])
    seq = MeshSequence(
        faces=np.asarray(faces, np.int32), uvs=np.asarray(uvs, np.float32), vertices=vertices, normals=np.zeros_like(vertices), **kwargs
    )
    if not np.isfinite(vertices).all():
        validate_sequence(seq, source)
    seq.normals = vertex_normals(vertices, seq.faces)
    validate_sequence(seq, source)
    return seq


# --------------------------------------------------------------------------------------------------------------
# Tiny procedural subject (fast tests)
# --------------------------------------------------------------------------------------------------------------


def _uv_sphere(rings: int, segments: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit sphere with a UV seam: (rings+1)*(segments+1) vertices, UVs in [0,1]²."""
    theta = np.linspace(0.0, math.pi, rings + 1)
    phi = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    pos = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], axis=-1).reshape(-1, 3)
    uv = np.stack([p / (2.0 * math.pi), t / math.pi], axis=-1).reshape(-1, 2)
    faces = []
    for r in range(rings):
        for s in range(segments):
            a, b = r * (segments + 1) + s, (r + 1) * (segments + 1) + s
            if r > 0:
                faces.append([a, b, a + 1])
            if r < rings - 1:
                faces.append([a + 1, b, b + 1])
    return pos, uv, np.asarray(faces, np.int32)


WHOLE_FRAME_BYTES = {"tiny": 131072, "anny": 2 << 20}
"""The peak memory per frame of a subject's sequence made whole in memory (measured: 109 kB a tiny frame, 0.72 MB an
anny frame before it is saved), for checking a frame count against the machine before it is made."""


def tiny_subject(num_frames: int = 8, fps: float = 24.0) -> MeshSequence:
    """A torso (ellipsoid) and a swinging arm (capsule) that shadows it: ~450 triangles, a looping motion.

    The torso takes the left half of the UV atlas, the arm the right half.
    """
    torso_p, torso_uv, torso_f = _uv_sphere(10, 16)
    arm_p, arm_uv, arm_f = _uv_sphere(8, 10)
    torso_uv = torso_uv * [0.48, 0.96] + [0.01, 0.02]
    arm_uv = arm_uv * [0.48, 0.96] + [0.51, 0.02]
    faces = np.concatenate([torso_f, arm_f + len(torso_p)])
    uvs = np.concatenate([torso_uv, arm_uv])
    torso = torso_p * [0.22, 0.55, 0.15] + [0.0, 1.0, 0.0]
    arm_local = arm_p * [0.05, 0.32, 0.05] + [0.0, -0.32, 0.0]  # hangs from the shoulder at the origin
    shoulder = np.array([0.30, 1.42, 0.0])
    frames = []
    for t in range(num_frames):
        a = 0.12 + 0.1 * math.sin(2.0 * math.pi * t / num_frames)  # close to the body: shadows the torso
        c, s = math.cos(a), math.sin(a)
        rot_z = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # about +Z, swings the hand outward
        swing = 0.4 * math.sin(2.0 * math.pi * t / num_frames)
        cx, sx = math.cos(swing), math.sin(swing)
        rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
        frames.append(np.concatenate([torso, arm_local @ (rot_x @ rot_z).T + shoulder]))
    colors = np.concatenate([np.tile([0.55, 0.35, 0.25], (len(torso_p), 1)), np.tile([0.2, 0.3, 0.6], (len(arm_p), 1))])
    return sequence_from_frames(
        frames, faces, uvs, source="tiny_subject", fps=fps, frame_labels=["tiny"] * num_frames, vertex_colors=colors.astype(np.float32)
    )
