"""RelightNet (paper Sec. 3.2, Supp. "Details about RelightNet"): a UV-space UNet that turns the coarse physics
texture into a pose- and illumination-aware texture.

- Input: the 15 channels of :mod:`gra_mi.render.bridge` (coarse texture 3 + normals of the last 3 frames 9 + view
  direction 3); output: 3 channels (linear RGB radiance).
- **Exposure-invariant** (:func:`exposure`): the coarse texture and the envmap are divided by the lighting's
  exposure (the coarse texture's mean over the covered texels) before the network sees them, and the output is
  multiplied back, so the same avatar under a 10× brighter light gives a 10× brighter texture, and every sample
  weighs the same in training whatever its lighting. The coarse texture enters as log(1 + radiance / exposure).
- **Output**: a per-texel gain g and offset b (normalised units) on the coarse texture,
  out = exposure · max(coarse / exposure · exp(g) + b, 0): non-negative by construction. The last convolution
  starts at zero, so an untrained RelightNet reproduces the microfacet render exactly (training starts from the
  physics, not from noise).
- The full-resolution work runs at R / ``patch`` (space-to-depth stem, depth-to-space head): the correction is
  smooth, the coarse texture carries the detail, and a 512² pass stays within 200 ms on 2 CPU cores.
- Resolutions ≥ 64²: convolution-only residual blocks. Below 64²: convolution + self-attention + cross-attention
  to environment-map tokens (4 heads).
- Environment tokens: a small CNN encodes the camera-space envmap E^κ (log of exposure-normalised radiance).

Weights are saved as safetensors with the config as JSON beside them (``relightnet.safetensors``,
``relightnet.json``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.render.bridge import IN_CHANNELS

FORMAT = "gra-mi-relightnet/2"
"""relightnet.json's format. 2: exposure-invariant output (1, additive absolute radiance, is refused). Files that a
gra-mi before 2026-12-02 wrote say ``"format": 2``: the same model, refused until the line reads this string."""
HINT = " (train one with `gra-mi train-relightnet`)"

TOP_LEVEL = 128  # the automatic patch puts the UNet's top level here
MAX_LOG_GAIN = 3.0  # the gain stays within e^±3: a correction, not a new image


@dataclass
class RelightNetConfig:
    resolution: int = 512
    """UV resolution of the texture (a power of two, ≥ 32)."""
    patch: int | None = None
    """Space-to-depth factor of the stem: the UNet's top level runs at resolution / patch. None: the factor that
    puts the top level at 128² (1 for 128², 2 for 256², 4 for 512²)."""
    base_channels: int = 16
    """Channels at the UNet's top level; doubled per level down to ``max_channels``."""
    max_channels: int = 128
    lowest_resolution: int = 16
    """The bottleneck's resolution."""
    attention_below: int = 64
    """Levels with a resolution below this get self- and cross-attention (the paper: 64)."""
    heads: int = 4
    env_height: int = 16
    """Height of the camera-space envmap fed to the token encoder (width = 2x)."""
    env_token_dim: int = 64
    in_channels: int = IN_CHANNELS
    out_channels: int = 3
    input_bounces: int = 1
    """The bounces of light in the coarse renders it was trained on (``--bounces``): it is fed the same."""
    output_gain: float = 1.0
    """One gain on the output, fitted after training (:func:`gra_mi.relightnet.train.calibrate_output_gain`) so
    that the training views keep their total light: L1 learns each pixel's median, and the light the coarse render
    misses is one-sided, so the network alone comes out a few per cent too dark."""

    def __post_init__(self):
        if self.patch is None:
            self.patch = int(min(4, max(1, self.resolution // TOP_LEVEL)))

    def levels(self) -> list[int]:
        res, out = self.resolution // self.patch, []
        while res >= self.lowest_resolution:
            out.append(res)
            res //= 2
        return out

    def channels(self, level: int) -> int:
        return min(self.base_channels * 2**level, self.max_channels)

    def validate(self) -> None:
        if self.resolution < 32 or self.resolution & (self.resolution - 1):
            raise GraMiInputError("relightnet.resolution", f"must be a power of two ≥ 32, got {self.resolution}")
        if self.patch not in (1, 2, 4) or self.resolution // self.patch < self.lowest_resolution:
            raise GraMiInputError("relightnet.patch", f"must be 1, 2 or 4 and leave ≥ {self.lowest_resolution}² texels, got {self.patch}")
        if any(self.channels(i) % self.heads for i, r in enumerate(self.levels()) if r < self.attention_below):
            raise GraMiInputError("relightnet.heads", "attention channels must divide by the number of heads")


def check_input_transport(config: RelightNetConfig, transport, where) -> None:
    """Refuse to feed a RelightNet coarse renders with other bounces of light than those it was trained on."""
    if config.input_bounces != transport.bounces:
        raise GraMiParameterError(
            "bounces",
            f"the RelightNet at {where} was trained on renders with {config.input_bounces} bounce(s) of light; "
            f"run with --bounces {config.input_bounces} (got {transport.bounces})",
        )


def _groups(channels: int) -> int:
    return math.gcd(channels, 8)


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.norm1, self.conv1 = nn.GroupNorm(_groups(cin), cin), nn.Conv2d(cin, cout, 3, padding=1)
        self.norm2, self.conv2 = nn.GroupNorm(_groups(cout), cout), nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()

    def forward(self, x):
        h = self.conv1(F.silu(self.norm1(x)))
        h = self.conv2(F.silu(self.norm2(h)))
        return self.skip(x) + h


class AttentionBlock(nn.Module):
    """Self-attention over the texels of a level, then cross-attention to the environment tokens."""

    def __init__(self, channels: int, heads: int, token_dim: int):
        super().__init__()
        self.norm_self = nn.LayerNorm(channels)
        self.self_attn = nn.MultiheadAttention(channels, heads, batch_first=True)
        self.norm_cross = nn.LayerNorm(channels)
        self.cross_attn = nn.MultiheadAttention(channels, heads, kdim=token_dim, vdim=token_dim, batch_first=True)

    def forward(self, x, tokens):
        n, c, h, w = x.shape
        t = x.flatten(2).transpose(1, 2)  # (N, HW, C)
        q = self.norm_self(t)
        t = t + self.self_attn(q, q, q, need_weights=False)[0]
        q = self.norm_cross(t)
        t = t + self.cross_attn(q, tokens, tokens, need_weights=False)[0]
        return t.transpose(1, 2).reshape(n, c, h, w)


class EnvEncoder(nn.Module):
    """Camera-space envmap (N, 3, H, 2H) → tokens (N, H/4 · H/2, D) with learned positions."""

    def __init__(self, env_height: int, dim: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, dim // 2, 3, padding=1), nn.SiLU(), nn.Conv2d(dim // 2, dim, 3, stride=2, padding=1), nn.SiLU(),
            nn.Conv2d(dim, dim, 3, stride=2, padding=1),
        )  # fmt: skip
        self.positions = nn.Parameter(torch.zeros(1, (env_height // 4) * (env_height // 2), dim))

    def forward(self, env):
        z = self.net(torch.log1p(env.clamp(min=0)))  # HDR → log: a sun must not swamp the sky (env is normalised)
        return z.flatten(2).transpose(1, 2) + self.positions


def exposure(coarse: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """The lighting's exposure of each sample, (N, 1, 1, 1): the mean coarse radiance over the covered texels (all
    channels). Proportional to the light, so dividing by it makes RelightNet exposure-invariant."""
    weights = torch.ones_like(coarse[:, :1]) if mask is None else mask
    total = (coarse.clamp(min=0) * weights).sum(dim=(1, 2, 3), keepdim=True)
    count = 3 * weights.sum(dim=(1, 2, 3), keepdim=True)
    return (total / count.clamp(min=1)).clamp(min=1e-12)  # a black view stays black; no division by zero


class RelightNet(nn.Module):
    def __init__(self, config: RelightNetConfig):
        super().__init__()
        config.validate()
        self.config = config
        levels = config.levels()
        ch = [config.channels(i) for i in range(len(levels))]
        p2 = config.patch**2
        self.stem = nn.Conv2d(config.in_channels * p2, ch[0], 3, padding=1)
        self.env = EnvEncoder(config.env_height, config.env_token_dim)
        self.down = nn.ModuleList()
        self.down_attn = nn.ModuleList()
        for i, res in enumerate(levels):
            self.down.append(ResBlock(ch[max(i - 1, 0)], ch[i]))
            self.down_attn.append(
                AttentionBlock(ch[i], config.heads, config.env_token_dim) if res < config.attention_below else nn.Identity()
            )
        self.up = nn.ModuleList()
        self.up_attn = nn.ModuleList()
        for i in range(len(levels) - 2, -1, -1):
            self.up.append(ResBlock(ch[i + 1] + ch[i], ch[i]))
            self.up_attn.append(
                AttentionBlock(ch[i], config.heads, config.env_token_dim) if levels[i] < config.attention_below else nn.Identity()
            )
        self.head = nn.Conv2d(ch[0], 2 * config.out_channels * p2, 3, padding=1)  # gain and offset
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(
        self, features: torch.Tensor, env: torch.Tensor, mask: torch.Tensor | None = None, drop_env: torch.Tensor | None = None
    ) -> torch.Tensor:
        """features (N, 15, R, R), env (N, 3, H, 2H) camera-space envmap, mask (N, 1, R, R) → texture (N, 3, R, R).

        ``drop_env`` (N,) bool, training only: those samples see a black envmap (environment-token dropout)."""
        n, c, r, r2 = features.shape
        if c != self.config.in_channels or r != r2 or r != self.config.resolution:
            raise ValueError(
                f"expected (N, {self.config.in_channels}, {self.config.resolution}, {self.config.resolution}), got {tuple(features.shape)}"
            )
        coarse = features[:, :3]
        scale = exposure(coarse, mask)
        coarse_n = coarse / scale
        env_n = env / scale
        if drop_env is not None:
            env_n = env_n * (~drop_env).to(env_n.dtype)[:, None, None, None]
        tokens = self.env(env_n)
        x = torch.cat([torch.log1p(coarse_n.clamp(min=0)), features[:, 3:]], dim=1)
        x = self.stem(F.pixel_unshuffle(x, self.config.patch) if self.config.patch > 1 else x)
        skips = []
        for i, (block, attn) in enumerate(zip(self.down, self.down_attn, strict=True)):
            if i > 0:
                x = F.avg_pool2d(x, 2)
            x = block(x)
            x = attn(x, tokens) if isinstance(attn, AttentionBlock) else x
            skips.append(x)
        skips.pop()  # the bottleneck is x itself
        for block, attn in zip(self.up, self.up_attn, strict=True):
            skip = skips.pop()
            x = F.interpolate(x, size=skip.shape[-2:], mode="nearest")
            x = block(torch.cat([x, skip], dim=1))
            x = attn(x, tokens) if isinstance(attn, AttentionBlock) else x
        x = self.head(x)
        x = F.pixel_shuffle(x, self.config.patch) if self.config.patch > 1 else x
        gain, offset = x.split(self.config.out_channels, dim=1)
        out = (scale * self.config.output_gain) * F.relu(coarse_n * torch.exp(gain.clamp(-MAX_LOG_GAIN, MAX_LOG_GAIN)) + offset)
        return out if mask is None else out * mask

    # ------------------------------------------------------------------------------------------------------

    def save(self, folder: str | Path) -> None:
        from gra_mi.core.weights import write_model

        write_model(folder, "relightnet", FORMAT, self.config, self.state_dict())

    @classmethod
    def load(cls, folder: str | Path, device: str = "cpu") -> RelightNet:
        from gra_mi.core.weights import read_model_config, read_weights

        folder = Path(folder)
        config = read_model_config(folder / "relightnet.json", RelightNetConfig, FORMAT, HINT)
        gain = config.output_gain
        if not (math.isfinite(gain) and gain > 0):
            raise GraMiInputError(folder / "relightnet.json", f"must be a finite number > 0, got {gain!r}", field="output_gain")
        model = cls(config)
        tensors = read_weights(folder / "relightnet.safetensors", HINT)
        try:
            model.load_state_dict(tensors)
        except RuntimeError as exc:  # weights of another config
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise GraMiInputError(folder / "relightnet.safetensors", f"cannot load the weights ({first})") from None
        return model.to(device).eval()
