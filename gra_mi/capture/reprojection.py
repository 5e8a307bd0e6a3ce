"""The check that catches what a calibration got wrong: the mesh reprojected over each camera's mask. What would spoil
the comparison is ruled out first (an empty or full mask, images too small, a subject lying on its side); a camera
that does not fit is named with the likely mistake and the IoU undoing it reaches (a convention, the mesh's units, two
cameras' calibrations swapped)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gra_mi.capture.placement import CameraPlan, WorldFrame, plan_camera, resample_image
from gra_mi.capture.source import Source
from gra_mi.capture.source_files import orientation_hint, read_image, read_mask
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.progress import progress
from gra_mi.stage.lightstage import Camera
from gra_mi.subject.sequence import MeshSequence

MISTAKES = {
    "the extrinsic read as world-to-camera (it is camera-to-world)": "inverted",
    "OpenGL camera axes (y up, z backwards) instead of OpenCV's": "opengl",
    "a calibration in metres read as millimetres": "metres",
    "a calibration in millimetres read as metres": "millimetres",
}
MASK_SOURCES = {  # where each source's masks go, for a capture whose images keep their background
    "humanolat": "POSE_<nn>/segmentations/masks/000/Cam<NN>.png",
    "transforms": "each frame's mask_path in the JSON",
    "easymocap": "mask/<cam>/<frame>.png",
}
ALIGNABLE = ("transforms", "easymocap", "colmap")  # the sources --align-cameras can move
OUTLIER_IOU = 0.1  # a camera this far below the others' median IoU is wrong even above the threshold
MIN_CHECK_PIXELS = 16  # images smaller than this on a side cannot be compared with the mesh


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
    mask = read_mask(path).astype(np.float32)
    if mask.shape[::-1] != plan.source_size:
        raise GraMiInputError(path, f"is {mask.shape[1]}x{mask.shape[0]}, its camera's images {plan.source_size[0]}x{plan.source_size[1]}")
    return resample_image(mask[..., None], plan)[..., 0]


def _covered(source: Source, camera: int) -> np.ndarray:
    """Pixels lit in any image of a camera, on its source grid."""
    covered = None
    for key, _, _ in progress(source.frames, description=f"mask of {source.names[camera]}"):
        if key not in source.images[camera]:
            continue  # a gap --missing-images skip lets through
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


def _other_mesh_frame(source: Source, sequence: MeshSequence, frame: WorldFrame) -> tuple[str, MeshSequence] | None:
    """Where --align-cameras moved the calibration: the sequence as it would be with the mesh in the other frame (moved
    with the cameras, or left among the LEDs), and those words; None without an alignment."""
    from dataclasses import replace

    if source.alignment is None:
        return None
    scale, rotation, translation = source.alignment_move
    metres = (np.asarray(sequence.vertices, float) - frame.translation) @ frame.rotation  # back to the source's metres
    if not source.mesh_moved:
        said, metres = (
            "a mesh tracked in the calibration's own frame (--mesh-frame calibration)",
            scale * metres @ rotation.T + translation * source.units,
        )
    else:
        said, metres = "a mesh in the LEDs' frame (--mesh-frame leds)", (metres - translation * source.units) @ rotation / scale
    return said, replace(sequence, vertices=(metres @ frame.rotation.T + frame.translation).astype(np.float32))


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
    if (other := _other_mesh_frame(source, sequence, frame)) is not None:
        scores[other[0]] = mask_iou(other[1], plan.camera, mask, pose)[0]
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
    if margin := _margin_around(sequence, plan.camera, mask, pose):
        return margin
    return "no single convention mistake explains it: check the calibration's units, axes and camera order against the images"


def _margin_around(sequence: MeshSequence, camera: Camera, mask: np.ndarray, pose: int) -> str | None:
    """The words for a mask that holds the whole reprojected mesh and more (the calibration is right; the mask is too
    big), else None."""
    seen, inside = mask_iou(sequence, camera, mask, pose)[1], mask > 0.5
    if not seen.any() or (seen & inside).sum() < 0.97 * seen.sum() or inside.sum() < 1.15 * seen.sum():
        return None
    return (f"the mesh lies inside the mask, which is {100 * (inside.sum() / seen.sum() - 1):.0f} % larger: the calibration "
            "fits, the mask holds more than the subject (taken from pixels that are not black: a soft edge, a glow, a noise "
            "floor or another object): give masks (mask files, or images with alpha)")  # fmt: skip


def reprojection_checks(
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
                + likely_mistake(source, frame, plan, sequence, mask, pose, plans, masks)
                + orientation_hint(next(iter(source.images[plan.index].values())))
                + _frame_hint(source, median, min_iou),
            )
    return checks


def _frame_hint(source: Source, median: float, min_iou: float) -> str:
    """Where most cameras miss the mesh and the calibration was taken as it is: it may be in a frame of its own (with
    --align-cameras, :func:`likely_mistake` tries the mesh in the other frame instead)."""
    if median >= min_iou or source.format not in ALIGNABLE or source.alignment is not None:
        return ""
    return (f"; most cameras miss it (median IoU {median:.2f}): a calibration in a frame of its own (a COLMAP "
            "reconstruction's, a chessboard's) comes into the LEDs' and the mesh's frame with --align-cameras PLACES "
            "(docs/data-format.md)")  # fmt: skip


def _check_mask(source: Source, plan: CameraPlan, mask: np.ndarray) -> None:
    """A mask that is empty, full or too small to compare is named as the culprit, not the calibration."""
    where = source.masks[plan.index] or next(iter(source.images[plan.index].values()))
    if min(mask.shape) < MIN_CHECK_PIXELS:
        raise GraMiParameterError(
            "scale", f"leaves camera {plan.camera.name}'s images at {mask.shape[1]} × {mask.shape[0]} pixels, too small to import or check"
        )
    covered = float((mask > 0.5).mean())
    if covered < 1e-3:
        raise GraMiInputError(where, f"camera {plan.camera.name}: the subject's mask is empty (it must show the subject)")
    if covered > 0.99:
        from_pixels = source.masks[plan.index] is None and not (source.frame_masks and source.frame_masks[plan.index])
        raise GraMiInputError(
            where, f"camera {plan.camera.name}: the subject's mask covers the whole image (it must show the subject alone)"
            + (f"; no mask file was given and its images keep their background: give masks ({MASK_SOURCES[source.format]})" if from_pixels else ""),
        )  # fmt: skip


def _check_upright(source: Source, frame: WorldFrame, sequence, pose: int) -> None:
    """A subject whose height is well below its width along the chosen up axis would import lying on its side: the
    source's up axis, or (where --align-cameras moved the calibration) the mesh in the other frame."""
    extent = _extent(sequence, pose)
    if extent[1] < 0.6 * max(extent[0], extent[2]):
        axis = "the up axis estimated from the cameras" if frame.up_estimated else "--up"
        other = _other_mesh_frame(source, sequence, frame)
        upright = other is not None and (e := _extent(other[1], pose))[1] >= 0.6 * max(e[0], e[2])
        raise GraMiInputError(
            source.folder,
            f"the subject is {extent[1]:.2f} m tall and {max(extent[0], extent[2]):.2f} m wide along {axis}: it would import lying "
            + (f"on its side; likely {other[0]}, where it stands" if upright else
               "on its side. Give the source's up axis with --up (e.g. +z for a Z-up source)"),
        )  # fmt: skip


def _extent(sequence, pose: int) -> np.ndarray:
    """The subject's size along each world axis (1st to 99th percentile of its vertices)."""
    low, high = np.percentile(np.asarray(sequence.vertices[pose], float), [1, 99], axis=0)
    return high - low
