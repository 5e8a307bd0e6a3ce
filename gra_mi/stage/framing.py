"""Framing cameras on the subject: a film crop window around the subject's projected box.

A camera of a rig sees the whole stage, and a moving subject covers a fraction of its frame; rendering (and fitting,
and scoring) the rest costs pixels that cannot see the subject. :func:`frame_subject` keeps each camera's position
and orientation and crops its sensor to the box the subject's sequence covers in it (with a margin), then scales
that box into a common image size: the same as cutting a crop window out of a larger sensor, so only the intrinsics
change (focal length and principal point). Each camera gets its own crop, so the subject fills every frame alike.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from gra_mi.core.errors import GraMiParameterError
from gra_mi.stage.lightstage import Camera


def subject_box(camera: Camera, points: np.ndarray) -> tuple[float, float, float, float]:
    """(u0, v0, u1, v1): the pixel box that ``points`` (N, 3, world) cover in ``camera`` (not clipped to the image).
    Raises if a point is behind or on the camera's plane (no crop window can hold it)."""
    projected = camera.project(np.asarray(points, dtype=np.float64))
    if not np.all(projected[:, 2] > 1e-6):
        raise GraMiParameterError("frame_subject", f"camera {camera.name}: the subject reaches behind the camera; no crop window holds it")
    u, v = projected[:, 0], projected[:, 1]
    return float(u.min()), float(v.min()), float(u.max()), float(v.max())


def frame_subject(cameras: list[Camera], points: np.ndarray, width: int, height: int, margin: float = 0.04) -> list[Camera]:
    """Each camera cropped to the subject's box (``points``: every vertex of every frame, or a sample of them) and
    scaled into ``width`` × ``height``: the box, grown by ``margin`` of the image on each side, fits the image and is
    centred in it. Position and orientation are kept."""
    if width < 1 or height < 1:
        raise GraMiParameterError("frame_subject", f"the image size must be positive, got {width}x{height}")
    if not 0 <= margin < 0.5:
        raise GraMiParameterError("frame_subject", f"the margin is a fraction of the image per side in [0, 0.5), got {margin}")
    framed = []
    for camera in cameras:
        u0, v0, u1, v1 = subject_box(camera, points)
        scale = min(width * (1 - 2 * margin) / max(u1 - u0, 1e-9), height * (1 - 2 * margin) / max(v1 - v0, 1e-9))
        framed.append(
            replace(
                camera,
                width=width,
                height=height,
                fx=camera.fx * scale,
                fy=camera.fy * scale,
                cx=width / 2.0 - scale * (0.5 * (u0 + u1) - camera.cx),
                cy=height / 2.0 - scale * (0.5 * (v0 + v1) - camera.cy),
            )
        )
    return framed
