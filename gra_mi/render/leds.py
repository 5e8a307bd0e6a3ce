"""The LEDs as the renderer sees them: one frozen record of where they are, the stage centre and whether they light
near field (points where they are) or far field (directions from the centre, an environment at infinity).

The far-field transform is written here once, and :attr:`LedLayout.digest` covers everything that changes a texel's
visibility bits, so the visibility cache can never hand one rig's bits to another.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True, eq=False)
class LedLayout:
    positions: np.ndarray
    """(L, 3) LED positions, metres, world frame."""
    center: np.ndarray
    """(3,) the stage centre: far field, LEDs are directions seen from here and their irradiance is measured here."""
    far_field: bool = False

    def __post_init__(self):
        object.__setattr__(self, "positions", np.asarray(self.positions, np.float64).reshape(-1, 3))
        object.__setattr__(self, "center", np.asarray(self.center, np.float64).reshape(3))

    @classmethod
    def of(cls, stage, far_field: bool = False) -> LedLayout:
        """A lightstage's LEDs (:class:`gra_mi.stage.lightstage.Lightstage`)."""
        return cls(stage.led_positions, stage.center, far_field)

    @property
    def num_leds(self) -> int:
        return int(self.positions.shape[0])

    @cached_property
    def digest(self) -> str:
        data = np.ascontiguousarray(self.positions, np.float32).tobytes() + np.ascontiguousarray(self.center, np.float32).tobytes()
        return hashlib.sha1(data + bytes([self.far_field])).hexdigest()[:16]

    def brightest(self, intensities: np.ndarray, k: int) -> np.ndarray:
        """The ``k`` brightest LEDs lit, each other LED's flux (at the centre, I / r²) given to its nearest lit one: the
        same energy from fewer LEDs, for light whose direction matters little (what reaches a texel after a bounce)."""
        intensities = np.asarray(intensities, np.float64)
        if k >= self.num_leds or np.count_nonzero(intensities.max(axis=1) > 0) <= k:
            return intensities.copy()
        keep = np.argsort(-intensities.sum(axis=1))[:k]
        offset = self.positions - self.center
        r2 = np.sum(offset**2, axis=1)
        direction = offset / np.sqrt(r2)[:, None]
        nearest = keep[np.argmax(direction @ direction[keep].T, axis=1)]
        moved = np.zeros_like(intensities)
        np.add.at(moved, nearest, intensities / r2[:, None])
        return moved * r2[:, None]

    def as_lights(self, intensities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(targets, intensities) as the shading loop and shadow rays take them. Near field: the LED positions and
        radiant intensities. Far field: unit directions from the centre and the irradiance I / r² measured there."""
        intensities = np.asarray(intensities, np.float64)
        if not self.far_field:
            return self.positions, intensities
        offset = self.positions - self.center
        r2 = np.sum(offset**2, axis=1, keepdims=True)
        return offset / np.sqrt(r2), intensities / r2
