"""The tiny refiner's video autoencoder: AutoencoderKLWan's interface on a codec that keeps the image.

Why not a small ``AutoencoderKLWan``: its round trip is learnt from scratch, and on two CPU cores it stays far from
the image (measured on the demo's held-out frames: 10.8 dB for a 71 k-parameter one, 10.6 dB for a 3.2 M-parameter
one after 25 minutes; docs/results/refiner.md), so it lost more than every other stage together. This codec starts
as an exact one and learns only what lies above it:

- Causal in time as Wan's VAE: latent frame 0 holds pixel frame 0 alone (as a group of 4 copies), latent frame
  k ≥ 1 pixel frames 4k − 3 … 4k; 16 channels per 4 × 4 pixels (Wan2.1's: 16 per 8 × 8).
- Encoder: the 3 × 4 × 4 × 4 = 192 values of a block of 4 frames × 4 × 4 pixels → a linear map to 16 channels,
  plus a convolutional branch over neighbouring blocks. Initialised as the block means of each colour and frame
  (12 channels; 4 more start at zero), the branch at zero.
- Decoder: a linear map back to the 192 values, initialised to spread each mean over its block, plus a
  convolutional branch (zero at init).

At initialisation the round trip is the 4 × 4 block mean of every frame: exact wherever the output is area-averaged
4× (the refiner's subject crops are magnified 4× over the delivered frames, gra_mi.refiner.data). Training
(pipelines/pretrain_tiny_vae.py) teaches the branches the detail inside a block.

Interface (what the refiner uses of diffusers' ``AutoencoderKLWan``): ``encode(x).latent_dist.mode()``,
``decode(z).sample``, ``config.z_dim``, ``config.latents_mean``, ``config.latents_std``,
``config.scale_factor_spatial`` and ``config.scale_factor_temporal``.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import nn


class _Posterior:
    """A deterministic posterior: the refiner encodes with the mode, as diffusers' pipelines do."""

    def __init__(self, z: torch.Tensor):
        self.z = z

    def mode(self) -> torch.Tensor:
        return self.z

    def sample(self, generator=None) -> torch.Tensor:
        return self.z


def _branch(inputs: int, hidden: int, outputs: int) -> nn.Sequential:
    net = nn.Sequential(
        nn.Conv2d(inputs, hidden, 3, padding=1),
        nn.SiLU(),
        nn.Conv2d(hidden, hidden, 3, padding=1),
        nn.SiLU(),
        nn.Conv2d(hidden, outputs, 3, padding=1),
    )
    nn.init.zeros_(net[-1].weight)
    nn.init.zeros_(net[-1].bias)
    return net


class TinyVideoAutoencoder(nn.Module):
    """See the module docstring. Videos (B, 3, T, H, W) in [-1, 1], H and W multiples of ``spatial``."""

    def __init__(
        self,
        z_dim: int = 16,
        spatial: int = 4,
        temporal: int = 4,
        hidden: int = 64,
        latents_mean: list[float] | None = None,
        latents_std: list[float] | None = None,
    ):
        super().__init__()
        if z_dim < 3 * temporal:
            raise ValueError(f"z_dim {z_dim} cannot hold the block means of 3 colours × {temporal} frames")
        self.config = SimpleNamespace(
            z_dim=z_dim,
            scale_factor_spatial=spatial,
            scale_factor_temporal=temporal,
            hidden=hidden,
            latents_mean=list(latents_mean) if latents_mean is not None else [0.0] * z_dim,
            latents_std=list(latents_std) if latents_std is not None else [1.0] * z_dim,
        )
        block = 3 * temporal * spatial * spatial
        self.encode_linear = nn.Conv2d(block, z_dim, 1)
        self.encode_branch = _branch(block, hidden, z_dim)
        self.decode_linear = nn.Conv2d(z_dim, block, 1)
        self.decode_branch = _branch(z_dim, hidden, block)
        self.reset_to_block_means()

    @torch.no_grad()
    def reset_to_block_means(self) -> None:
        """The exact start: latent channel c·T + t is the mean of colour c over frame t's block; decoding spreads it back."""
        t, s = self.config.scale_factor_temporal, self.config.scale_factor_spatial
        area = s * s
        for layer in (self.encode_linear, self.decode_linear):
            nn.init.zeros_(layer.weight)
            nn.init.zeros_(layer.bias)
        for k in range(3 * t):  # the 192 inputs are ordered (colour, frame, y, x): block k is rows k·area … (k + 1)·area
            self.encode_linear.weight[k, k * area : (k + 1) * area] = 1.0 / area
            self.decode_linear.weight[k * area : (k + 1) * area, k] = 1.0
        for branch in (self.encode_branch, self.decode_branch):
            nn.init.zeros_(branch[-1].weight)
            nn.init.zeros_(branch[-1].bias)

    # -- layout ------------------------------------------------------------------------------------------------

    def _blocks(self, video: torch.Tensor) -> tuple[torch.Tensor, int]:
        """(B, 3, T, H, W) → (B·G, 192, H/s, W/s), G = 1 + ⌈(T − 1)/4⌉ groups (the first frame alone, repeated)."""
        b, c, frames, h, w = video.shape
        t, s = self.config.scale_factor_temporal, self.config.scale_factor_spatial
        if h % s or w % s:
            raise ValueError(f"video of {h}×{w} pixels: the tiny VAE needs multiples of {s}")
        rest = video[:, :, 1:]
        if rest.shape[2] % t:  # a last group cut short repeats its last frame
            rest = torch.cat([rest, rest[:, :, -1:].expand(-1, -1, t - rest.shape[2] % t, -1, -1)], dim=2)
        grouped = torch.cat([video[:, :, :1].expand(-1, -1, t, -1, -1), rest], dim=2)
        groups = grouped.shape[2] // t
        x = grouped.reshape(b, c, groups, t, h // s, s, w // s, s).permute(0, 2, 1, 3, 5, 7, 4, 6)
        return x.reshape(b * groups, c * t * s * s, h // s, w // s), groups

    def _frames(self, blocks: torch.Tensor, batch: int) -> torch.Tensor:
        """Inverse of :meth:`_blocks`: (B·G, 192, h, w) → (B, 3, 1 + 4(G − 1), H, W); group 0's copies are averaged."""
        t, s = self.config.scale_factor_temporal, self.config.scale_factor_spatial
        n, _, h, w = blocks.shape
        groups = n // batch
        x = blocks.reshape(batch, groups, 3, t, s, s, h, w).permute(0, 2, 1, 3, 6, 4, 7, 5).reshape(batch, 3, groups * t, h * s, w * s)
        return torch.cat([x[:, :, :t].mean(dim=2, keepdim=True), x[:, :, t:]], dim=2)

    # -- AutoencoderKLWan's interface ----------------------------------------------------------------------------

    def encode(self, video: torch.Tensor) -> SimpleNamespace:
        """(B, 3, T, H, W) → ``.latent_dist.mode()`` of shape (B, z_dim, 1 + ⌈(T − 1)/4⌉, H/4, W/4)."""
        blocks, groups = self._blocks(video)
        z = self.encode_linear(blocks) + self.encode_branch(blocks)
        b = video.shape[0]
        return SimpleNamespace(latent_dist=_Posterior(z.reshape(b, groups, *z.shape[1:]).transpose(1, 2)))

    def decode(self, latents: torch.Tensor) -> SimpleNamespace:
        """(B, z_dim, F, h, w) → ``.sample`` of shape (B, 3, 1 + 4(F − 1), 4h, 4w)."""
        b = latents.shape[0]
        z = latents.transpose(1, 2).flatten(0, 1)
        return SimpleNamespace(sample=self._frames(self.decode_linear(z) + self.decode_branch(z), b))
