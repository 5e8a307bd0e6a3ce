"""A tracked mesh as a source gives it: one file per mesh frame (OBJ or PLY, one topology), read when a frame is used,
so that an import of tens of thousands of frames holds one at a time (:class:`MeshFrames`).

The first file is read whole (its faces and UVs are every frame's). Later OBJ frames of a tracked sequence differ from
it only in their ``v`` lines: where every other line of a file is the first file's, its positions are read from those
lines alone (about 9× faster than a full parse); any other file is read whole and its topology compared."""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

import numpy as np

from gra_mi.capture.source_files import ObjMesh, one_uv_tile, read_obj
from gra_mi.core.errors import GraMiInputError

MESH_SUFFIXES = (".obj", ".ply")


class MeshFrames:
    """The mesh of each mesh frame, in the file's units: ``first`` whole, every frame's positions on demand
    (:meth:`positions`, checked: finite, the first's topology)."""

    def __init__(self, files: list[Path]):
        if not files:
            raise ValueError("a mesh sequence needs at least one file")  # a reader's mistake, not the user's
        self.files = list(files)
        self.first = read_mesh(self.files[0])
        self._topology = _obj_lines(self.files[0])[1] if self.files[0].suffix.lower() == ".obj" else None

    def __len__(self) -> int:
        return len(self.files)

    def normals(self, k: int) -> None:
        """A mesh file's normals are not kept: gra-mi computes them from the positions (a scene's are:
        :class:`~gra_mi.capture.mitsuba_capture.SceneMeshes`)."""
        return None

    def positions(self, k: int) -> np.ndarray:
        """(P, 3) float64 positions of mesh frame ``k``."""
        if k == 0:
            return _finite(self.files[0], np.asarray(self.first.positions, float))
        path = self.files[k]
        fast = _fast_positions(path, self._topology, len(self.first.positions)) if self._topology else None
        if fast is not None:
            return fast
        mesh = read_mesh(path)
        if mesh.positions.shape != self.first.positions.shape or not np.array_equal(mesh.faces, self.first.faces):
            raise GraMiInputError(
                path,
                f"mesh frame {k} has another topology than mesh frame 0 ({self.files[0].name}): a tracked sequence keeps its vertices and faces",
            )
        return _finite(path, np.asarray(mesh.positions, float))


def read_meshes(mesh: Path, poses: int) -> MeshFrames:
    """One mesh, or a folder of one per mesh frame (OBJ or PLY, in the numbers' order: ``frame_2`` before
    ``frame_10``): the first ``poses``."""
    if mesh.is_dir():
        files = mesh_files_in_order(mesh)
        if len(files) < poses:
            raise GraMiInputError(mesh, f"{len(files)} OBJ/PLY files, but the frames name {poses} mesh frames (mesh_frame)")
        return MeshFrames(files[:poses])
    if poses > 1:
        raise GraMiInputError(mesh, f"the frames name {poses} mesh frames (mesh_frame): give a folder of one mesh per frame")
    return MeshFrames([mesh])


def mesh_files_in_order(folder: Path) -> list[Path]:
    """A folder's OBJ and PLY files in their names' order with numbers compared as numbers (``frame_2`` before
    ``frame_10``, as a tracker numbers them unpadded); two names for one place (``frame_1.obj`` and ``frame_01.obj``,
    or ``.obj`` and ``.ply``) are refused naming both, where one would silently win."""
    keyed: dict[tuple, Path] = {}
    for path in (p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file()):
        key = tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", path.stem))
        if key in keyed:
            first, second = sorted((keyed[key].name, path.name))
            raise GraMiInputError(folder, f"{first} and {second} are one mesh frame: keep one")
        keyed[key] = path
    return [keyed[key] for key in sorted(keyed)]  # re.split alternates text and numbers: like compares with like


def read_mesh(path: Path) -> ObjMesh:
    """An OBJ (:func:`read_obj`) or a PLY (per-vertex ``s t`` / ``u v`` texture coordinates where it has them)."""
    if path.suffix.lower() == ".obj":
        return read_obj(path)
    if path.suffix.lower() != ".ply":
        raise GraMiInputError(path, f"expected an .obj or .ply mesh, got {path.suffix or 'no suffix'}")
    import trimesh

    try:
        mesh = trimesh.load(path, process=False, force="mesh")
    except Exception as exc:  # trimesh raises several kinds for a damaged file
        raise GraMiInputError(path, f"not a readable PLY ({exc})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if faces.size == 0:
        raise GraMiInputError(path, "no faces: the subject's mesh must be a surface")
    uv = getattr(getattr(mesh, "visual", None), "uv", None)
    if uv is None:
        return ObjMesh(np.asarray(mesh.vertices, float), np.zeros((0, 2)), faces, None)
    uv = one_uv_tile(path, np.asarray(uv, float))
    return ObjMesh(np.asarray(mesh.vertices, float), np.stack([uv[:, 0], 1.0 - uv[:, 1]], 1), faces, faces)


def _obj_lines(path: Path) -> tuple[list[bytes], bytes]:
    """An OBJ's ``v`` lines, and a digest of all its other lines (what makes its topology, and anything else)."""
    try:
        lines = path.read_bytes().splitlines()
    except OSError as exc:
        raise GraMiInputError(path, f"cannot read the mesh ({exc.strerror or exc})") from None
    positions = [line for line in lines if line[:2] == b"v "]
    rest = b"\n".join(line for line in lines if line[:2] != b"v ")
    return positions, hashlib.blake2b(rest, digest_size=16).digest()


def _fast_positions(path: Path, topology: bytes, count: int) -> np.ndarray | None:
    """The positions of an OBJ whose lines other than ``v`` are the first file's, each ``v`` line three finite numbers;
    None where it is not so (the file is then read whole, and any error named by its line)."""
    lines, digest = _obj_lines(path)
    if digest != topology or len(lines) != count:
        return None
    words = b" ".join(lines).split()
    # every fourth word a "v": each line is "v x y z" (a line with more or fewer numbers shifts the ones after it)
    if len(words) != 4 * count or words[0::4].count(b"v") != count:
        return None
    del words[0::4]
    try:
        positions = np.array(list(map(float, words))).reshape(count, 3)
    except ValueError:
        return None
    return positions if np.isfinite(positions).all() else None


def _finite(path: Path, positions: np.ndarray) -> np.ndarray:
    bad = ~np.isfinite(positions).all(axis=1)
    if bad.any():
        raise GraMiInputError(path, f"{int(bad.sum())} non-finite vertices (first: {int(np.argmax(bad))})")
    return positions
