"""The refiner's conditioning layout: VACE's control channels by name, the seed mask of a window, latent frame counts."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gra_mi.refiner.config import TEMPORAL_FACTOR


@dataclass(frozen=True)
class ControlChannels:
    """The VACE context's channels, as ``WanVACEPipeline`` stacks them: [inactive latents | reactive latents | the
    s × s latent mask] (``latent`` channels each, then s²). Views, so an in-place edit reaches the context."""

    latent: int

    def inactive(self, control: torch.Tensor) -> torch.Tensor:
        """The latents of the frames kept as they are (the reference, seed frames); zeros elsewhere."""
        return control[:, : self.latent]

    def reactive(self, control: torch.Tensor) -> torch.Tensor:
        """The latents of the frames to refine (the coarse input); zeros elsewhere."""
        return control[:, self.latent : 2 * self.latent]

    def mask(self, control: torch.Tensor) -> torch.Tensor:
        """The latent mask: 1 where the frame is refined (reactive), 0 where it is kept (inactive)."""
        return control[:, 2 * self.latent :]


def seed_mask(frames: int, height: int, width: int, seeded: int) -> torch.Tensor:
    """(1, 1, T, H, W): 1 = reactive (refine), 0 = inactive (the first ``seeded`` frames are kept)."""
    mask = torch.ones(1, 1, frames, height, width)
    mask[:, :, :seeded] = 0
    return mask


def latent_frames(pixel_frames: int) -> int:
    return (pixel_frames - 1) // TEMPORAL_FACTOR + 1


def pad_to_multiple(h: int, w: int, m: int = 16) -> tuple[int, int]:
    return int(math.ceil(h / m) * m), int(math.ceil(w / m) * m)
