"""Whether the captured images fit the stage's light: an albedo above 1 is a sign of a wrong scale, not of a material.

An import cannot know the LEDs' absolute intensity (``--led-intensity``: the source does not say), and the images are
in the camera's units. Albedo × LED intensity is what the images fix; with the intensity stated too low, every texel's
least-squares albedo reaches past 1 and is clipped there, so the fitted maps and every relight are too dark while the
fit itself runs to the end. Stated far too high, the albedo of skin and cloth comes out near black: the relights in
the capture's units still match, but the maps mean nothing outside them (an export renders the avatar black). This
module measures how far the unclipped albedo reaches, and where its middle lies, and says what to change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

OVER_SHARE = 0.05  # texels whose least-squares albedo exceeds 1 in a channel: more than this share is not noise
HIGH_QUANTILE = 0.95
DARK_MEDIAN = 0.02  # the median texel's brightest channel below this: no skin or cloth is so dark (coal is about 0.04)
TYPICAL_ALBEDO = 0.3  # a person's median albedo, roughly: what the warning sizes a re-import's --led-intensity for


@dataclass(frozen=True)
class AlbedoHeadroom:
    """The least-squares albedo of the observed texels before it is clipped to [0, 1]."""

    over: float  # share of observed texels with a channel above 1
    high: float  # the HIGH_QUANTILE of their largest channel
    median: float = 0.5  # the median of their largest channel

    @classmethod
    def of(cls, num: np.ndarray, den: np.ndarray) -> AlbedoHeadroom | None:
        """From the normal equations' sums (M, 3) of the least-squares albedo ``num / den``; None without a texel."""
        seen = (den > 0).all(axis=1)
        if not seen.any():
            return None
        largest = (num[seen] / den[seen]).max(axis=1)
        return cls(float((largest > 1.0).mean()), float(np.quantile(largest, HIGH_QUANTILE)), float(np.median(largest)))

    def warning(self, led_intensity: float, set_left_out: bool = False) -> str | None:
        """What to tell the user where the images are brighter than the stated LEDs can make any surface, or far darker
        than they make a person.
        ``set_left_out``: the fit models one bounce in a scene with a set, whose light (a floor's) the images hold."""
        if 0.0 < self.median < DARK_MEDIAN:
            return (
                f"half the observed texels' albedo is below {self.median:.2g} (no skin or cloth is so dark): the images are "
                f"darker than LEDs of {led_intensity:g} W/sr at full drive light any person, so the maps are near black "
                "outside this capture's units (an export, another renderer). Re-import with --led-intensity "
                f"{led_intensity * self.median / TYPICAL_ALBEDO:.3g} (a median albedo of {TYPICAL_ALBEDO:g}), or scale the images"
            )
        if self.over <= OVER_SHARE or self.high <= 1.0:
            return None
        cause = (
            "The capture's scene has a set (a floor, walls) whose light reaches the subject after the first bounce, which "
            "one bounce leaves to the albedo: fit with --bounces 2. If the albedo still exceeds 1, re-import"
            if set_left_out
            else "Re-import"
        )
        return (
            f"{100 * self.over:.0f} % of the observed texels' albedo would exceed 1 ({HIGH_QUANTILE:.0%} of them below "
            f"{self.high:.2f}): the images are brighter than LEDs of {led_intensity:g} W/sr at full drive can light any surface, "
            f"so the albedo is clipped at 1 and relights come out too dark. {cause} with --led-intensity "
            f"{led_intensity * self.high:.3g} or more (the source's LED intensity in the images' units), or scale the images"
        )
