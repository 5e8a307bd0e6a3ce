"""Export the fitted avatar as glTF 2.0 binary (.glb): it opens in Blender, three.js and every glTF viewer.

- the tracked mesh at its first frame (positions, normals, UVs, triangles);
- a PBR material: ``baseColorTexture`` = albedo (sRGB PNG), ``metallicRoughnessTexture`` with roughness in G and
  metallic 0 in B. glTF's roughness is perceptual (α = r²), the same convention as gra-mi's;
- the other frames as morph targets (position and normal deltas), with an animation that steps through them at the
  sequence's frame rate;
- optionally a scene's set (a floor, walls, props; :mod:`gra_mi.apps.set_export`) as static meshes, each with a
  constant double-sided metallic-roughness material;
- optionally a rig's cameras (perspective, looking along −Z with +Y up as glTF's do; glTF has no principal point, so
  a camera whose centre is off the image's is said in the export's warnings) and the LEDs that are on as
  ``KHR_lights_punctual`` point lights, in candela: 683 lm/W × the LED's W/sr, which Blender's importer turns back
  into the watts a point light of that intensity emits (4π × W/sr); a light path's moving point and spot lights too,
  their nodes keyed in the avatar's animation.
"""

from __future__ import annotations

import io
import json
import math
import struct
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_path, to_srgb8
from gra_mi.stage.lightstage import Camera
from gra_mi.subject.sequence import MeshSequence

FLOAT, UINT = 5126, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
LUMENS_PER_WATT = 683.0  # glTF's punctual lights are photometric (candela); gra-mi's LEDs radiometric (W/sr)
OPENCV_TO_GLTF_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV looks along +Z with +Y down; glTF along −Z, +Y up
NEAR_M = 0.01


class _Buffer:
    def __init__(self):
        self.data = bytearray()
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def view(self, payload: bytes, target: int | None = None) -> int:
        while len(self.data) % 4:
            self.data += b"\0"
        entry = {"buffer": 0, "byteOffset": len(self.data), "byteLength": len(payload)}
        if target is not None:
            entry["target"] = target
        self.data += payload
        self.views.append(entry)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, component: int, target: int | None, minmax: bool = False) -> int:
        view = self.view(np.ascontiguousarray(array).tobytes(), target)
        entry = {"bufferView": view, "componentType": component, "count": int(array.shape[0]), "type": kind}
        if minmax:
            entry["min"] = array.min(axis=0).tolist()
            entry["max"] = array.max(axis=0).tolist()
        self.accessors.append(entry)
        return len(self.accessors) - 1


def _png(image: np.ndarray) -> bytes:
    import imageio.v3 as iio

    out = io.BytesIO()
    iio.imwrite(out, image, extension=".png")
    return out.getvalue()


GLB_LIMIT = 1 << 32  # bytes: a .glb's header stores its length in 32 bits


def check_glb_size(seq: MeshSequence, count: int, first: int = 0) -> None:
    """Refuse, before anything is read or written, morph targets that cannot fit a .glb (positions and normals, float32,
    per frame after the first; the mesh and textures take less than the margin left)."""
    per_frame = seq.num_vertices * 2 * 3 * 4
    if count * per_frame > GLB_LIMIT - (64 << 20):
        fits = max(1, (GLB_LIMIT - (64 << 20)) // per_frame)
        raise GraMiParameterError(
            "frames", f"{count} frames of this {seq.num_vertices}-vertex mesh need {count * per_frame / 2**30:.1f} GiB of morph targets, "
            f"more than a .glb can hold (4 GiB): give at most {fits} frames (--frames {first}:{first + fits}), or export .usdc",
        )  # fmt: skip


def _stepping_through(buf: _Buffer, count: int, fps: float) -> dict:
    """The animation that shows frame t (morph target t − 1 at full weight, the mesh itself at t = 0) at t / fps."""
    times = (np.arange(count, dtype=np.float32) / fps).reshape(-1, 1)
    weights = np.zeros((count, count - 1), np.float32)
    weights[np.arange(1, count), np.arange(count - 1)] = 1.0
    sampler = {
        "input": buf.accessor(times, "SCALAR", FLOAT, None, minmax=True),
        "output": buf.accessor(weights.reshape(-1, 1), "SCALAR", FLOAT, None),
        "interpolation": "STEP",
    }
    return {"name": "performance", "samplers": [sampler], "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}


def camera_entries(cameras: list[Camera]) -> tuple[list[dict], list[dict]]:
    """(glTF cameras, their nodes): each camera's vertical field of view and aspect from its focal lengths, its node's
    matrix the camera-to-world turned to glTF's camera axes (column-major)."""
    entries, nodes = [], []
    for k, cam in enumerate(cameras):
        yfov = 2.0 * math.atan(cam.height / (2.0 * cam.fy))
        aspect = (cam.width / cam.fx) / (cam.height / cam.fy)  # tan(xfov / 2) / tan(yfov / 2)
        entries.append({"name": cam.name, "type": "perspective", "perspective": {"yfov": yfov, "aspectRatio": aspect, "znear": NEAR_M}})
        matrix = cam.camera_to_world @ OPENCV_TO_GLTF_CAMERA
        nodes.append({"name": cam.name, "camera": k, "matrix": matrix.T.ravel().tolist()})
    return entries, nodes


def led_light_entries(positions: np.ndarray, intensities: np.ndarray) -> tuple[list[dict], list[dict]]:
    """(KHR_lights_punctual lights, their nodes) of the LEDs that are on (the others are not written)."""
    lights, nodes = [], []
    for led in np.flatnonzero(np.asarray(intensities).max(axis=1) > 0):
        peak = float(np.max(intensities[led]))
        color = (np.asarray(intensities[led], np.float64) / peak).tolist()
        lights.append({"name": f"led{led:04d}", "type": "point", "color": color, "intensity": peak * LUMENS_PER_WATT})
        node = {"name": f"led{led:04d}", "translation": np.asarray(positions[led], np.float64).tolist()}
        nodes.append(node | {"extensions": {"KHR_lights_punctual": {"light": len(lights) - 1}}})
    return lights, nodes


def _uses(gltf: dict, extension: str) -> None:
    """Name ``extension`` in the file's ``extensionsUsed`` (once)."""
    if extension not in gltf.setdefault("extensionsUsed", []):
        gltf["extensionsUsed"].append(extension)


def _add_rig(gltf: dict, cameras: list[Camera], leds: tuple[np.ndarray, np.ndarray] | None) -> None:
    """The cameras and lit LEDs as nodes of the scene beside the avatar."""
    entries, nodes = camera_entries(cameras)
    lights, light_nodes = led_light_entries(*leds) if leds is not None else ([], [])
    if entries:
        gltf["cameras"] = entries
    if lights:
        _uses(gltf, "KHR_lights_punctual")
        gltf.setdefault("extensions", {})["KHR_lights_punctual"] = {"lights": lights}
    first = len(gltf["nodes"])
    gltf["nodes"] += nodes + light_nodes
    gltf["scenes"][0]["nodes"] += list(range(first, len(gltf["nodes"])))


def _add_set(gltf: dict, buf: _Buffer, parts: list) -> None:
    """The set's shapes as meshes of the scene beside the avatar, each with its own preview material."""
    for part in parts:
        attributes = {
            "POSITION": buf.accessor(part.vertices, "VEC3", FLOAT, ARRAY_BUFFER, minmax=True),
            "NORMAL": buf.accessor(part.normals, "VEC3", FLOAT, ARRAY_BUFFER),
        }
        indices = buf.accessor(part.faces.astype(np.uint32).reshape(-1, 1), "SCALAR", UINT, ELEMENT_ARRAY_BUFFER)
        preview = part.preview
        pbr = {"baseColorFactor": [*preview.base_color, 1.0], "metallicFactor": preview.metallic, "roughnessFactor": preview.roughness}
        material = {"name": part.name, "pbrMetallicRoughness": pbr, "doubleSided": True}
        if preview.ior != 1.5:  # (glTF's default; 1: no specular, a diffuse BSDF's)
            material["extensions"] = {"KHR_materials_ior": {"ior": preview.ior}}
            _uses(gltf, "KHR_materials_ior")
        gltf["materials"].append(material)
        primitive = {"attributes": attributes, "indices": indices, "material": len(gltf["materials"]) - 1, "mode": 4}
        gltf["meshes"].append({"name": part.name, "primitives": [primitive]})
        gltf["nodes"].append({"name": part.name, "mesh": len(gltf["meshes"]) - 1})
        gltf["scenes"][0]["nodes"].append(len(gltf["nodes"]) - 1)


def _add_moving_lights(gltf: dict, buf: _Buffer, tracks: list, fps: float) -> None:
    """A light path's lights as ``KHR_lights_punctual`` point and spot lights (a spot's outer cone its cutoff, its inner
    its full beam), each on a node whose translation and rotation step through the exported frames in the avatar's own
    animation (one timeline: importers play one animation per scene; LINEAR between frames); the first frame's
    intensity, colour and cone (glTF cannot animate a light's)."""
    from gra_mi.apps.export_lights import light_to_world, rotation_quaternion

    if not tracks:
        return
    extension = gltf.setdefault("extensions", {}).setdefault("KHR_lights_punctual", {"lights": []})
    _uses(gltf, "KHR_lights_punctual")
    performance = gltf["animations"][0] if gltf.get("animations") else None  # (two frames or more: the avatar's)
    if performance is not None:
        times = buf.accessor((np.arange(len(tracks[0].states), dtype=np.float32) / fps).reshape(-1, 1), "SCALAR", FLOAT, None, minmax=True)
    channels, samplers = ([], []) if performance is None else (performance["channels"], performance["samplers"])
    for track in tracks:
        first = track.states[0]
        peak = float(first.intensity.max())
        light = {"name": track.name, "type": "spot" if track.is_spot else "point", "intensity": peak * LUMENS_PER_WATT}
        light["color"] = (first.intensity / peak if peak > 0 else np.ones(3)).tolist()
        if track.is_spot:
            outer = math.radians(first.cutoff_angle)
            light["spot"] = {"innerConeAngle": min(math.radians(first.beam_width), outer * (1 - 1e-6)), "outerConeAngle": outer}
        extension["lights"].append(light)
        places = [light_to_world(state) for state in track.states]
        node = {
            "name": track.name,
            "translation": places[0][:3, 3].tolist(),
            "extensions": {"KHR_lights_punctual": {"light": len(extension["lights"]) - 1}},
        }
        if track.is_spot:
            node["rotation"] = rotation_quaternion(places[0]).tolist()
        gltf["nodes"].append(node)
        gltf["scenes"][0]["nodes"].append(len(gltf["nodes"]) - 1)
        if performance is None:
            continue
        moves = {"translation": np.array([m[:3, 3] for m in places], np.float32), "rotation": None}
        if track.is_spot:
            moves["rotation"] = np.array([rotation_quaternion(m) for m in places], np.float32)
        for path, values in moves.items():
            if values is None:
                continue
            samplers.append({"input": times, "output": buf.accessor(values, "VEC3" if path == "translation" else "VEC4", FLOAT, None),
                             "interpolation": "LINEAR"})  # fmt: skip
            channels.append({"sampler": len(samplers) - 1, "target": {"node": len(gltf["nodes"]) - 1, "path": path}})


def export_glb(
    path: str | Path, seq: MeshSequence, albedo: np.ndarray, roughness: np.ndarray, frames: list[int] | None = None,
    cameras: list[Camera] | None = None, leds: tuple[np.ndarray, np.ndarray] | None = None, set_parts: list | None = None,
    tracks: list | None = None,
) -> Path:  # fmt: skip
    """Write ``path`` (.glb). ``frames``: the sequence's frames to animate, in order (default: all); the first is the
    mesh, the others its morph targets, and the animation's time 0 is the first (``extras.gra_mi.source_frames``).
    ``cameras``: a rig's cameras; ``leds``: (positions, W/sr (L, 3)) of a rig's LEDs under a pattern; ``set_parts``: a
    scene's set (:mod:`~gra_mi.apps.set_export`); ``tracks``: a light path's lights (:mod:`~gra_mi.apps.export_lights`)."""
    frames = list(range(seq.num_frames)) if frames is None else list(frames)
    check_glb_size(seq, len(frames), frames[0])
    buf = _Buffer()
    base_p = seq.vertices[frames[0]].astype(np.float32)
    base_n = seq.normals[frames[0]].astype(np.float32)
    # glTF's UV origin is the top-left of the image; gra-mi's row 0 is v = 0, which glTF also reads as the top row.
    attributes = {
        "POSITION": buf.accessor(base_p, "VEC3", FLOAT, ARRAY_BUFFER, minmax=True),
        "NORMAL": buf.accessor(base_n, "VEC3", FLOAT, ARRAY_BUFFER),
        "TEXCOORD_0": buf.accessor(seq.uvs.astype(np.float32), "VEC2", FLOAT, ARRAY_BUFFER),
    }
    indices = buf.accessor(seq.faces.astype(np.uint32).reshape(-1, 1), "SCALAR", UINT, ELEMENT_ARRAY_BUFFER)
    targets = [
        {
            "POSITION": buf.accessor((seq.vertices[t] - base_p).astype(np.float32), "VEC3", FLOAT, ARRAY_BUFFER, minmax=True),
            "NORMAL": buf.accessor((seq.normals[t] - base_n).astype(np.float32), "VEC3", FLOAT, ARRAY_BUFFER),
        }
        for t in frames[1:]
    ]
    rough = np.clip(roughness[..., 0], 0, 1)
    mr = np.stack([np.zeros_like(rough), rough, np.zeros_like(rough)], axis=-1)  # R unused, G roughness, B metallic
    images = [
        {"bufferView": buf.view(_png(to_srgb8(np.clip(albedo[..., :3], 0, 1))[..., :3])), "mimeType": "image/png", "name": "albedo"},
        {"bufferView": buf.view(_png((mr * 255 + 0.5).astype(np.uint8))), "mimeType": "image/png", "name": "metallicRoughness"},
    ]
    primitive = {"attributes": attributes, "indices": indices, "material": 0, "mode": 4}
    mesh = {"name": "avatar", "primitives": [primitive]}
    gltf: dict = {
        "asset": {"version": "2.0", "generator": "gra-mi"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "avatar"}],
        "meshes": [mesh],
        "materials": [
            {
                "name": "gra-mi fitted material",
                "pbrMetallicRoughness": {
                    "baseColorTexture": {"index": 0},
                    "metallicRoughnessTexture": {"index": 1},
                    "metallicFactor": 1.0,  # scaled by the texture's B channel (0)
                    "roughnessFactor": 1.0,
                },
                "doubleSided": False,
            }
        ],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "textures": [{"source": 0, "sampler": 0}, {"source": 1, "sampler": 0}],
        "images": images,
    }
    if targets:
        primitive["targets"] = targets
        mesh["weights"] = [0.0] * len(targets)
        gltf["animations"] = [_stepping_through(buf, len(frames), seq.fps)]
    gltf["nodes"][0]["extras"] = {"gra_mi": {"source_frames": frames}}  # the sequence's frame at each step
    _add_set(gltf, buf, set_parts or [])
    _add_rig(gltf, cameras or [], leds)
    _add_moving_lights(gltf, buf, tracks or [], seq.fps)
    while len(buf.data) % 4:
        buf.data += b"\0"
    gltf["buffers"] = [{"byteLength": len(buf.data)}]
    gltf["bufferViews"] = buf.views
    gltf["accessors"] = buf.accessors
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * ((4 - len(text) % 4) % 4)
    total = 12 + 8 + len(text) + 8 + len(buf.data)
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(struct.pack("<4sII", b"glTF", 2, total))
        fh.write(struct.pack("<I4s", len(text), b"JSON") + text)
        fh.write(struct.pack("<I4s", len(buf.data), b"BIN\0") + bytes(buf.data))
    return path
