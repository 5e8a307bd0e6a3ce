"""A real human body: the CC0 MakeHuman-based ``anny`` model, animated by looping skeletal motion clips.

anny works in its own frame (+Z up, the body facing −Y, its left hand toward +X); :data:`ANNY_TO_WORLD` turns that
into ours (+Y up, facing +Z). Poses use anny's ``local-ref`` parameterisation: each bone's delta rotation is
given in world-aligned axes of the anny frame, relative to its parent, so "swing the thigh forward" is a rotation
about −X whatever the bone's own axes are.

Every clip is a smooth periodic function of its phase that starts and ends at the rest pose, so clips loop and can
be concatenated without jumps. The first ``anny.Anny()`` call on a fresh machine builds and caches the model
(about 1.5 minutes on 2 cores); later calls take under a second.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from gra_mi.core.progress import progress
from gra_mi.subject.sequence import MeshSequence, SequenceLayout, split_uv_seams, validate_sequence, vertex_normals

logger = logging.getLogger(__name__)

# anny (x, y, z) -> world (x, z, -y): +Z up becomes +Y up, facing −Y becomes facing +Z. A proper rotation (det +1).
ANNY_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

# Rotations about the anny-frame axes (radians) for each bone, for one phase value in [0, 2 pi).
Pose = dict[str, list[tuple[str, float]]]


def _walk(p: float) -> tuple[Pose, float]:
    s = math.sin(p)
    knee_l, knee_r = 0.9 * max(0.0, s) ** 2, 0.9 * max(0.0, -s) ** 2
    pose = {
        "upperleg01.L": [("x", -0.45 * s)],
        "upperleg01.R": [("x", 0.45 * s)],
        "lowerleg01.L": [("x", knee_l)],
        "lowerleg01.R": [("x", knee_r)],
        "upperarm01.L": [("x", 0.4 * s), ("y", 0.25 * (1 - math.cos(2 * p)) / 2)],
        "upperarm01.R": [("x", -0.4 * s), ("y", -0.25 * (1 - math.cos(2 * p)) / 2)],
        "lowerarm01.L": [("x", -0.3 * (1 - math.cos(p)) / 2)],
        "lowerarm01.R": [("x", -0.3 * (1 - math.cos(p)) / 2)],
    }
    return pose, 0.0


def _arm_raise(p: float) -> tuple[Pose, float]:
    a = 2.3 * (1 - math.cos(p)) / 2  # sideways, from the rest A-pose up to above the head
    return {"upperarm01.L": [("y", -a)], "upperarm01.R": [("y", a)]}, 0.0


def _turn(p: float) -> tuple[Pose, float]:
    bend = 0.5 * (1 - math.cos(2 * p)) / 2
    return {"lowerarm01.L": [("x", -bend)], "lowerarm01.R": [("x", -bend)]}, p  # a full turn about the up axis


def _march(p: float) -> tuple[Pose, float]:
    """High knees in place, arms swinging with bent elbows: poses a walk never makes, at full height (one leg stands)."""
    s = math.sin(p)
    lift_l, lift_r = max(0.0, s) ** 2, max(0.0, -s) ** 2
    elbow = -0.9 * s * s
    pose = {
        "upperleg01.L": [("x", -1.3 * lift_l)],
        "upperleg01.R": [("x", -1.3 * lift_r)],
        "lowerleg01.L": [("x", 1.7 * lift_l)],
        "lowerleg01.R": [("x", 1.7 * lift_r)],
        "upperarm01.L": [("x", 0.6 * s)],
        "upperarm01.R": [("x", -0.6 * s)],
        "lowerarm01.L": [("x", elbow)],
        "lowerarm01.R": [("x", elbow)],
    }
    return pose, 0.0


def _squat(p: float) -> tuple[Pose, float]:
    s = (1 - math.cos(p)) / 2
    hip, knee = 1.3 * s, 2.1 * s
    pose = {
        "upperleg01.L": [("x", -hip)],
        "upperleg01.R": [("x", -hip)],
        "lowerleg01.L": [("x", knee)],
        "lowerleg01.R": [("x", knee)],
        "foot.L": [("x", -(knee - hip))],  # keep the soles level
        "foot.R": [("x", -(knee - hip))],
        "spine03": [("x", 0.35 * s)],  # lean forward for balance
        "upperarm01.L": [("x", -1.3 * s)],
        "upperarm01.R": [("x", -1.3 * s)],
    }
    return pose, 0.0


@dataclass(frozen=True)
class MotionClip:
    name: str
    frames_per_loop: int
    pose_at: Callable[[float], tuple[Pose, float]]  # phase -> (bone rotations, turn angle about up)


MOTION_CLIPS: dict[str, MotionClip] = {
    "walk": MotionClip("walk", 24, _walk),
    "arm_raise": MotionClip("arm_raise", 24, _arm_raise),
    "turn": MotionClip("turn", 48, _turn),
    "squat": MotionClip("squat", 24, _squat),
    "march": MotionClip("march", 24, _march),
}


def _axis_rotation(axis: str, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def clip_frames(clips: list[str], frames_per_clip: int | list[int] | None = None) -> list[tuple[str, float]]:
    """(clip name, phase) for every frame of the clips played one after the other (frames: one count, one per clip,
    or None for each clip's own loop length)."""
    counts = frames_per_clip if isinstance(frames_per_clip, list) else [frames_per_clip] * len(clips)
    if len(counts) != len(clips):
        raise ValueError(f"{len(counts)} frame counts for {len(clips)} clips")
    out = []
    for name, count in zip(clips, counts, strict=True):
        if name not in MOTION_CLIPS:
            raise ValueError(f"unknown motion clip '{name}', expected one of {sorted(MOTION_CLIPS)}")
        n = count or MOTION_CLIPS[name].frames_per_loop
        out += [(name, 2.0 * math.pi * k / n) for k in range(n)]
    return out


def _body_colors(model, position_index: np.ndarray) -> np.ndarray:
    """Base albedo per vertex from its dominant bone: skin, shirt, trousers, shoes (for stock-BSDF previews)."""
    weights = model.vertex_bone_weights.detach().cpu().numpy()
    indices = model.vertex_bone_indices.detach().cpu().numpy()
    dominant = indices[np.arange(len(indices)), np.argmax(weights, axis=1)]
    labels = [model.bone_labels[i] for i in dominant]
    skin, shirt, trousers, shoes = [0.62, 0.42, 0.33], [0.12, 0.28, 0.55], [0.18, 0.17, 0.16], [0.55, 0.52, 0.48]

    def color(label: str) -> list[float]:
        if label.startswith(("foot", "toe")):
            return shoes
        if label.startswith(("pelvis", "upperleg", "lowerleg", "root")):
            return trousers
        if label.startswith(("spine", "clavicle", "shoulder", "upperarm")):
            return shirt
        return skin

    per_position = np.array([color(lbl) for lbl in labels], dtype=np.float32)
    return per_position[position_index]


def anny_sequence(clips: list[str], frames_per_clip: int | list[int] | None = None, fps: float = 24.0) -> MeshSequence:
    """Animate the anny body through the given clips and export a tracked mesh sequence (world frame), whole."""
    layout, frames = anny_frames(clips, frames_per_clip, fps)
    vertices, normals = (np.stack(arrays) for arrays in zip(*frames, strict=True))
    seq = MeshSequence(layout.faces, layout.uvs, vertices, normals, fps, layout.frame_labels, layout.vertex_colors, origin="anny")
    validate_sequence(seq, "anny")
    return seq


def anny_frames(
    clips: list[str], frames_per_clip: int | list[int] | None = None, fps: float = 24.0
) -> tuple[SequenceLayout, Iterator[tuple[np.ndarray, np.ndarray]]]:
    """The anny body through the given clips, a frame at a time: what every frame shares, and each frame's (vertices,
    normals) as it is posed (:func:`~gra_mi.subject.sequence.write_sequence` writes a sequence of any length so)."""
    import anny

    logger.info("building the anny body model (cached after the first run)")
    model = anny.Anny()
    if model.pose_parameterization != "local-ref":
        raise RuntimeError(f"anny's pose parameterisation changed to {model.pose_parameterization!r}; gra-mi expects 'local-ref'")
    faces = model.get_triangular_faces().cpu().numpy()
    face_uv = model.face_texture_coordinate_indices.cpu().numpy()
    uv_table = model.texture_coordinates.cpu().numpy()
    new_faces, position_index, uv_index = split_uv_seams(faces, face_uv)
    uvs = np.clip(uv_table[uv_index], 0.0, 1.0).astype(np.float32)
    schedule = clip_frames(clips, frames_per_clip)
    colors = _body_colors(model, position_index)
    layout = SequenceLayout(new_faces, uvs, len(schedule), fps, [name for name, _ in schedule], colors)

    def frames() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for name, phase in progress(schedule, description="posing anny"):
            world = _posed(model, name, phase)
            # Normals from the welded mesh, so UV seams do not show as shading creases.
            yield world[position_index].astype(np.float32), vertex_normals(world, faces)[position_index]

    return layout, frames()


def _posed(model, name: str, phase: float) -> np.ndarray:
    """The body's welded vertices in the world frame at ``phase`` of clip ``name``, feet on the floor (y = 0)."""
    import torch

    rotations, turn = MOTION_CLIPS[name].pose_at(phase)
    dtype = model.template_vertices.dtype
    pose = {}
    for bone, parts in rotations.items():
        r = np.eye(3)
        for axis, angle in parts:
            r = r @ _axis_rotation(axis, angle)
        h = torch.eye(4, dtype=dtype)
        h[:3, :3] = torch.as_tensor(r, dtype=dtype)
        pose[bone] = h[None]
    with torch.no_grad():
        verts = model(pose_parameters=pose)["vertices"][0].cpu().numpy().astype(np.float64)
    verts = verts @ (_axis_rotation("z", turn) if turn else np.eye(3)).T  # turn about anny's up axis
    world = verts @ ANNY_TO_WORLD.T
    world[:, 1] -= world[:, 1].min()
    return world
