"""A source in gra-mi's frame: the world frame (up axis, the LED sphere's centre over the origin, the floor), each
camera planned onto square pixels at the import's scale, the rig and the subject's mesh sequence as gra-mi stores
them."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.lens import LensDistortion, pinhole_positions, undistort_image
from gra_mi.capture.source import UP_AXES, Source
from gra_mi.capture.source_files import resample_columns
from gra_mi.core.progress import progress
from gra_mi.stage.lightstage import Camera, Lightstage
from gra_mi.subject.sequence import MeshSequence, SequenceLayout, split_uv_seams, vertex_normals, write_sequence


@dataclass
class WorldFrame:
    """source metres → gra-mi: ``p' = rotation @ p + translation`` (Y up, the LED sphere's centre above the origin,
    the subject's lowest point on y = 0)."""

    rotation: np.ndarray
    translation: np.ndarray
    up_source: np.ndarray  # the source's up direction
    up_estimated: bool
    up_off_axis_deg: float  # how far the cameras' up is from the nearest source axis
    led_radius: float
    led_fit_rms: float  # metres: the LEDs' distance from the fitted sphere

    def apply(self, points: np.ndarray) -> np.ndarray:
        return points @ self.rotation.T + self.translation

    def matrix(self) -> list[list[float]]:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = self.rotation, self.translation
        return m.round(9).tolist()


def fit_sphere(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least-squares sphere: (centre, radius, RMS distance of the points from it)."""
    a = np.concatenate([2 * points, np.ones((len(points), 1))], axis=1)
    solution, *_ = np.linalg.lstsq(a, (points**2).sum(axis=1), rcond=None)
    centre = solution[:3]
    radius = math.sqrt(max(solution[3] + centre @ centre, 0.0))
    return centre, radius, float(np.sqrt(np.mean((np.linalg.norm(points - centre, axis=1) - radius) ** 2)))


def _rotation_to_y(up: np.ndarray) -> np.ndarray:
    """The smallest rotation taking ``up`` to +Y (Rodrigues)."""
    up = up / np.linalg.norm(up)
    y = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(up, y), float(up @ y)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def world_frame(source: Source, up: str) -> WorldFrame:
    """The up axis (given, or estimated: the direction most nearly perpendicular to every camera's image x axis,
    which is level on an upright camera whatever its tilt, signed by the cameras' image-up), the LED sphere's centre
    over the origin, and the mesh's lowest point on the floor."""
    if up == "auto":
        rights = np.array([c.extrinsic[:3, 0] / np.linalg.norm(c.extrinsic[:3, 0]) for c in source.calib])
        values, vectors = np.linalg.eigh(rights.T @ rights)
        level = vectors[:, values < 0.05 * values.max()]  # directions no camera's x axis has a share in
        mean_up = np.mean([-c.extrinsic[:3, 1] for c in source.calib], axis=0)
        direction = level @ (level.T @ mean_up)  # the cameras' image-up, made level to every x axis
        direction /= np.linalg.norm(direction)
    else:
        direction = np.array(UP_AXES[up], float)
    off_axis = math.degrees(math.acos(min(1.0, float(np.abs(direction).max()))))
    rotation = _rotation_to_y(direction)
    centre, radius, rms = fit_sphere(source.leds)
    floor = _floor(source, centre, radius, rotation)
    translation = -rotation @ centre - np.array([0.0, floor, 0.0])
    return WorldFrame(rotation, translation, direction, up == "auto", off_axis, radius, rms)


@dataclass
class CameraPlan:
    """A source camera as gra-mi stores it: square pixels, scaled; and how its images are resampled."""

    index: int
    camera: Camera
    source_size: tuple[int, int]
    square_width: int  # columns after making the pixels square (before the scale)
    anisotropy: float  # fx / fy of the source
    source_k: np.ndarray  # K of the source's images, in their pixels
    lens: LensDistortion | None = None  # undone first (the pinhole camera with source_k), then the resampling


def plan_camera(source: Source, index: int, frame: WorldFrame, scale: float) -> CameraPlan:
    """A distorted camera is first its pinhole with the same K (:mod:`~gra_mi.capture.lens`). Non-square pixels
    (fx ≠ fy) are resampled along x to fx = fy; then both axes by ``scale``. Whatever rounding the sizes leave (a
    fraction of a pixel over the width) is split evenly between fx and fy."""
    width, height = source.sizes[index]
    k = source.calib[index].k_matrix(width)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    square_width = round(width * fy / fx)
    out_w, out_h = max(1, round(square_width * scale)), max(1, round(height * scale))
    sx, sy = out_w / width, out_h / height
    f = math.sqrt(fx * sx * fy * sy)
    c2w = np.eye(4)
    c2w[:3, :3] = frame.rotation @ source.calib[index].extrinsic[:3, :3]
    c2w[:3, 3] = frame.apply(source.calib[index].extrinsic[:3, 3][None] * source.units)[0]
    camera = Camera(source.names[index], out_w, out_h, f, f, cx * sx, cy * sy, c2w)
    return CameraPlan(index, camera, (width, height), square_width, fx / fy, k, source.calib[index].lens)


def resample_image(image: np.ndarray, plan: CameraPlan) -> np.ndarray:
    """A source image onto the planned camera's pixel grid: its lens distortion undone (bilinear, at the source's
    resolution), then area-weighted along each axis."""
    if plan.lens is not None:
        image = undistort_image(image, plan.source_k, plan.lens)
    w, h = plan.camera.width, plan.camera.height
    if image.shape[1] != w:
        image = resample_columns(image, w)
    if image.shape[0] != h:
        image = np.swapaxes(resample_columns(np.swapaxes(image, 0, 1), h), 0, 1)
    return image


def build_stage(
    source: Source, frame: WorldFrame, plans: list[CameraPlan], led_intensity: float, gains: np.ndarray | None = None
) -> Lightstage:
    positions = frame.apply(source.leds)
    centre = frame.apply(fit_sphere(source.leds)[0][None])[0]
    to_centre = centre - positions
    normals = to_centre / np.maximum(np.linalg.norm(to_centre, axis=1, keepdims=True), 1e-12)
    return Lightstage(
        led_positions=positions,
        led_normals=normals,
        cameras=[p.camera for p in plans],
        center=centre,
        radius=frame.led_radius,
        led_gains=gains,
        max_led_intensity=led_intensity,
    )


def _floor(source: Source, centre: np.ndarray, radius: float, rotation: np.ndarray) -> float:
    """The height (above the LED sphere's centre, along up) of the floor under the subject the cameras see: its lowest
    vertex inside the LED sphere over every mesh frame (a stray vertex 100 m away is not), else its lowest of all. One
    frame at a time: this pass also checks every frame (:meth:`MeshFrames.positions`) before anything is written."""
    lowest_inside = lowest = math.inf
    for k in progress(range(len(source.meshes)), "reading the meshes", len(source.meshes)):
        mesh_m = source.mesh_metres(source.meshes.positions(k))
        heights = (mesh_m - centre) @ rotation[1]
        inside = np.linalg.norm(mesh_m - centre, axis=1) < radius
        lowest = min(lowest, float(heights.min()))
        if inside.any():
            lowest_inside = min(lowest_inside, float(heights[inside].min()))
    return lowest_inside if math.isfinite(lowest_inside) else lowest


@dataclass
class SubjectPlan:
    """The subject as gra-mi stores it: the first mesh's UV atlas (its own, or one generated for it), a vertex per
    position and UV pair; each mesh frame's vertices in the world frame, made when written (:meth:`write`)."""

    faces: np.ndarray
    uvs: np.ndarray
    position_of: np.ndarray  # the source position of each vertex
    atlas: str  # where the atlas came from

    def vertices(self, source: Source, frame: WorldFrame, k: int) -> np.ndarray:
        return frame.apply(source.mesh_metres(source.meshes.positions(k)[self.position_of])).astype(np.float32)

    def normals(self, source: Source, frame: WorldFrame, k: int) -> np.ndarray | None:
        """The source's own vertex normals of mesh frame ``k``, turned into the world frame; None where it has none
        (computed from the positions when written)."""
        normals = source.meshes.normals(k)
        return None if normals is None else (source.mesh_directions(normals[self.position_of]) @ frame.rotation.T).astype(np.float32)

    def posed(self, source: Source, frame: WorldFrame, k: int) -> MeshSequence:
        """Mesh frame ``k`` alone, as a one-frame sequence (what the reprojection check looks at)."""
        v = self.vertices(source, frame, k)[None]
        return MeshSequence(self.faces, self.uvs, v, vertex_normals(v, self.faces), fps=1.0, frame_labels=[f"pose {k}"])

    def write(self, source: Source, frame: WorldFrame, folder: Path) -> None:
        count = len(source.meshes)
        layout = SequenceLayout(self.faces, self.uvs, count, fps=1.0, frame_labels=[f"pose {k}" for k in range(count)])
        frames = ((self.vertices(source, frame, k), self.normals(source, frame, k)) for k in range(count))
        write_sequence(folder, layout, frames, source=str(source.folder))


def plan_subject(source: Source, uv_resolution: int) -> SubjectPlan:
    """Every mesh frame shares the first's topology (a tracked mesh; checked as each is read)."""
    first = source.meshes.first
    if first.face_uvs is None:
        first.uvs, first.face_uvs, said = generate_atlas(first.positions, first.faces, uv_resolution)
    else:
        said = "the mesh's own"
    faces, position_of, uv_of = split_uv_seams(first.faces, first.face_uvs)
    return SubjectPlan(faces, first.uvs[uv_of].astype(np.float32), position_of, said)


def generate_atlas(positions: np.ndarray, faces: np.ndarray, resolution: int) -> tuple[np.ndarray, np.ndarray, str]:
    """A UV atlas for a mesh that has none (xatlas, charts packed for a ``resolution``² texture with 2 texels of
    padding so bilinear lookups stay in their chart). Returns (uvs, face UV indices, what was done); the faces keep
    their order, so a tracked sequence shares the atlas."""
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(positions.astype(np.float32), faces.astype(np.uint32))
    packing = xatlas.PackOptions()
    packing.resolution, packing.padding, packing.bilinear = resolution, 2, True
    atlas.generate(pack_options=packing)
    position_of, face_uvs, uvs = atlas[0]
    if not np.array_equal(position_of[face_uvs], faces):  # xatlas keeps face order; a change would scramble the poses
        raise RuntimeError("xatlas reordered the mesh's faces")
    said = f"generated (xatlas: {atlas.chart_count} charts, {100 * atlas.utilization:.0f} % of the texture used)"
    return uvs.astype(float), face_uvs.astype(np.int64), said


def mask_at_source(mask: np.ndarray, plan: CameraPlan) -> np.ndarray:
    """The planned-grid mask back on the source grid (nearest; through the lens where it has one), to count
    saturated subject pixels there."""
    w, h = plan.source_size
    sy, sx = mask.shape[0] / h, mask.shape[1] / w
    if plan.lens is None:
        rows = np.minimum((np.arange(h) + 0.5) * sy, mask.shape[0] - 1).astype(int)
        cols = np.minimum((np.arange(w) + 0.5) * sx, mask.shape[1] - 1).astype(int)
        return mask[np.ix_(rows, cols)]
    x, y = pinhole_positions(plan.source_k, plan.lens, w, h)  # each source pixel in the pinhole image
    x, y = np.nan_to_num((x + 0.5) * sx, nan=-1.0), np.nan_to_num((y + 0.5) * sy, nan=-1.0)
    held = (x >= 0) & (x < mask.shape[1]) & (y >= 0) & (y < mask.shape[0])
    picked = mask[np.clip(y, 0, mask.shape[0] - 1).astype(int), np.clip(x, 0, mask.shape[1] - 1).astype(int)]
    return np.where(held, picked, 0).astype(mask.dtype)
