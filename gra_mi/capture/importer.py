"""``gra-mi import``: the path every source format shares, from a :class:`Source` to a capture in the layout every
stage reads (docs/data-format.md), in gra-mi's world frame, with an import report a user reads first.

One module per source format reads its files into a :class:`Source` (:mod:`~gra_mi.capture.humanolat`,
:mod:`~gra_mi.capture.transforms`, :mod:`~gra_mi.capture.easymocap`, with the files they share in
:mod:`~gra_mi.capture.source_files`); the format's quirks stay there. Then, here, for every format:
:meth:`Source.check` (what gra-mi's readers would refuse, named against the source's files) → the frame
(:func:`world_frame`: units to metres, the up axis, the LED sphere's centre, the floor) → the mesh reprojected over
every camera's mask (what spoils it, or a convention mistake, stops here, named) → written into a staging folder (rig,
subject, scene, patterns, images streamed one at a time, capture.json, import_report.{md,json}) → loaded back by
gra-mi's own readers → published by rename (:func:`import_capture`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture
from gra_mi.capture.source_files import image_size, read_image, resample_columns, write_mask
from gra_mi.core.config import comma_list, option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.guard import path_component, staging_folder
from gra_mi.core.io import atomic_write_text, read_exr, write_exr, write_png
from gra_mi.core.progress import progress
from gra_mi.core.provenance import PROVENANCE, claim_output, release_folder, run_differences, run_record
from gra_mi.core.schema import rigid_rotation
from gra_mi.core.shard import Shard
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.lightstage import Camera, Lightstage, load_pattern, olat_pattern, uniform_pattern
from gra_mi.stage.scene import subject_scene_xml, write_rig
from gra_mi.subject.sequence import MeshSequence, save_sequence, split_uv_seams, vertex_normals

logger = logging.getLogger(__name__)

UP_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


@dataclass(kw_only=True)
class ImportConfig:
    """What every import route shares (:func:`import_capture`)."""

    cameras: list[str] | None = field(default=None, metadata=option(parse=comma_list))
    """Cameras to import, comma-separated (Cam01,Cam05,...). Default: all."""
    eval_cameras: list[str] | None = field(default=None, metadata=option(parse=comma_list))
    """Cameras held out for novel-view evaluation, comma-separated. Default: two, spread over the rig."""
    scale: float = 1.0
    """Image scale after the pixels are made square (0.25: a quarter of the size; a full HumanOLAT pose is ~13,700
    images)."""
    up: str = field(default="auto", metadata=option(choices=("auto", *UP_AXES)))
    """The source frame's up axis; auto: level to every camera's image x axis, signed by their image up (reported)."""
    led_intensity: float = 4.0
    """Radiant intensity (W/sr) of a fully driven LED (the source does not say; sets the albedo's scale only)."""
    uv_resolution: int = 256
    """UV resolution of the maps fitted to the capture."""
    min_iou: float = 0.5
    """Stop when the mesh reprojected over a camera's mask overlaps it less than this (intersection over union)."""

    def validate(self) -> None:
        require_positive({"scale": self.scale, "led_intensity": self.led_intensity, "uv_resolution": self.uv_resolution})
        if not 0 <= self.min_iou <= 1:
            raise GraMiParameterError("min_iou", f"must be in [0, 1], got {self.min_iou}")
        if self.up not in ("auto", *UP_AXES):
            raise GraMiParameterError("up", f"expected auto or one of {', '.join(UP_AXES)}, got {self.up!r}")


@dataclass
class Source:
    """A capture as read, before anything is written: everything in the source's own frame and units. Readers
    (:func:`read_humanolat`, :func:`gra_mi.capture.transforms.read_transforms`) fill it; the rest of the import is
    the same for every source."""

    folder: Path
    format: str  # "humanolat", "transforms"
    calib_path: Path  # what a camera error names
    names: list[str]  # camera names
    calib: list  # CalibCamera per camera: K / width, camera-to-world (OpenCV axes) in the source's units
    sizes: list[tuple[int, int]]  # (width, height) of each camera's images
    images: list[dict[int, Path]]  # per camera: frame key → image file
    units: float  # metres per source unit of the calibration (0.001: millimetres)
    leds: np.ndarray  # (L, 3) metres, the source's frame
    meshes: list  # ObjMesh per pose (one topology), source units
    masks: list[Path | None]  # per camera: a mask file, else the images' alpha or non-black pixels
    frames: list = field(default_factory=list)  # (frame key, FrameLighting, drive): an LED, "white" or an envmap file
    left_out: list[int] = field(default_factory=list)  # LEDs whose OLATs were not imported
    white: int | None = None  # the frame key of an all-LEDs frame (the linearity check)
    olat_keys: list[int] | None = None  # the frame keys of every LED's OLAT, imported or not (the linearity check)
    order: np.ndarray | None = None  # the OLAT firing order (HumanOLAT)
    mesh_units: float | None = None  # metres per unit of the meshes (None: as the calibration)
    frame_masks: list[dict[int, Path]] | None = None  # per camera: frame key → its own mask file (a moving subject)
    mask_cache: dict[int, np.ndarray] = field(default_factory=dict, repr=False)  # per camera: a mask every frame shares

    leds_path: Path | None = None  # what an LED error names (None: the calibration)
    mesh_files: list[Path] = field(default_factory=list)  # the mesh file(s) or folder read (for provenance)

    def check(self) -> None:
        """What every source must satisfy before anything is written, whichever reader filled it: the checks gra-mi's
        own loaders make of a capture, stated here against the source's files (each reader checks its format).
        :func:`import_capture` calls it first."""
        self._check_cameras()
        self._check_leds()
        self._check_meshes()
        self._check_frames()

    def _check_cameras(self) -> None:
        # Camera names become folder names in the capture (and in every later command's output): plain and unique.
        seen: dict[tuple, str] = {}
        for i, (name, cam) in enumerate(zip(self.names, self.calib, strict=True)):
            path_component(name, self.calib_path, f"camera {i} name")
            if name in self.names[:i]:
                raise GraMiInputError(self.calib_path, f"cameras {self.names.index(name)} and {i} are both named '{name}'", field="cameras")
            if not (np.isfinite(cam.extrinsic).all() and np.isfinite(cam.intrinsic).all()):
                raise GraMiInputError(self.calib_path, "non-finite calibration values", field=f"camera {name}")
            try:
                rigid_rotation(np.asarray(cam.extrinsic)[:3, :3], "camera-to-world rotation")
            except ValueError as exc:
                raise GraMiInputError(self.calib_path, str(exc), field=f"camera {name}") from None
            key = tuple(np.round(np.concatenate([np.ravel(cam.extrinsic), np.ravel(cam.intrinsic)]), 6))
            if key in seen:
                raise GraMiInputError(
                    self.calib_path, f"cameras {seen[key]} and {name} have one pose and intrinsics: a camera listed twice", field="cameras"
                )
            seen[key] = name
        if not (np.isfinite(self.units) and self.units > 0):
            raise GraMiInputError(self.calib_path, f"units must be a positive length in metres, got {self.units}")

    def _check_leds(self) -> None:
        from scipy.spatial import cKDTree

        where = self.leds_path or self.calib_path
        leds = np.asarray(self.leds, float)
        if leds.ndim != 2 or leds.shape[1] != 3 or not np.isfinite(leds).all():
            raise GraMiInputError(where, "LED positions must be finite (x, y, z) triples")
        pairs = sorted(cKDTree(leds).query_pairs(1e-6)) if len(leds) > 1 else []
        if pairs:
            a, b = pairs[0]
            raise GraMiInputError(where, f"LEDs {a} and {b} are at one position {leds[a].round(6).tolist()}: an LED listed twice")

    def _check_meshes(self) -> None:
        for k, mesh in enumerate(self.meshes):
            bad = ~np.isfinite(np.asarray(mesh.positions, float)).all(axis=1)
            if bad.any():
                raise GraMiInputError(
                    self.folder, f"the mesh of pose {k} has {int(bad.sum())} non-finite vertices (first: {int(np.argmax(bad))})"
                )

    def _check_frames(self) -> None:
        keys = [key for key, _, _ in self.frames]
        if not keys:
            raise GraMiInputError(self.folder, "no frames to import")
        if twice := sorted({k for k in keys if keys.count(k) > 1}):
            raise GraMiInputError(self.folder, f"frame {twice[0]} is listed twice")
        # One name, one thing: envmaps are stored by file name; two different files with one name get distinct names.
        stored: dict[str, Path] = {}
        for _, entry, drive in self.frames:
            if entry.kind != "envmap":
                continue
            name, source = entry.envmap, Path(drive).resolve()
            if name in stored and stored[name] != source:
                stem, suffix = Path(name).stem, Path(name).suffix
                n = 1
                while f"envmaps/{stem}_{n}{suffix}" in stored and stored[f"envmaps/{stem}_{n}{suffix}"] != source:
                    n += 1
                entry.envmap = name = f"envmaps/{stem}_{n}{suffix}"
            stored[name] = source

    def mesh_metres(self, positions: np.ndarray) -> np.ndarray:
        return positions * (self.units if self.mesh_units is None else self.mesh_units)


# --------------------------------------------------------------------------------------------------------------
# The world frame
# --------------------------------------------------------------------------------------------------------------


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
    mesh_m = source.mesh_metres(np.concatenate([m.positions for m in source.meshes]))
    # the floor under the subject the cameras see: vertices inside the LED sphere (a stray vertex 100 m away is not)
    inside = np.linalg.norm(mesh_m - centre, axis=1) < radius
    heights = ((mesh_m[inside] if inside.any() else mesh_m) - centre) @ rotation.T
    floor = float(heights[:, 1].min())
    translation = -rotation @ centre - np.array([0.0, floor, 0.0])
    return WorldFrame(rotation, translation, direction, up == "auto", off_axis, radius, rms)


# --------------------------------------------------------------------------------------------------------------
# Cameras, LEDs, the mesh in gra-mi's frame
# --------------------------------------------------------------------------------------------------------------


@dataclass
class CameraPlan:
    """A source camera as gra-mi stores it: square pixels, scaled; and how its images are resampled."""

    index: int
    camera: Camera
    source_size: tuple[int, int]
    square_width: int  # columns after making the pixels square (before the scale)
    anisotropy: float  # fx / fy of the source


def plan_camera(source: Source, index: int, frame: WorldFrame, scale: float) -> CameraPlan:
    """Non-square pixels (fx ≠ fy) are resampled along x to fx = fy; then both axes by ``scale``. Whatever rounding
    the sizes leave (a fraction of a pixel over the width) is split evenly between fx and fy."""
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
    return CameraPlan(index, camera, (width, height), square_width, fx / fy)


def resample_image(image: np.ndarray, plan: CameraPlan) -> np.ndarray:
    """A source image onto the planned camera's pixel grid (area-weighted along each axis)."""
    w, h = plan.camera.width, plan.camera.height
    if image.shape[1] != w:
        image = resample_columns(image, w)
    if image.shape[0] != h:
        image = np.swapaxes(resample_columns(np.swapaxes(image, 0, 1), h), 0, 1)
    return image


def build_stage(source: Source, frame: WorldFrame, plans: list[CameraPlan], led_intensity: float) -> Lightstage:
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
        max_led_intensity=led_intensity,
    )


def build_sequence(source: Source, frame: WorldFrame, uv_resolution: int) -> tuple[MeshSequence, str]:
    """The poses as a sequence in the first mesh's own UV atlas, or one generated for it (a vertex per position and
    UV pair); every pose must share its topology (a tracked mesh). Also says where the atlas came from."""
    first = source.meshes[0]
    if first.face_uvs is None:
        first.uvs, first.face_uvs, said = generate_atlas(first.positions, first.faces, uv_resolution)
    else:
        said = "the mesh's own"
    faces, position_of, uv_of = split_uv_seams(first.faces, first.face_uvs)
    for k, mesh in enumerate(source.meshes[1:], 1):
        if mesh.positions.shape != first.positions.shape or not np.array_equal(mesh.faces, first.faces):
            raise GraMiInputError(
                source.folder, f"mesh {k} has another topology than mesh 0: a tracked sequence keeps its vertices and faces"
            )
    vertices = np.stack([frame.apply(source.mesh_metres(m.positions[position_of])) for m in source.meshes]).astype(np.float32)
    labels = [f"pose {k}" for k in range(len(source.meshes))]
    uvs = first.uvs[uv_of].astype(np.float32)
    return MeshSequence(faces, uvs, vertices, vertex_normals(vertices, faces), fps=1.0, frame_labels=labels), said


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


# --------------------------------------------------------------------------------------------------------------
# The check that catches convention mistakes: the mesh reprojected over each camera's mask
# --------------------------------------------------------------------------------------------------------------

MISTAKES = {
    "the extrinsic read as world-to-camera (it is camera-to-world)": "inverted",
    "OpenGL camera axes (y up, z backwards) instead of OpenCV's": "opengl",
    "a calibration in metres read as millimetres": "metres",
    "a calibration in millimetres read as metres": "millimetres",
}


def frame_mask(source: Source, plan: CameraPlan, key: int, image: tuple | None = None) -> np.ndarray:
    """A frame's mask on the camera's planned grid: the frame's own mask file (a moving subject), the camera's mask
    file, else the image's alpha, else the pixels the subject covers in the (masked, black-background) images: for a
    static pose the union over all the camera's images (an OLAT alone leaves part of the subject black), for a
    sequence the frame's own. ``image``: the frame's (RGB, alpha) when the caller has read it already."""
    own = source.frame_masks[plan.index].get(key) if source.frame_masks else None
    if own is not None:
        return _mask_file(own, plan)
    if plan.index in source.mask_cache:  # a camera's mask file, or a static pose's covered pixels: every frame's
        return source.mask_cache[plan.index]
    if source.masks[plan.index] is not None:
        source.mask_cache[plan.index] = _mask_file(source.masks[plan.index], plan)
        return source.mask_cache[plan.index]
    path = source.images[plan.index][key]
    rgb, alpha = image if image is not None else read_image(path)[::2]
    if alpha is None and len(source.meshes) == 1:
        source.mask_cache[plan.index] = resample_image(_covered(source, plan.index)[..., None], plan)[..., 0]
        return source.mask_cache[plan.index]
    mask = alpha.astype(np.float32) if alpha is not None else (rgb.max(axis=-1) > 0).astype(np.float32)  # a matte stays soft
    return resample_image(mask[..., None], plan)[..., 0]


def _mask_file(path: Path, plan: CameraPlan) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as image:
            mask = (np.asarray(image.convert("L")) > 127).astype(np.float32)
    except (OSError, SyntaxError, ValueError) as exc:
        raise GraMiInputError(path, f"not a readable mask ({exc})") from None
    if mask.shape[::-1] != plan.source_size:
        raise GraMiInputError(path, f"is {mask.shape[1]}x{mask.shape[0]}, its camera's images {plan.source_size[0]}x{plan.source_size[1]}")
    return resample_image(mask[..., None], plan)[..., 0]


def _covered(source: Source, camera: int) -> np.ndarray:
    """Pixels lit in any image of a camera, on its source grid."""
    covered = None
    for key, _, _ in progress(source.frames, description=f"mask of {source.names[camera]}"):
        lit = read_image(source.images[camera][key])[0].max(axis=-1) > 0
        covered = lit if covered is None else covered | lit
    return covered.astype(np.float32)


def mask_iou(sequence: MeshSequence, camera: Camera, mask: np.ndarray, pose: int = 0) -> tuple[float, np.ndarray]:
    from gra_mi.render.rasterize import silhouette

    seen = silhouette(sequence.vertices[pose], sequence.faces, camera)
    inside = mask > 0.5
    union = int((seen | inside).sum())
    return (float((seen & inside).sum()) / union if union else 0.0), seen


def _rescaled(sequence: MeshSequence, frame: WorldFrame, factor: float) -> MeshSequence:
    """The sequence as it would be with the mesh's units ``factor`` × what they were read as, in the same world frame as
    the cameras (whose floor, taken from the misread mesh, is off by as much as the mesh's)."""
    from dataclasses import replace

    vertices = factor * (np.asarray(sequence.vertices, float) - frame.translation) + frame.translation
    return replace(sequence, vertices=vertices.astype(np.float32))


def _mistaken(extrinsic: np.ndarray, kind: str) -> np.ndarray:
    """A source camera-to-world (3 × 4, the source's units) with ``kind``'s mistake undone."""
    m = np.eye(4)
    m[:3] = extrinsic
    if kind == "inverted":
        m = np.linalg.inv(m)
    elif kind == "opengl":
        m[:3, 1:3] *= -1
    elif kind == "metres":
        m[:3, 3] *= 1000.0
    elif kind == "millimetres":
        m[:3, 3] /= 1000.0
    return m[:3]


def likely_mistake(
    source: Source,
    frame: WorldFrame,
    plan: CameraPlan,
    sequence: MeshSequence,
    mask: np.ndarray,
    pose: int,
    plans: list[CameraPlan] | None = None,
    masks: list | None = None,
) -> str:
    """Which mistake, undone in the source's own calibration, makes the reprojection fit the mask (the best of them),
    in words with the IoU it reaches: a convention (inverted, OpenGL axes, units), the mesh's units, or the camera's
    calibration swapped with another camera's."""
    from dataclasses import replace

    scores = {}
    for said, kind in MISTAKES.items():
        calib = list(source.calib)
        calib[plan.index] = replace(calib[plan.index], extrinsic=_mistaken(calib[plan.index].extrinsic, kind))
        camera = plan_camera(replace(source, calib=calib), plan.index, frame, plan.camera.width / plan.square_width).camera
        scores[said] = mask_iou(sequence, camera, mask, pose)[0]
    for k, said in (
        (1e-3, "a mesh in millimetres read as metres (--mesh-units mm)"),
        (1e3, "a mesh in metres read as millimetres (--mesh-units m)"),
    ):
        scores[said] = mask_iou(_rescaled(sequence, frame, k), plan.camera, mask, pose)[0]
    for other, other_mask in zip(plans or [], masks or [], strict=True):  # swapped calibrations: both fit once exchanged
        if other.index == plan.index:
            continue
        calib = list(source.calib)
        calib[plan.index], calib[other.index] = calib[other.index], calib[plan.index]
        swapped = replace(source, calib=calib)
        scale = plan.camera.width / plan.square_width
        mine = mask_iou(sequence, plan_camera(swapped, plan.index, frame, scale).camera, mask, pose)[0]
        theirs = mask_iou(sequence, plan_camera(swapped, other.index, frame, scale).camera, other_mask, pose)[0]
        scores[f"the calibrations of {plan.camera.name} and {other.camera.name} swapped (camera order)"] = min(mine, theirs)
    best = max(scores, key=scores.get)
    if scores[best] >= 0.5:  # explanations one view cannot tell apart (calibration or mesh units) are all named
        alike = [said for said in scores if scores[said] >= scores[best] - 0.03]
        return f"likely {' or '.join(alike)} (IoU {scores[best]:.2f} if so)"
    return "no single convention mistake explains it: check the calibration's units, axes and camera order against the images"


# --------------------------------------------------------------------------------------------------------------
# Frames: the white frame and the OLATs, each its own lighting of the one pose
# --------------------------------------------------------------------------------------------------------------


def check_images_present(source: Source, plans: list[CameraPlan]) -> None:
    for plan in plans:
        for key, _, drive in source.frames:
            path = source.images[plan.index].get(key)
            if path is None:
                what = {"white": "the white frame"}.get(drive, f"the OLAT of LED {drive + 1}" if isinstance(drive, int) else "its lighting")
                raise GraMiInputError(source.folder, f"camera {plan.camera.name} has no image of frame {key:06d} ({what})")
            if image_size(path) != plan.source_size:
                raise GraMiInputError(path, f"is {image_size(path)}, other images of {plan.camera.name} are {plan.source_size}")


# --------------------------------------------------------------------------------------------------------------
# The import
# --------------------------------------------------------------------------------------------------------------


def import_capture(
    source: Source, out: Path, config: ImportConfig, record: dict, overwrite: bool = False, options=None, shard: Shard | None = None
) -> Capture | None:
    """The import, whatever the source: its checks, frame, cameras, the reprojection check, then the files.

    Everything is built in a staging folder beside ``out`` (:func:`gra_mi.core.guard.staging_folder`; an interrupted
    import resumes there), loaded back with gra-mi's own readers, and published by renaming it to ``out`` only when
    they accept it: a failure leaves nothing at ``out``. ``shard``: import only its frames' images (every shard writes
    the rig and subject alike); the shard that finds every shard's images done checks and publishes the capture and
    returns it, the others return None."""

    source.check()
    ensure_mitsuba()
    frame = world_frame(source, config.up)
    plans = _camera_plans(source, frame, config)
    eval_cameras = config.eval_cameras or _held_out(plans)
    train_cameras = [p.camera.name for p in plans if p.camera.name not in eval_cameras]
    if not train_cameras:
        raise GraMiParameterError("eval_cameras", "holds every imported camera: at least one camera must be left to fit on")
    check_images_present(source, plans)
    check_envmaps(source)
    sequence, atlas_said = build_sequence(source, frame, config.uv_resolution)
    key, pose = source.frames[0][0], source.frames[0][1].mesh_frame  # the frame every camera's mask is checked on
    masks = [frame_mask(source, plan, key) for plan in plans]
    checks = _reprojection_checks(source, frame, sequence, plans, masks, config.min_iou, pose)
    said = asdict(config) | (asdict(options) if options is not None else {})
    shard, command = shard or Shard(), f"import {source.format}"
    inputs = {"source": source.folder, "files outside the source": files_read_outside(source)}
    if (done := _already_published(out, run_record(command, inputs, said), overwrite)) is not None:
        return done
    staging = staging_folder(out)
    claim_output(staging, command, inputs, said, shard=shard, restart=shard.whole)  # a changed source restarts the staging
    stage = build_stage(source, frame, plans, config.led_intensity)
    _write_stage_files(staging, stage, sequence, source.frames)
    record = {"format": source.format, "folder": str(source.folder), "transform": frame.matrix(), **record}
    record |= {"gains": "assumed equal (the source has none)", "left_out_leds": source.left_out, "uv_atlas": atlas_said, "images": {}}
    frames = [f for _, f, _ in source.frames]
    capture = Capture(staging, source.format, "captured", config.uv_resolution, train_cameras, eval_cameras, frames, source=record)
    mine = shard.take(source.frames)
    saturated = {plan.camera.name: _import_camera(source, plan, capture, mine) for plan in plans}
    if not shard.whole:
        saturated = _merge_shards(staging, shard, saturated)
        if saturated is None:
            return None  # other shards' images are still being written: the last shard checks and publishes
    for plan in plans:
        record["images"][plan.camera.name] = _camera_summary(source, plan, saturated[plan.camera.name])
    capture.save()
    _write_report(staging, source, frame, plans, checks, record)
    shutil.rmtree(staging / "parts", ignore_errors=True)
    check_loadable(staging, source)
    publish(staging, out)
    return Capture.load(out)


def files_read_outside(source: Source) -> list[Path]:
    """Every file the import reads that lies outside the source folder (a mesh, LED file, lighting file, envmaps or
    images reached through ``../``): the run's provenance covers them by content, so an edited one is another run."""
    folder = source.folder.resolve()
    found = {source.calib_path, source.leds_path, *(p for images in source.images for p in images.values())}
    found |= {p for p in source.masks if p is not None} | {Path(d) for _, f, d in source.frames if f.kind == "envmap"}
    found |= {p for masks in source.frame_masks or [] for p in masks.values()}
    found |= {Path(d[1]) for _, _, d in source.frames if isinstance(d, tuple) and d[0] == "pattern"}
    found |= set(source.mesh_files)
    return sorted(p for p in found if p is not None and folder not in Path(p).resolve().parents)


def check_envmaps(source: Source) -> None:
    """Every environment map a frame names, read as the HDR image it claims to be (finite, non-negative, 2:1), before
    anything is written: a text file, a NaN map or a file reached through ``../`` by mistake stops here, by name."""
    from gra_mi.stage.envmap import load_envmap

    for path in sorted({Path(d) for _, f, d in source.frames if f.kind == "envmap"}):
        load_envmap(path)


def _already_published(out: Path, record: dict, overwrite: bool) -> Capture | None:
    """The capture at ``out`` when this same import already finished there; None when ``out`` is new or empty (or
    ``overwrite``: it is replaced on publishing); otherwise the difference is named."""
    if not out.exists() or (out.is_dir() and not any(out.iterdir())):
        return None
    if not out.is_dir():
        raise GraMiInputError(out, "is a file; expected an output folder")
    differences = run_differences(out, record)
    if differences is None:
        raise GraMiInputError(out, "is not empty and was not made by gra-mi (no provenance.json); choose an empty or new output folder")
    if overwrite:
        return None
    if differences:
        raise GraMiInputError(
            out / PROVENANCE,
            f"this folder was made by another run ({'; '.join(differences)}). Use --overwrite to start over, or choose another output folder",
        )
    capture = Capture.load(out)
    cameras = capture.train_cameras + capture.eval_cameras
    if all(capture.image_path(c, f.frame).is_file() for c in cameras for f in capture.frames):
        logger.info("%s: this import is already complete", out)
        return capture
    logger.info("%s: images are missing; the import resumes", out)
    staging = staging_folder(out)
    shutil.rmtree(staging, ignore_errors=True)  # a leftover of an older attempt: the published images are newer
    os.replace(out, staging)  # back into staging: published again once complete and checked
    return None


def check_loadable(staging: Path, source: Source) -> None:
    """gra-mi's own readers on the staged capture: the capture record, its calibration, the subject, every frame's
    lighting and every image. What they refuse is a fault of the import (its source passed every check), said so."""
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    try:
        capture = Capture.load(staging)
        stage = load_calibration(staging / "rig" / "calibration.json")
        load_sequence(staging / "subject")
        for entry in capture.frames:
            capture.lighting(stage, entry)
        capture.check_images()
    except GraMiInputError as exc:
        raise GraMiInputError(source.folder, f"the import of this source would not load in gra-mi ({exc}); please report it") from None


def publish(staging: Path, out: Path) -> None:
    """Rename the checked staging folder to ``out`` (replacing an older import there: ``--overwrite``)."""
    release_folder(staging)
    if out.exists():
        shutil.rmtree(out)
    os.replace(staging, out)


def _merge_shards(out: Path, shard: Shard, saturated: dict[str, list[float]]) -> dict[str, list[float]] | None:
    """Record this shard's per-camera saturation; every shard's, once all are recorded (else None)."""
    parts = [out / "parts" / f"import-shard-{i}-of-{shard.count}.json" for i in range(shard.count)]
    atomic_write_text(parts[shard.index], json.dumps(saturated) + "\n")
    if not all(p.is_file() for p in parts):
        return None
    merged: dict[str, list[float]] = {}
    for part in parts:
        for cam, values in json.loads(part.read_text()).items():
            merged.setdefault(cam, []).extend(values)
    return merged


def _held_out(plans: list[CameraPlan]) -> list[str]:
    """Two cameras spread over the rig for novel-view evaluation (one with 3 or fewer; none with one)."""
    if len(plans) < 2:
        return []
    picks = [len(plans) // 4, (3 * len(plans)) // 4] if len(plans) > 3 else [len(plans) - 1]
    return [plans[k].camera.name for k in dict.fromkeys(picks)]


def _camera_plans(source: Source, frame: WorldFrame, config: ImportConfig) -> list[CameraPlan]:
    names = source.names
    chosen = config.cameras or names
    unknown = [c for c in chosen + (config.eval_cameras or []) if c not in names]
    if unknown:
        raise GraMiParameterError("cameras", f"no camera {', '.join(unknown)} in {source.calib_path} (it has {names[0]} … {names[-1]})")
    if config.eval_cameras and not set(config.eval_cameras) <= set(chosen):
        raise GraMiParameterError("eval_cameras", "held-out cameras must be among the imported ones (--cameras)")
    return [plan_camera(source, names.index(c), frame, config.scale) for c in chosen]


def _reprojection_checks(
    source: Source, frame: WorldFrame, sequence, plans: list[CameraPlan], masks: list, min_iou: float, pose: int
) -> list[dict]:
    """Per camera, the mesh reprojected over its mask: IoU and the silhouette (for the overlays). What would spoil the
    comparison is ruled out first (an empty or full mask, images too small to compare, a subject lying on its side);
    a camera below ``min_iou``, or far below the others (a swapped pair passes a loose threshold), stops the import
    naming the likely cause with the IoUs."""
    _check_upright(source, frame, sequence, pose)
    for plan, mask in zip(plans, masks, strict=True):
        _check_mask(source, plan, mask)
    checks = []
    for plan, mask in progress(list(zip(plans, masks, strict=True)), description="mesh over masks"):
        iou, seen = mask_iou(sequence, plan.camera, mask, pose)
        checks.append({"camera": plan.camera.name, "iou": iou, "silhouette": seen})
    median = float(np.median([c["iou"] for c in checks]))
    for plan, mask, check in zip(plans, masks, checks, strict=True):
        iou = check["iou"]
        if iou < min_iou or (len(plans) > 2 and iou < median - OUTLIER_IOU):
            below = f"(< {min_iou})" if iou < min_iou else f"(the other cameras' median is {median:.2f})"
            raise GraMiInputError(
                source.calib_path,
                f"camera {plan.camera.name}: the mesh reprojected over its mask overlaps it by IoU {iou:.2f} {below}; "
                + likely_mistake(source, frame, plan, sequence, mask, pose, plans, masks),
            )
    return checks


OUTLIER_IOU = 0.1  # a camera this far below the others' median IoU is wrong even above the threshold
MIN_CHECK_PIXELS = 16  # images smaller than this on a side cannot be compared with the mesh


def _check_mask(source: Source, plan: CameraPlan, mask: np.ndarray) -> None:
    """A mask that is empty, full or too small to compare is named as the culprit, not the calibration."""
    where = source.masks[plan.index] or source.images[plan.index][source.frames[0][0]]
    if min(mask.shape) < MIN_CHECK_PIXELS:
        raise GraMiParameterError(
            "scale", f"leaves camera {plan.camera.name}'s images at {mask.shape[1]} × {mask.shape[0]} pixels, too small to import or check"
        )
    covered = float((mask > 0.5).mean())
    if covered < 1e-3:
        raise GraMiInputError(where, f"camera {plan.camera.name}: the subject's mask is empty (it must show the subject)")
    if covered > 0.99:
        raise GraMiInputError(
            where, f"camera {plan.camera.name}: the subject's mask covers the whole image (it must show the subject alone)"
        )


def _check_upright(source: Source, frame: WorldFrame, sequence, pose: int) -> None:
    """A subject whose height is well below its width along the chosen up axis would import lying on its side."""
    v = np.asarray(sequence.vertices[pose], float)
    low, high = np.percentile(v, [1, 99], axis=0)
    extent = high - low
    if extent[1] < 0.6 * max(extent[0], extent[2]):
        axis = "the up axis estimated from the cameras" if frame.up_estimated else "--up"
        raise GraMiInputError(
            source.folder,
            f"the subject is {extent[1]:.2f} m tall and {max(extent[0], extent[2]):.2f} m wide along {axis}: it would import lying "
            "on its side. Give the source's up axis with --up (e.g. +z for a Z-up source)",
        )


def _write_stage_files(out: Path, stage: Lightstage, sequence: MeshSequence, frames: list) -> None:

    write_rig(stage, out / "rig")
    if not (out / "subject" / "sequence.npz").is_file():
        save_sequence(sequence, out / "subject")
    atomic_write_text(out / "scene.xml", subject_scene_xml("rig", "subject"))
    for _, entry, drive in frames:
        if entry.kind == "envmap":  # the source's map, copied in so the capture stands on its own
            target = out / entry.envmap
            if not target.is_file():
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(drive, target)
            continue
        atomic_write_text(out / entry.pattern, json.dumps({"intensities": _drive(stage, drive).tolist()}) + "\n")


def _drive(stage: Lightstage, drive) -> np.ndarray:
    """LED intensities of a frame's lighting: "white" (every LED at the maximum), an LED index (its OLAT),
    ("uniform", fraction of the maximum) or ("pattern", a drive file of the source)."""
    if drive == "white":
        return uniform_pattern(stage, 1.0)
    if isinstance(drive, tuple) and drive[0] == "uniform":
        return uniform_pattern(stage, drive[1])
    if isinstance(drive, tuple) and drive[0] == "pattern":
        return load_pattern(stage, drive[1])
    return olat_pattern(stage, drive)


def _import_camera(source: Source, plan: CameraPlan, capture: Capture, frames: list) -> list[float]:
    """The ``frames`` of one camera, one image at a time: sRGB → linear, onto the planned grid, its mask as alpha.
    Returns each frame's fraction of saturated subject pixels."""
    saturated, name = [], plan.camera.name
    for key, entry, _ in progress(frames, description=f"import {name}"):
        path = capture.image_path(name, entry.frame)
        image_path = source.images[plan.index][key]
        rgb, clipped, alpha = read_image(image_path)
        mask = frame_mask(source, plan, key, (rgb, alpha))  # the image decoded once
        saturated.append(float((clipped & (mask_at_source(mask, plan) > 0.5)).mean()) if clipped.any() else 0.0)
        if path.is_file():
            continue
        if clipped.any():  # a planned pixel any clipped source pixel contributes to is left out of the fit
            write_mask(capture.saturation_path(name, entry.frame), resample_image(clipped[..., None].astype(np.float32), plan)[..., 0] > 0)
        rgb = resample_image(rgb, plan)
        if alpha is None:  # a binary mask: the background is cut away
            rgb = rgb * (mask[..., None] > 0.5)
        elif image_path.suffix.lower() != ".exr":  # straight alpha (PNG, AVIF) → premultiplied, as EXR holds it
            rgb = rgb * mask[..., None]
        write_exr(path, np.concatenate([rgb, mask[..., None]], axis=-1).astype(np.float32))
    return saturated


def _camera_summary(source: Source, plan: CameraPlan, saturated: list[float]) -> dict:
    """What the report says of a camera's images: saturation, the square-pixel resampling's error."""
    first = read_image(source.images[plan.index][source.frames[0][0]])[0]
    return {"saturated_fraction": max(saturated), "resampling_error": _resampling_error(first, plan), "anisotropy": plan.anisotropy}


def mask_at_source(mask: np.ndarray, plan: CameraPlan) -> np.ndarray:
    """The planned-grid mask back on the source grid (nearest), to count saturated subject pixels there."""
    w, h = plan.source_size
    rows = np.minimum((np.arange(h) + 0.5) * mask.shape[0] / h, mask.shape[0] - 1).astype(int)
    cols = np.minimum((np.arange(w) + 0.5) * mask.shape[1] / w, mask.shape[1] - 1).astype(int)
    return mask[np.ix_(rows, cols)]


def _resampling_error(image: np.ndarray, plan: CameraPlan) -> float | None:
    """Relative RMSE of the white frame taken to square pixels and back, over lit pixels (None: already square)."""
    if plan.square_width == plan.source_size[0]:
        return None
    there = resample_columns(image, plan.square_width)
    back = resample_columns(there, plan.source_size[0])
    lit = image.max(axis=-1) > 0
    return float(np.sqrt(np.mean((back - image)[lit] ** 2)) / max(float(np.sqrt(np.mean(image[lit] ** 2))), 1e-12))


# --------------------------------------------------------------------------------------------------------------
# The import report
# --------------------------------------------------------------------------------------------------------------


def linearity(source: Source, plan: CameraPlan, mask: np.ndarray) -> dict:
    """The white frame against the sum of every OLAT (door LEDs included) of one camera, over the subject: 1 for a
    linear sensor, a subject that held still and equal LED gains."""
    inside = mask_at_source(mask, plan) > 0.5
    total = np.zeros(int(inside.sum()) * 3)
    for number in progress(source.olat_keys, description=f"linearity {plan.camera.name}"):
        if number in source.images[plan.index]:
            total += read_image(source.images[plan.index][number])[0][inside].ravel()
    white = read_image(source.images[plan.index][source.white])[0][inside].ravel()
    ratio = float(total.sum() / max(white.sum(), 1e-12))
    return {"camera": plan.camera.name, "olats_over_white": ratio, "olats": len(source.olat_keys)}


def _write_report(out: Path, source: Source, frame: WorldFrame, plans: list[CameraPlan], checks: list[dict], record: dict) -> None:
    """import_report.json and .md, and an overlay per camera (mask green, reprojected mesh magenta, both white)."""
    check_of = {c["camera"]: c for c in checks}
    for plan in plans:
        mask = read_exr(out / "images" / plan.camera.name / "frame_0000.exr")[..., 3] > 0.5
        seen = check_of[plan.camera.name]["silhouette"]
        overlay = np.stack([seen.astype(float), mask.astype(float), seen.astype(float)], axis=-1)
        write_png(out / "import" / f"overlay_{plan.camera.name}.png", overlay, exposure=1.0)
    report = {
        "cameras": [{"camera": c["camera"], "mask_iou": round(c["iou"], 4)} | record["images"][c["camera"]] for c in checks],
        "frame": {
            "transform": frame.matrix(),
            "up_source": frame.up_source.round(6).tolist(),
            "up_estimated": frame.up_estimated,
            "up_off_axis_deg": round(frame.up_off_axis_deg, 3),
            "led_sphere_radius_m": round(frame.led_radius, 4),
            "led_sphere_rms_m": round(frame.led_fit_rms, 5),
        },
        "leds": {"count": len(source.leds), "left_out": record["left_out_leds"], "gains": record["gains"]},
        "linearity": linearity(source, plans[0], read_exr(out / "images" / plans[0].camera.name / "frame_0000.exr")[..., 3])
        if source.olat_keys is not None and source.white is not None
        else None,
        "frames": {"imported": sum(1 for _ in (out / "images" / plans[0].camera.name).glob("frame_*.exr"))},
        "uv_atlas": record["uv_atlas"],
    }
    atomic_write_text(out / "import_report.json", json.dumps(report, indent=1) + "\n")
    atomic_write_text(out / "import_report.md", import_markdown(report, source.format))


def import_markdown(r: dict, source_format: str) -> str:
    f, leds = r["frame"], r["leds"]
    lines = [
        "# Import report",
        "",
        f"Source: {source_format}. {len(r['cameras'])} cameras, {r['frames']['imported']} lightings each; {leds['count']} "
        f"LEDs, the OLATs of {len(leds['left_out'])} left out; LED gains {leds['gains']}. UV atlas: {r['uv_atlas']}.",
        "",
        f"Up in the source: {f['up_source']} ({'estimated from the cameras' if f['up_estimated'] else 'given'}, "
        f"{f['up_off_axis_deg']:.2f}° off its nearest axis). LED sphere: radius {f['led_sphere_radius_m']:.3f} m, the LEDs "
        f"within {1000 * f['led_sphere_rms_m']:.1f} mm RMS of it. The transform into gra-mi's frame (Y up, metres) is in "
        "capture.json (`source.transform`).",
        "",
        "| camera | mesh over mask (IoU) | saturated (subject, most of any image; left out of the fit) | fx / fy | square-pixel resampling error |",
        "|---|---|---|---|---|",
    ]
    for c in r["cameras"]:
        error = "—" if c["resampling_error"] is None else f"{100 * c['resampling_error']:.2f} %"
        lines.append(f"| {c['camera']} | {c['mask_iou']:.3f} | {100 * c['saturated_fraction']:.2f} % | {c['anisotropy']:.4f} | {error} |")
    if r["linearity"] is not None:
        lin = r["linearity"]
        lines += [
            "",
            f"Linearity ({lin['camera']}): the sum of the {lin['olats']} OLATs over the white frame is {lin['olats_over_white']:.3f} "
            "over the subject (1: a linear sensor, a subject that held still, equal LED gains).",
        ]
    lines += [
        "",
        "Overlays (green: the mask, magenta: the mesh reprojected, white: both): "
        + " ".join(f"![{c['camera']}](import/overlay_{c['camera']}.png)" for c in r["cameras"]),
    ]
    return "\n".join(lines) + "\n"
