"""The video refiner's configuration: the model sizes (WAN2.1-VACE's real ones and the tiny CPU one), the shipped
tiny weights, and :class:`RefinerConfig`, which refiner.json holds (format :data:`FORMAT`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError

# Real configurations (Wan-AI/Wan2.1-VACE-{1.3B,14B}-diffusers transformer/config.json).
TRANSFORMER_CONFIGS = {
    "tiny": dict(
        patch_size=(1, 4, 4), num_attention_heads=4, attention_head_dim=64, in_channels=16, out_channels=16, text_dim=32,
        freq_dim=32, ffn_dim=512, num_layers=4, cross_attn_norm=True, qk_norm="rms_norm_across_heads", eps=1e-6,
        rope_max_seq_len=64, vace_layers=[0, 2], vace_in_channels=48,  # 16 + 16 latents + a 4×4 mask (its VAE is 4×)
    ),
    "1.3B": dict(
        patch_size=(1, 2, 2), num_attention_heads=12, attention_head_dim=128, in_channels=16, out_channels=16, text_dim=4096,
        freq_dim=256, ffn_dim=8960, num_layers=30, cross_attn_norm=True, qk_norm="rms_norm_across_heads", eps=1e-6,
        rope_max_seq_len=1024, vace_layers=list(range(0, 30, 2)), vace_in_channels=96,
    ),
    "14B": dict(
        patch_size=(1, 2, 2), num_attention_heads=40, attention_head_dim=128, in_channels=16, out_channels=16, text_dim=4096,
        freq_dim=256, ffn_dim=13824, num_layers=40, cross_attn_norm=True, qk_norm="rms_norm_across_heads", eps=1e-6,
        rope_max_seq_len=1024, vace_layers=list(range(0, 40, 5)), vace_in_channels=96,
    ),
}  # fmt: skip
# The real VAE is diffusers' default AutoencoderKLWan (8× in space, 4× in time, 16 channels). The tiny one
# (gra_mi.refiner.tiny_vae) has its interface, time factor and channels (so windows of 4k + 1 frames carry over) but
# shrinks images 4× and starts as an exact block-mean codec: it keeps the image (docs/results/refiner.md).
VAE_CONFIGS = {
    "tiny": dict(z_dim=16, spatial=4, temporal=4, hidden=64),
    "1.3B": {},
    "14B": {},
}
TINY_VAE_WEIGHTS = Path(__file__).resolve().parent.parent / "data" / "tiny_vae.safetensors"
"""The tiny VAE pretrained as an autoencoder by pipelines/pretrain_tiny_vae.py (shipped)."""
TINY_PRIOR_WEIGHTS = Path(__file__).resolve().parent.parent / "data" / "tiny_refiner_prior.safetensors"
"""The tiny DiT (with its VACE and envmap layers) pretrained by pipelines/pretrain_tiny_refiner.py on another subject
(shipped): what the tiny refiner fine-tunes, as the real sizes fine-tune Wan2.1-VACE."""
TEMPORAL_FACTOR = 4  # the causal VAE: 4k + 1 frames → k + 1 latent frames (the spatial factor is the VAE's config)
LORA_TARGETS = r"blocks\.\d+\.(attn1|attn2)\.(to_q|to_k|to_v|to_out\.0)|blocks\.\d+\.ffn\.net\.(0\.proj|2)"
"""Main DiT blocks only (the regex is matched against the whole module name, so ``vace_blocks.*`` is excluded)."""


def parse_blocks(text: str) -> list[int] | None:
    """``--env-blocks``: 'all' (None), 'none' ([]) or a comma list of block indices."""
    import argparse

    if text == "all":
        return None
    if text == "none":
        return []
    try:
        return [int(b) for b in text.split(",") if b.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'all', 'none' or a comma list of block indices, got '{text}'") from None


@dataclass
class RefinerConfig:
    size: str = field(default="tiny", metadata=option(choices=tuple(sorted(TRANSFORMER_CONFIGS))))
    """Model size. tiny: random weights, CPU. Real sizes (1.3B, 14B) need their weights."""
    weights: str | None = None
    """Real sizes: a local diffusers folder (with transformer/ and vae/) or an original-format .safetensors/.pth checkpoint
    of the transformer (then `vae_weights` names the VAE file)."""
    vae_weights: str | None = None
    """With an original-format checkpoint: the Wan2.1 VAE checkpoint (Wan2.1_VAE.pth)."""
    prompt_embeds: str | None = None
    """Real sizes: a .safetensors file with `prompt_embeds` (1, L, 4096) computed once by `gra-mi refiner-prompt`."""
    lora_rank: int = 32
    """LoRA rank on the main DiT blocks."""
    env_blocks: list[int] | None = field(default=None, metadata=option(parse=parse_blocks))
    """Main blocks followed by atemporal envmap cross-attention: 'all', 'none' or a comma list; default: all."""
    env_heads: int = 2
    env_mlp_hidden: int = 64
    window: int = 17
    """Pixel frames per window (4k + 1)."""
    handoff: int = 5
    """Frames a window hands to the next as inactive seeds."""
    seed: int = 0
    """Random seed of the new weights."""
    prompt_length: int = 8
    residual_scale: float = 0.1
    """Size tiny: the flow runs on the residual (target latents − the coarse input's latents) / residual_scale, so a
    refiner that has learnt nothing returns its input, not noise; 0: on the latents themselves, as the real sizes
    always do (their pretrained Wan prior models natural video latents; the paper)."""
    prior: bool = True
    """The tiny size's DiT starts from the shipped prior, pretrained on another subject (pipelines/pretrain_tiny_refiner.py);
    off: from random weights."""
    dtype: str = field(default="float32", metadata=option(choices=("float32", "bfloat16")))
    """Transformer dtype (float32 or bfloat16; the VAE stays float32)."""
    mix: float = 1.0
    """The fraction of the refiner's change delivered: input + mix·(refined − input). Training chooses it on the
    data's selection sequences (:mod:`gra_mi.refiner.mix`); 1 (the refiner's output as it is) without them."""

    def validate(self, source: str | Path | None = None) -> None:
        """Check every field; ``source``: the refiner.json these came from (errors then name it and the field;
        without it they name the parameter, which the CLI shows as its flag)."""

        def bad(name: str, problem: str):
            raise GraMiInputError(source, problem, field=name) if source else GraMiParameterError(name, problem)

        if self.size not in TRANSFORMER_CONFIGS:
            bad("size", f"'{self.size}' is not one of {sorted(TRANSFORMER_CONFIGS)}")
        if self.window < 5 or (self.window - 1) % TEMPORAL_FACTOR:
            bad("window", f"must be 4k + 1 frames (e.g. 17), got {self.window}")
        if not 0 < self.handoff < self.window:
            bad("handoff", f"must be between 1 and window - 1, got {self.handoff}")
        layers = TRANSFORMER_CONFIGS[self.size]["num_layers"]
        if self.env_blocks is not None and any(not 0 <= b < layers for b in self.env_blocks):
            bad("env_blocks", f"{self.env_blocks} must be block indices in [0, {layers})")
        width = TRANSFORMER_CONFIGS[self.size]["num_attention_heads"] * TRANSFORMER_CONFIGS[self.size]["attention_head_dim"]
        if not 0 <= self.lora_rank <= width:  # a rank beyond the layers' width is no low-rank update (and costs its square)
            bad("lora_rank", f"must be in [0, {width}] (0: no LoRA; {width}: the {self.size} DiT's width), got {self.lora_rank}")
        if self.size == "tiny" and (given := [n for n in ("weights", "vae_weights", "prompt_embeds") if getattr(self, n)]):
            bad(given[0], "is for the real sizes (1.3B, 14B): the tiny refiner loads no weights")
        if not (math.isfinite(self.residual_scale) and self.residual_scale >= 0):
            bad("residual_scale", f"must be >= 0 (0: flow on the latents), got {self.residual_scale}")
        if not 0 <= self.seed < 2**32:
            bad("seed", f"must be an integer in [0, 2^32), got {self.seed}")
        if self.dtype not in ("float32", "bfloat16"):
            bad("dtype", f"must be float32 or bfloat16, got '{self.dtype}'")
        if not 0 <= self.mix <= 1:  # NaN fails too
            bad("mix", f"must be in [0, 1], got {self.mix}")
        for name in ("weights", "vae_weights", "prompt_embeds"):
            path = getattr(self, name)
            if path is not None and not Path(path).exists():
                bad(name, f"{path}: not found")


FORMAT = "gra-mi-refiner/1"
"""refiner.json's format (:func:`gra_mi.core.weights.write_model`)."""
RETIRED_KEYS = frozenset({"extra"})
"""Fields refiner.json files from before 2026-12-02 hold that the config no longer has (ignored on load)."""
HINT = " (train one with `gra-mi train-refiner`)"
