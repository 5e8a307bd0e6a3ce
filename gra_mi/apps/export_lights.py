"""The near-field lights of a light path (``relight --lights``) as ``gra-mi export --lights`` hands them over: each light
sampled at every exported frame (time t shows the sequence's frame ``frames[t]``, as the avatar's), so that a DCC
tool's animation between samples is linear, as gra-mi's between keyframes.

A light's place is a 4 × 4 transform: its position, and for a spot a rotation that turns −Z (the axis along which
USD's ShapingAPI and glTF's spot lights shine) onto its direction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gra_mi.render.light_path import LightPath
from gra_mi.render.point_light import PointLight


@dataclass(frozen=True)
class LightTrack:
    """One light of a path at each exported frame."""

    name: str
    states: list[PointLight]

    @property
    def is_spot(self) -> bool:
        return self.states[0].is_spot

    def varies(self, read) -> bool:
        """Whether ``read(state)`` (a number or an array) changes over the exported frames (beyond the rounding of the
        interpolation between two equal keyframes)."""
        first = np.asarray(read(self.states[0]), np.float64)
        return any(not np.allclose(np.asarray(read(s), np.float64), first, rtol=1e-9, atol=0.0) for s in self.states[1:])


def light_tracks(path: LightPath, frames: list[int]) -> list[LightTrack]:
    """Each light of ``path`` at each of ``frames`` (all within its keyframes: checked here)."""
    path.check_frames(frames)
    return [LightTrack(light.name, [light.at(f) for f in frames]) for light in path.lights]


def light_to_world(light: PointLight) -> np.ndarray:
    """The light's 4 × 4 transform: at its position; a spot's −Z along its direction (its +Y as near world +Y as can
    be, so that a light aimed level stays upright)."""
    m = np.eye(4)
    m[:3, 3] = light.position
    if light.is_spot:
        back = -np.asarray(light.direction, np.float64)  # +Z, away from where it shines
        up = np.array([0.0, 1.0, 0.0]) if abs(back[1]) < 0.99 else np.array([1.0, 0.0, 0.0])
        x = np.cross(up, back)
        x /= np.linalg.norm(x)
        m[:3, :3] = np.stack([x, np.cross(back, x), back], axis=1)
    return m


def rotation_quaternion(m: np.ndarray) -> np.ndarray:
    """The unit quaternion (x, y, z, w) of a 3 × 3 rotation, w ≥ 0."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(np.asarray(m, np.float64)[:3, :3]).as_quat()
    return q if q[3] >= 0 else -q
