"""RelightNet (paper Sec. 3.2, Supp. "Details about RelightNet"): a UV-space UNet that turns the coarse physics
texture into a pose- and illumination-aware texture.

- Input: the 15 channels of :mod:`gra_mi.bridge` (coarse texture 3 + normals of the last 3 frames 9 + view
  direction 3); output: 3 channels (linear RGB radiance).
- Resolutions ≥ 64²: convolution-only residual blocks. Below 64²: convolution + self-attention + cross-attention
  to environment-map tokens (4 heads).
- Environment tokens: a small CNN encodes the camera-space envmap E^κ (log radiance) into a grid of tokens.
- The output is added to the coarse texture and the last convolution starts at zero, so an untrained RelightNet
  reproduces the microfacet render exactly (training starts from the physics, not from noise).

Weights are saved as safetensors with the config as JSON beside them (``relightnet.safetensors``,
``relightnet.json``).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from gra_mi.core.errors import GraMiInputError
from gra_mi.render.bridge import IN_CHANNELS


@dataclass
class RelightNetConfig:
    resolution: int = 512
    """UV resolution the network runs at (a power of two, ≥ 32)."""
    base_channels: int = 16
    """Channels at full resolution; doubled per level down to ``max_channels``."""
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

    def levels(self) -> list[int]:
        res, out = self.resolution, []
        while res >= self.lowest_resolution:
            out.append(res)
            res //= 2
        return out

    def channels(self, level: int) -> int:
        return min(self.base_channels * 2**level, self.max_channels)

    def validate(self) -> None:
        if self.resolution < 32 or self.resolution & (self.resolution - 1):
            raise GraMiInputError("relightnet.resolution", f"must be a power of two ≥ 32, got {self.resolution}")
        if any(self.channels(i) % self.heads for i, r in enumerate(self.levels()) if r < self.attention_below):
            raise GraMiInputError("relightnet.heads", "attention channels must divide by the number of heads")


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
        z = self.net(torch.log1p(env.clamp(min=0)))  # HDR → log: a sun must not swamp the sky
        return z.flatten(2).transpose(1, 2) + self.positions


class RelightNet(nn.Module):
    def __init__(self, config: RelightNetConfig):
        super().__init__()
        config.validate()
        self.config = config
        levels = config.levels()
        ch = [config.channels(i) for i in range(len(levels))]
        self.stem = nn.Conv2d(config.in_channels, ch[0], 3, padding=1)
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
        self.head = nn.Conv2d(ch[0], config.out_channels, 3, padding=1)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, features: torch.Tensor, env: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        """features (N, 15, R, R), env (N, 3, H, 2H) camera-space envmap, mask (N, 1, R, R) → texture (N, 3, R, R)."""
        n, c, r, r2 = features.shape
        if c != self.config.in_channels or r != r2 or r != self.config.resolution:
            raise ValueError(
                f"expected (N, {self.config.in_channels}, {self.config.resolution}, {self.config.resolution}), got {tuple(features.shape)}"
            )
        tokens = self.env(env)
        x = self.stem(features)
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
        out = features[:, :3] + self.head(x)
        return out if mask is None else out * mask

    # ------------------------------------------------------------------------------------------------------

    def save(self, folder: str | Path) -> None:
        from safetensors.torch import save_file

        from gra_mi.core.io import atomic_path, atomic_write_text

        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(folder / "relightnet.safetensors") as tmp:
            save_file({k: v.detach().cpu().contiguous() for k, v in self.state_dict().items()}, str(tmp))
        atomic_write_text(folder / "relightnet.json", json.dumps(asdict(self.config), indent=1) + "\n")

    @classmethod
    def load(cls, folder: str | Path, device: str = "cpu") -> RelightNet:
        from safetensors.torch import load_file

        folder = Path(folder)
        for name in ("relightnet.json", "relightnet.safetensors"):
            if not (folder / name).is_file():
                raise GraMiInputError(folder / name, "file not found (train one with `gra-mi train-relightnet`)")
        from gra_mi.core.io import read_json

        config = RelightNetConfig(**read_json(folder / "relightnet.json"))
        model = cls(config)
        model.load_state_dict(load_file(str(folder / "relightnet.safetensors")))
        return model.to(device).eval()
