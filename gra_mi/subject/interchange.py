"""Read an animated avatar back from USD or glTF binary, as ``gra-mi export`` writes it and as DCC tools (Blender,
Maya, Houdini) write it after an edit, so that it can come back for relighting.

- **USD** (.usda / .usdc / .usd / .usdz, read by usd-core): the one ``Mesh`` under the default prim (or the stage's only
  mesh); its points at each authored time sample (frame t = the t-th sample) in world space (the prim's transforms
  applied), converted to gra-mi's frame (Y up, metres) from the stage's ``upAxis`` and ``metersPerUnit``; polygons
  fan-triangulated; ``st`` (or the only texture-coordinate primvar) per vertex or per face corner (then vertices are
  split along UV seams); ``st`` starts at the image's bottom-left, so v = 1 − t.
- **glTF binary** (.glb): the one triangle primitive of the scene's one mesh; its node's world transform; morph
  targets played by the animation of its weights (one frame per keyframe time, fps from their spacing).

Normals are recomputed from the faces (area-weighted), as ``gra-mi subject`` computes them.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.subject.geometry import split_uv_seams, vertex_normals

USD_SUFFIXES = (".usda", ".usdc", ".usd", ".usdz")
GLTF_SUFFIXES = (".glb",)
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # (x, y, z) → (x, z, −y)


def is_interchange_file(path: str | Path) -> bool:
    return Path(path).suffix.lower() in USD_SUFFIXES + GLTF_SUFFIXES


def read_interchange(path: str | Path) -> dict[str, np.ndarray | float]:
    """The arrays of a :class:`~gra_mi.subject.sequence.MeshSequence` (faces, uvs, vertices, normals, fps) read from a
    USD or .glb file (``load_sequence`` validates them)."""
    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "file not found")
    return _read_usd(path) if path.suffix.lower() in USD_SUFFIXES else _read_glb(path)


def _sequence(frames: np.ndarray, faces: np.ndarray, uvs: np.ndarray, fps: float) -> dict:
    frames = np.asarray(frames, np.float32)
    normals = vertex_normals(frames, faces)
    return {"faces": faces.astype(np.int32), "uvs": uvs.astype(np.float32), "vertices": frames, "normals": normals, "fps": fps}


def _fan(counts: np.ndarray, indices: np.ndarray, path: Path) -> np.ndarray:
    """Corner index of each triangle's corners, (F, 3), from polygons of ``counts`` corners (fan triangulation)."""
    if counts.size == 0 or counts.min() < 3 or counts.sum() != indices.size:
        raise GraMiInputError(path, "faceVertexCounts must be ≥ 3 each and add up to faceVertexIndices' length", field="faceVertexCounts")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    corners = [
        np.stack([s + np.zeros(n - 2, int), s + np.arange(1, n - 1), s + np.arange(2, n)], axis=1)
        for s, n in zip(starts, counts, strict=True)
    ]
    return np.concatenate(corners)


# --------------------------------------------------------------------------------------------------------------
# USD
# --------------------------------------------------------------------------------------------------------------


def _usd_mesh(stage, path: Path):
    from pxr import UsdGeom

    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    meshes = [p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and p.GetPath().HasPrefix(root.GetPath())]
    if len(meshes) != 1:
        names = ", ".join(str(m.GetPath()) for m in meshes[:5]) or "none"
        raise GraMiInputError(
            path, f"expected one Mesh under {root.GetPath()}, found {len(meshes)} ({names}); merge the body into one mesh"
        )
    return UsdGeom.Mesh(meshes[0])


def _usd_uvs(mesh, corners: np.ndarray, indices: np.ndarray, num_points: int, path: Path):
    """(faces, position index per new vertex, uvs per new vertex) from the texture coordinates."""
    from pxr import Sdf, UsdGeom

    primvars = UsdGeom.PrimvarsAPI(mesh)
    coords = [p for p in primvars.GetPrimvars() if p.GetTypeName() in (Sdf.ValueTypeNames.TexCoord2fArray, Sdf.ValueTypeNames.Float2Array)]
    chosen = next((p for p in coords if p.GetPrimvarName() == "st"), coords[0] if len(coords) == 1 else None)
    if chosen is None:
        raise GraMiInputError(
            path, f"no texture coordinates: expected a primvar 'st' (found {[p.GetPrimvarName() for p in coords]})", field="primvars:st"
        )
    values = np.asarray(chosen.Get(), np.float64).reshape(-1, 2)
    if chosen.IsIndexed():
        values = values[np.asarray(chosen.GetIndices(), np.int64)]
    uv = np.stack([values[:, 0], 1.0 - values[:, 1]], axis=1)
    faces = indices[corners]
    interpolation = chosen.GetInterpolation()
    if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) and len(uv) == num_points:
        return faces, np.arange(num_points), uv
    if interpolation == UsdGeom.Tokens.faceVarying and len(uv) == indices.size:
        # corners that share a position and a UV value share a vertex (writers index UVs per corner or not at all)
        unique_uv, uv_index = np.unique(uv, axis=0, return_inverse=True)
        new_faces, position_of, uv_of = split_uv_seams(faces, uv_index.reshape(-1)[corners])
        return new_faces, position_of, unique_uv[uv_of]
    raise GraMiInputError(path, f"'{chosen.GetPrimvarName()}' has {len(uv)} values with {interpolation} interpolation", field="primvars:st")


def _bake_skinning(stage, mesh) -> list[float]:
    """A skinned mesh or one animated by blend shapes (UsdSkel: how Blender writes shape keys) baked into time-sampled
    points by usd-core's own ``UsdSkel.BakeSkinning``, in the session layer (the file is not touched); its time codes
    are the animation's. [] for a mesh that is not skinned."""
    from pxr import UsdSkel

    if not UsdSkel.BindingAPI(mesh.GetPrim()).GetSkeleton() and not UsdSkel.Root.Find(mesh.GetPrim()):
        return []
    animations = [p for p in stage.Traverse() if p.IsA(UsdSkel.Animation)]
    times = sorted({t for p in animations for a in p.GetAttributes() for t in a.GetTimeSamples()})
    stage.SetEditTarget(stage.GetSessionLayer())
    if not times or not UsdSkel.BakeSkinning(stage.Traverse()):
        return []
    return times


def _read_usd(path: Path) -> dict:
    from pxr import Tf, Usd, UsdGeom

    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        raise GraMiInputError(path, f"not a readable USD file ({str(exc).strip().splitlines()[-1]})") from None
    if stage is None:
        raise GraMiInputError(path, "not a readable USD file")
    mesh = _usd_mesh(stage, path)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], np.int64)
    corners = _fan(counts, indices, path)
    if mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded:
        corners = corners[:, ::-1]
    times = _bake_skinning(stage, mesh) or mesh.GetPointsAttr().GetTimeSamples() or [Usd.TimeCode.Default()]
    to_gra_mi = UsdGeom.GetStageMetersPerUnit(stage) * (Z_UP_TO_Y_UP if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z else np.eye(3))
    frames = []
    for t in times:
        points = np.asarray(mesh.GetPointsAttr().Get(t), np.float64).reshape(-1, 3)
        world = np.asarray(mesh.ComputeLocalToWorldTransform(t), np.float64)  # row-vector convention
        frames.append((points @ world[:3, :3] + world[3, :3]) @ to_gra_mi.T)
    num_points = frames[0].shape[0]
    if indices.size and (indices.min() < 0 or indices.max() >= num_points):
        raise GraMiInputError(path, f"face indices must lie in [0, {num_points})", field="faceVertexIndices")
    faces, position_of, uvs = _usd_uvs(mesh, corners, indices, num_points, path)
    return _sequence(np.stack(frames)[:, position_of], faces, uvs, float(stage.GetTimeCodesPerSecond()))


# --------------------------------------------------------------------------------------------------------------
# glTF binary
# --------------------------------------------------------------------------------------------------------------

COMPONENTS = {5120: "i1", 5121: "u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def _glb_chunks(path: Path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    if len(data) < 20 or data[:4] != b"glTF":
        raise GraMiInputError(path, "not a glTF binary file (no 'glTF' magic)")
    _, version, length = struct.unpack("<4sII", data[:12])
    if version != 2 or length != len(data):
        raise GraMiInputError(path, f"glTF version {version}, {len(data)} of {length} bytes: expected a whole glTF 2.0 file")
    size, kind = struct.unpack("<I4s", data[12:20])
    if kind != b"JSON" or 20 + size > len(data):
        raise GraMiInputError(path, "the first chunk is not a whole JSON chunk")
    try:
        gltf = json.loads(data[20 : 20 + size])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise GraMiInputError(path, f"unreadable JSON chunk ({exc})") from None
    rest = data[20 + size :]
    binary = rest[8 : 8 + struct.unpack("<I", rest[:4])[0]] if len(rest) >= 8 and rest[4:8] == b"BIN\0" else b""
    return gltf, binary


def _view_rows(gltf: dict, binary: bytes, view_index: int, offset: int, dtype: np.dtype, width: int, count: int, where: str, path: Path):
    """``count`` rows of ``width`` ``dtype`` values from a buffer view (its stride honoured), as float64."""
    view = gltf["bufferViews"][view_index]
    if view.get("buffer", 0) != 0:
        raise GraMiInputError(path, f"{where}: only data in the binary chunk is read", field="bufferViews")
    start = int(view.get("byteOffset", 0)) + offset
    stride = int(view.get("byteStride", 0)) or dtype.itemsize * width
    end = start + stride * (count - 1) + dtype.itemsize * width
    if count < 1 or end > len(binary):
        raise GraMiInputError(path, f"{where} runs past the binary chunk (truncated file?)", field="accessors")
    raw = np.frombuffer(binary, np.uint8, end - start, start)
    rows = np.lib.stride_tricks.as_strided(raw, (count, dtype.itemsize * width), (stride, 1))
    return np.ascontiguousarray(rows).view(dtype).reshape(count, width).astype(np.float64)


def _accessor(gltf: dict, binary: bytes, index: int, path: Path) -> np.ndarray:
    """An accessor's values, (count, width): from its buffer view, or zeros without one, then its sparse
    substitutions (Blender writes morph targets that way)."""
    where = f"accessor {index}"
    try:
        acc = gltf["accessors"][index]
        dtype, width, count = np.dtype(COMPONENTS[acc["componentType"]]), WIDTH[acc["type"]], int(acc["count"])
        if "bufferView" in acc:
            values = _view_rows(gltf, binary, acc["bufferView"], int(acc.get("byteOffset", 0)), dtype, width, count, where, path)
        else:
            values = np.zeros((count, width))
        if "sparse" in acc:
            sparse = acc["sparse"]
            n, ind, val = int(sparse["count"]), sparse["indices"], sparse["values"]
            rows = _view_rows(
                gltf,
                binary,
                ind["bufferView"],
                int(ind.get("byteOffset", 0)),
                np.dtype(COMPONENTS[ind["componentType"]]),
                1,
                n,
                where,
                path,
            )
            rows = rows[:, 0].astype(np.int64)
            if rows.min() < 0 or rows.max() >= count:
                raise GraMiInputError(path, f"{where}: sparse indices outside [0, {count})", field="accessors")
            values[rows] = _view_rows(gltf, binary, val["bufferView"], int(val.get("byteOffset", 0)), dtype, width, n, where, path)
        return values
    except (KeyError, IndexError, TypeError, ValueError) as exc:
        if isinstance(exc, GraMiInputError):
            raise
        raise GraMiInputError(path, f"{where} is malformed ({exc!r})", field="accessors") from None


def _node_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], np.float64).reshape(4, 4).T  # column-major
    x, y, z, w = node.get("rotation", [0.0, 0.0, 0.0, 1.0])
    rotation = np.array(
        [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
         [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
         [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    )  # fmt: skip
    m = np.eye(4)
    m[:3, :3] = rotation * np.asarray(node.get("scale", [1.0, 1.0, 1.0]))
    m[:3, 3] = node.get("translation", [0.0, 0.0, 0.0])
    return m


def _mesh_node(gltf: dict, path: Path) -> tuple[int, np.ndarray]:
    """(node index, its world matrix) of the one node that holds a mesh, or, among several, the one gra-mi's export
    marks as the avatar (``extras.gra_mi``: the others are a scene's set)."""
    nodes = gltf.get("nodes", [])
    parent = {child: k for k, node in enumerate(nodes) for child in node.get("children", [])}
    holders = [k for k, node in enumerate(nodes) if "mesh" in node]
    marked = [k for k in holders if isinstance(nodes[k].get("extras"), dict) and "gra_mi" in nodes[k]["extras"]]
    holders = marked if len(holders) > 1 and len(marked) == 1 else holders
    if len(holders) != 1:
        names = ", ".join(repr(nodes[k].get("name", k)) for k in holders[:8])
        raise GraMiInputError(
            path, f"expected one node with a mesh, found {len(holders)} ({names}); merge the body into one mesh", field="nodes"
        )
    world, k = np.eye(4), holders[0]
    while k is not None:
        world = _node_matrix(nodes[k]) @ world
        k = parent.get(k)
    return holders[0], world


def _morph_frames(gltf, binary, node: int, base: np.ndarray, targets: list[np.ndarray], path: Path) -> tuple[np.ndarray, float]:
    """The frames the weights animation of ``node`` plays (the base pose alone without one) and their rate."""
    for animation in gltf.get("animations", []):
        for channel in animation.get("channels", []):
            if channel.get("target", {}).get("node") == node and channel["target"].get("path") == "weights":
                sampler = animation["samplers"][channel["sampler"]]
                times = _accessor(gltf, binary, sampler["input"], path)[:, 0]
                weights = _accessor(gltf, binary, sampler["output"], path).reshape(len(times), -1)
                if weights.shape[1] != len(targets):  # CUBICSPLINE keeps in/out tangents around each value
                    weights = weights.reshape(len(times), 3, len(targets))[:, 1]
                frames = base[None] + np.einsum("tk,kvc->tvc", weights, np.stack(targets)) if targets else base[None]
                fps = round(1.0 / float(np.median(np.diff(times))), 3) if len(times) > 1 else 24.0  # keyframes are float32 seconds
                return frames, fps
    return base[None], 24.0


def _read_glb(path: Path) -> dict:
    gltf, binary = _glb_chunks(path)
    node, world = _mesh_node(gltf, path)
    try:
        primitives = gltf["meshes"][gltf["nodes"][node]["mesh"]]["primitives"]
    except (KeyError, IndexError, TypeError):
        raise GraMiInputError(path, "the mesh node names no mesh", field="meshes") from None
    if len(primitives) != 1 or primitives[0].get("mode", 4) != 4 or "indices" not in primitives[0]:
        raise GraMiInputError(path, "expected one indexed triangle primitive (one material over the body)", field="primitives")
    prim = primitives[0]
    if "TEXCOORD_0" not in prim.get("attributes", {}):
        raise GraMiInputError(path, "the body has no texture coordinates", field="TEXCOORD_0")
    base = _accessor(gltf, binary, prim["attributes"]["POSITION"], path)
    uvs = _accessor(gltf, binary, prim["attributes"]["TEXCOORD_0"], path)
    faces = _accessor(gltf, binary, prim["indices"], path).astype(np.int64).reshape(-1, 3)
    targets = [_accessor(gltf, binary, t["POSITION"], path) if "POSITION" in t else np.zeros_like(base) for t in prim.get("targets", [])]
    frames, fps = _morph_frames(gltf, binary, node, base, targets, path)
    frames = frames @ world[:3, :3].T + world[:3, 3]
    if faces.max() >= len(base):
        raise GraMiInputError(path, f"face indices must lie in [0, {len(base)})", field="indices")
    return _sequence(frames, faces, uvs, fps)
