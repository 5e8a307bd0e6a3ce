"""The video refiner's model (paper Sec. 3.3): diffusers' WAN2.1-VACE with LoRA and atemporal envmap attention.

- Backbone: diffusers' ``WanVACETransformer3DModel`` and ``AutoencoderKLWan``, untouched (no fork). Sizes: the real
  ``1.3B`` / ``14B`` configurations, whose weights are read from a local diffusers folder or an original-format
  checkpoint — never downloaded; and ``tiny`` (tests, CI, the CPU demo): a 4-block DiT whose shipped prior was
  pretrained on another subject (pipelines/pretrain_tiny_refiner.py), with a tiny VAE of the same interface that
  keeps the image (gra_mi.refiner.tiny_vae, pipelines/pretrain_tiny_vae.py).
- Trainable parts (paper Supp. "WAN2.1-VACE Finetuning"): LoRA (peft) on the main DiT blocks only, the VACE adapter
  (``vace_blocks`` + ``vace_patch_embedding``) in full, and new **atemporal cross-attention** layers: each latent
  frame's tokens attend only to the tokens of its own envmap latent (camera-space envmaps through the same VAE,
  then a shallow shared MLP). Their output projections start at zero, so at init the model *is* the stock model.
  The attention is added after chosen main blocks with forward hooks, so diffusers' forward runs as written.
- Conventions (docs/conventions.md): Wan's flow — σ = 1 is noise, ``x_σ = (1 − σ) x₀ + σ ε``, the network predicts
  ``v = ε − x₀`` — which is the paper's ``v = z₁ − z₀`` with the sign flipped (paper s = 1 − σ). Pixel videos are
  ``(B, 3, T, H, W)`` in [-1, 1]; latents are normalised with the VAE's latent mean and std as diffusers does.
- The text prompt is a fixed, cached embedding (a buffer): no text encoder runs at train or refine time.
"""

from __future__ import annotations

import json
import logging
import math
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError

logger = logging.getLogger(__name__)

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
        if self.lora_rank < 0:
            bad("lora_rank", f"must be >= 0 (0: no LoRA), got {self.lora_rank}")
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


# --------------------------------------------------------------------------------------------------------------
# Atemporal envmap cross-attention
# --------------------------------------------------------------------------------------------------------------


class AtemporalCrossAttention(nn.Module):
    """Each latent frame's video tokens attend to the tokens of that frame's envmap latent only (paper Sec. 3.3)."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        if dim % heads:
            raise ValueError(f"env attention: dim {dim} is not divisible by {heads} heads")
        self.heads = heads
        self.norm = nn.LayerNorm(dim, elementwise_affine=True, eps=1e-6)
        self.to_q, self.to_k, self.to_v = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)
        self.to_out = nn.Linear(dim, dim)
        nn.init.zeros_(self.to_out.weight)  # the stock model at init
        nn.init.zeros_(self.to_out.bias)

    def forward(self, tokens: torch.Tensor, env: torch.Tensor) -> torch.Tensor:
        """tokens (B, F·N, D) frame-major; env (B, F, M, D) → the residual to add, (B, F·N, D)."""
        b, fn, d = tokens.shape
        frames = env.shape[1]
        if fn % frames:
            raise ValueError(f"env attention: {fn} tokens do not split into {frames} latent frames")
        h = self.heads
        # Computed in this layer's own dtype (float32 while it trains), whatever the DiT's (bfloat16 for real sizes).
        dtype = self.to_q.weight.dtype
        x = self.norm(tokens.to(dtype)).view(b * frames, fn // frames, d)
        e = env.reshape(b * frames, env.shape[2], d).to(dtype)
        q = self.to_q(x).unflatten(-1, (h, d // h)).transpose(1, 2)
        k = self.to_k(e).unflatten(-1, (h, d // h)).transpose(1, 2)
        v = self.to_v(e).unflatten(-1, (h, d // h)).transpose(1, 2)
        out = F.scaled_dot_product_attention(q, k, v).transpose(1, 2).flatten(2)
        return self.to_out(out).view(b, fn, d).to(tokens.dtype)


# --------------------------------------------------------------------------------------------------------------
# The refiner
# --------------------------------------------------------------------------------------------------------------


def _dtype(name: str) -> torch.dtype:
    return {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}[name]


@contextmanager
def default_dtype(dtype: torch.dtype):
    """Build modules in ``dtype`` (the real sizes in bfloat16: the 14B takes 28 GB of memory to build, not 56)."""
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(torch.float32)


def cast_transformer(transformer, dtype: torch.dtype):
    """Cast to ``dtype`` as ``from_pretrained(torch_dtype=…)`` does: diffusers' fp32-sensitive parameters (norms, time
    embedding, RoPE, ``scale_shift_table``) stay float32, so every way of loading gives the same numerics."""
    keep = transformer._keep_in_fp32_modules or []
    for name, param in transformer.named_parameters():
        param.data = param.data.to(torch.float32 if any(k in name.split(".") for k in keep) else dtype)
    return transformer


def _build_backbone(config: RefinerConfig):
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel

    from gra_mi.refiner.tiny_vae import TinyVideoAutoencoder

    if config.size == "tiny":
        torch.manual_seed(config.seed)
        transformer = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"])  # random: a stand-in for pretrained weights
        if not TINY_VAE_WEIGHTS.is_file():
            raise GraMiInputError(
                TINY_VAE_WEIGHTS, "missing: the pretrained tiny VAE ships with gra-mi (make it with pipelines/pretrain_tiny_vae.py)"
            )
        from safetensors import safe_open
        from safetensors.torch import load_file

        try:  # a random VAE would decode noise: this one reconstructs
            with safe_open(str(TINY_VAE_WEIGHTS), framework="pt") as f:
                meta = f.metadata() or {}
            # its own latent statistics (the pretraining measures them), so normalised latents have unit variance
            stats = {k: json.loads(meta[k]) for k in ("latents_mean", "latents_std") if k in meta}
            vae = TinyVideoAutoencoder(**VAE_CONFIGS["tiny"], **stats)
            vae.load_state_dict(load_file(str(TINY_VAE_WEIGHTS)))
        except Exception as exc:  # truncated (SafetensorError) or of another config (RuntimeError)
            raise GraMiInputError(
                TINY_VAE_WEIGHTS,
                f"corrupt or of another VAE config ({str(exc).strip().splitlines()[0][:120]}); reinstall gra-mi, or rebuild it with "
                "pipelines/pretrain_tiny_vae.py",
            ) from None
        return transformer, vae
    if not config.weights:
        raise GraMiInputError(
            "--weights",
            f"the {config.size} refiner needs WAN2.1-VACE-{config.size} weights on disk (a local diffusers folder, or an "
            "original-format checkpoint); nothing is downloaded. Use size 'tiny' to run without weights.",
        )
    path = Path(config.weights)
    if not path.exists():
        raise GraMiInputError(path, f"WAN2.1-VACE-{config.size} weights not found (expected a diffusers folder or a checkpoint file)")
    dtype = _dtype(config.dtype)
    if path.is_dir():
        for sub in ("transformer", "vae"):
            if not (path / sub / "config.json").is_file():
                raise GraMiInputError(
                    path / sub / "config.json", "missing: a diffusers WAN2.1-VACE folder has transformer/ and vae/ with config.json"
                )
        # from_pretrained with torch_dtype keeps diffusers' fp32-sensitive modules in fp32; the VAE stays fp32 (hand-off colour).
        transformer = WanVACETransformer3DModel.from_pretrained(path / "transformer", torch_dtype=dtype, local_files_only=True)
        _check_size(transformer, config.size, path / "transformer" / "config.json")
        vae = AutoencoderKLWan.from_pretrained(path / "vae", torch_dtype=torch.float32, local_files_only=True)
        return transformer, vae
    from diffusers.loaders.single_file_utils import convert_wan_transformer_to_diffusers, convert_wan_vae_to_diffusers

    if not config.vae_weights or not Path(config.vae_weights).is_file():
        raise GraMiInputError(
            "--vae-weights", "an original-format transformer checkpoint needs the Wan2.1 VAE checkpoint file (Wan2.1_VAE.pth)"
        )
    state = convert_wan_transformer_to_diffusers(_read_checkpoint(path))
    with default_dtype(dtype):
        transformer = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS[config.size])
    try:
        missing, unexpected = transformer.load_state_dict(state, strict=False)
    except RuntimeError as error:  # shapes of another size
        raise GraMiInputError(
            path, f"not a WAN2.1-VACE-{config.size} transformer checkpoint: {str(error).splitlines()[-1].strip()}"
        ) from None
    if missing:
        raise GraMiInputError(
            path, f"not a WAN2.1-VACE-{config.size} transformer checkpoint: {len(missing)} weights missing, e.g. {missing[:3]}"
        )
    if unexpected:
        logger.warning("%s: %d unexpected weights ignored", path, len(unexpected))
    cast_transformer(transformer, dtype)
    for name, param in transformer.named_parameters():  # the float32-kept modules: their checkpoint values, unrounded
        if param.dtype == torch.float32 and name in state:
            param.data = state[name].to(torch.float32)
    vae = AutoencoderKLWan()
    try:
        vae.load_state_dict(convert_wan_vae_to_diffusers(_read_checkpoint(Path(config.vae_weights))))
    except RuntimeError as error:
        raise GraMiInputError(config.vae_weights, f"not the Wan2.1 VAE checkpoint: {str(error).splitlines()[0].strip()}") from None
    return transformer, vae


def _check_size(transformer, size: str, source: Path) -> None:
    """Weights of another size would load and run (shapes follow the folder's config): say so instead."""
    expected = TRANSFORMER_CONFIGS[size]
    for key in ("num_layers", "num_attention_heads", "attention_head_dim", "vace_layers"):
        got = transformer.config[key]
        if list(np.atleast_1d(got)) != list(np.atleast_1d(expected[key])):
            raise GraMiInputError(source, f"field '{key}' is {got}: not WAN2.1-VACE-{size} (expected {expected[key]}); check --size")


def _read_checkpoint(path: Path) -> dict:
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    return torch.load(path, map_location="cpu", weights_only=True)


class VideoRefiner(nn.Module):
    """WAN2.1-VACE + LoRA + atemporal envmap attention, with the VAE and the cached prompt embedding."""

    def __init__(self, config: RefinerConfig, backbone=None, lora: bool = True):
        super().__init__()
        config.validate()
        self.config = config
        self.transformer, self.vae = backbone if backbone is not None else _build_backbone(config)
        self.vae.requires_grad_(False).eval()
        self.transformer.requires_grad_(False)
        tcfg = self.transformer.config
        dim = tcfg.num_attention_heads * tcfg.attention_head_dim
        self.dim = dim
        torch.manual_seed(config.seed + 1)
        z_dim = self.vae.config.z_dim
        self.env_mlp = nn.Sequential(nn.Linear(z_dim, config.env_mlp_hidden), nn.GELU(), nn.Linear(config.env_mlp_hidden, dim))
        blocks = range(tcfg.num_layers) if config.env_blocks is None else config.env_blocks
        self.env_attention = nn.ModuleDict({str(i): AtemporalCrossAttention(dim, config.env_heads) for i in blocks})
        self._env_tokens: torch.Tensor | None = None
        self._zero_latents: dict[tuple, torch.Tensor] = {}  # the encoding of an all-zero video, by shape
        self._inference_only = False  # set by prepare_for_inference
        for i in blocks:
            self.transformer.blocks[i].register_forward_hook(self._env_hook(str(i)))
        self.register_buffer("prompt_embeds", self._prompt_embeds(), persistent=True)
        if config.size == "tiny" and config.prior and backbone is None:
            self._load_prior()
        if lora and config.lora_rank > 0:
            from peft import LoraConfig

            self.transformer.add_adapter(
                LoraConfig(r=config.lora_rank, lora_alpha=config.lora_rank, target_modules=LORA_TARGETS, init_lora_weights=True)
            )
        for name, p in self.transformer.named_parameters():
            p.requires_grad_("lora_" in name or name.startswith(("vace_blocks.", "vace_patch_embedding.")))
        latents_mean = torch.tensor(self.vae.config.latents_mean, dtype=torch.float32).view(1, z_dim, 1, 1, 1)
        latents_std = torch.tensor(self.vae.config.latents_std, dtype=torch.float32).view(1, z_dim, 1, 1, 1)
        self.register_buffer("latents_mean", latents_mean, persistent=False)
        self.register_buffer("latents_std", latents_std, persistent=False)

    def _load_prior(self) -> None:
        """The shipped tiny prior: every DiT weight, the envmap layers it has, and the prompt embedding it learnt with."""
        from safetensors.torch import load_file

        rebuild = "reinstall gra-mi, or rebuild it with pipelines/pretrain_tiny_refiner.py"
        if not TINY_PRIOR_WEIGHTS.is_file():
            raise GraMiInputError(TINY_PRIOR_WEIGHTS, f"missing: the pretrained tiny refiner ships with gra-mi ({rebuild})")
        mine = self.state_dict()
        try:
            state = load_file(str(TINY_PRIOR_WEIGHTS))
            wanted = {k: v for k, v in state.items() if k in mine and not k.startswith("vae.")}
            missing = [k for k in mine if k.startswith("transformer.") and k not in wanted]
            if missing:
                raise RuntimeError(f"{len(missing)} DiT weights missing, e.g. {missing[:2]}")
            self.load_state_dict(wanted, strict=False)
        except Exception as exc:  # truncated (SafetensorError), another config (RuntimeError: shapes, missing weights)
            raise GraMiInputError(
                TINY_PRIOR_WEIGHTS, f"corrupt or of another refiner config ({str(exc).strip().splitlines()[0][:120]}); {rebuild}"
            ) from None

    def _prompt_embeds(self) -> torch.Tensor:
        text_dim = self.transformer.config.text_dim
        if self.config.size == "tiny":  # a fixed embedding stands in for the umT5 encoding of the prompt
            g = torch.Generator().manual_seed(self.config.seed + 2)
            return torch.randn(1, self.config.prompt_length, text_dim, generator=g)
        if not self.config.prompt_embeds or not Path(self.config.prompt_embeds).is_file():
            raise GraMiInputError(
                "--prompt-embeds",
                "real sizes need the cached umT5 prompt embedding (.safetensors with 'prompt_embeds'); make it once with "
                "`gra-mi refiner-prompt --pipeline LOCAL_WAN_FOLDER --out prompt.safetensors`",
            )
        from safetensors.torch import load_file

        embeds = load_file(self.config.prompt_embeds).get("prompt_embeds")
        if embeds is None or embeds.ndim != 3 or embeds.shape[-1] != text_dim:
            raise GraMiInputError(self.config.prompt_embeds, f"expected a 'prompt_embeds' tensor of shape (1, L, {text_dim})")
        return embeds.float()

    def _env_hook(self, key: str):
        def hook(module, args, output):
            if self._env_tokens is None:
                return output
            return output + self.env_attention[key](output, self._env_tokens)

        return hook

    def trainable_parameters(self) -> list[nn.Parameter]:
        return [p for p in self.parameters() if p.requires_grad]

    def trainable_state(self) -> dict[str, torch.Tensor]:
        names = {n for n, p in self.named_parameters() if p.requires_grad}
        return {n: t.detach().cpu().contiguous() for n, t in self.state_dict().items() if n in names}

    # -- VAE ----------------------------------------------------------------------------------------------------

    @property
    def device(self) -> torch.device:
        return self.latents_mean.device

    def encode(self, video: torch.Tensor) -> torch.Tensor:
        """(B, 3, T, H, W) in [-1, 1] → normalised latents (B, 16, 1 + (T − 1)/4, H/8, W/8) (argmax, as diffusers)."""
        with torch.no_grad():
            mu = self.vae.encode(video.to(self.device, torch.float32)).latent_dist.mode()
        return (mu.float() - self.latents_mean) / self.latents_std

    def decode(self, latents: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            video = self.vae.decode(latents.float() * self.latents_std + self.latents_mean).sample
        return video.clamp(-1, 1)

    def control(self, video: torch.Tensor, mask: torch.Tensor, reference: torch.Tensor | None) -> torch.Tensor:
        """VACE context (B, 32 + s², F', h, w) exactly as ``WanVACEPipeline``: [inactive latents, reactive latents, s×s
        mask], s the VAE's spatial factor (8 for Wan2.1's: 96 channels).

        video (B, 3, T, H, W) in [-1, 1]; mask (B, 1, T, H, W), 1 = reactive (refine), 0 = inactive (keep);
        reference (B, 3, H, W) or None: one extra leading frame (its latent, zeros, a zero mask).
        """
        mask = (mask > 0.5).to(video.dtype)
        inactive = video * (1 - mask)
        # No seed frames (most windows): the inactive video is all zeros, whose encoding depends on its shape only.
        key = tuple(inactive.shape)
        if not bool(inactive.any()):
            if key not in self._zero_latents:
                self._zero_latents = {key: self.encode(inactive)}
            inactive_latents = self._zero_latents[key].to(video.device)
        else:
            inactive_latents = self.encode(inactive)
        latents = torch.cat([inactive_latents, self.encode(video * mask)], dim=1)
        masks = self.latent_mask(mask)
        if reference is not None:
            ref = self.encode(reference[:, :, None])
            latents = torch.cat([torch.cat([ref, torch.zeros_like(ref)], dim=1), latents], dim=2)
            masks = torch.cat([torch.zeros_like(masks[:, :, :1]), masks], dim=2)
        return torch.cat([latents, masks], dim=1)

    def latent_mask(self, mask: torch.Tensor) -> torch.Tensor:
        """(B, 1, T, H, W) → (B, s², F', H/s, W/s): space-to-depth s×s, nearest-exact in time (diffusers' prepare_masks)."""
        b, _, t, h, w = mask.shape
        s, p = self.vae.config.scale_factor_spatial, self.transformer.config.patch_size[1]
        nh, nw = h // (s * p) * p, w // (s * p) * p
        m = mask[:, 0].reshape(b, t, nh, s, nw, s).permute(0, 3, 5, 1, 2, 4).flatten(1, 2)
        frames = (t + TEMPORAL_FACTOR - 1) // TEMPORAL_FACTOR
        return F.interpolate(m, size=(frames, nh, nw), mode="nearest-exact")

    # -- what the flow runs on ----------------------------------------------------------------------------------

    @property
    def residual_scale(self) -> float:
        return self.config.residual_scale if self.config.size == "tiny" else 0.0

    def base_latents(self, control: torch.Tensor, given: int = 0) -> torch.Tensor:
        """The latents the flow starts from in residual mode: per latent frame the given (inactive) latents where the
        mask keeps them — the reference, seed frames — and the coarse input's (reactive) latents elsewhere.

        ``given``: the leading latent frames that are given (the reference and the seed frames' latents) take the
        inactive latents whatever the mask says: diffusers' nearest-exact latent mask marks the latent frame of seed
        frames 1–4 reactive, whose reactive latents are then those of a blank video."""
        keep = control[:, 32:].mean(dim=1, keepdim=True)  # the latent mask, 1 = reactive
        base = keep * control[:, 16:32] + (1 - keep) * control[:, :16]
        if given:
            base = torch.cat([control[:, :16, :given], base[:, :, given:]], dim=2)
        return base

    def to_flow(self, latents: torch.Tensor, control: torch.Tensor, given: int = 0) -> torch.Tensor:
        """Latents → the space the flow runs in (the latents, or the residual over the coarse input, scaled)."""
        if not self.residual_scale:
            return latents
        return (latents - self.base_latents(control, given)) / self.residual_scale

    def from_flow(self, x: torch.Tensor, control: torch.Tensor, given: int = 0) -> torch.Tensor:
        if not self.residual_scale:
            return x
        return self.base_latents(control, given) + self.residual_scale * x

    def decode_output(self, latents: torch.Tensor, control: torch.Tensor, coarse: torch.Tensor, given: int = 0) -> torch.Tensor:
        """Sampled latents (reference frame first) → the refined window (3, T, H, W) in [-1, 1]. Residual flow: the
        decoded change from the base (what the input's own latents decode to), added to the input ``coarse`` itself,
        so that what the VAE loses on the input is not charged to the output and a zero residual returns the input."""
        video = self.decode(latents[:, :, 1:])[0]  # drop the reference frame
        if not self.residual_scale:
            return video
        return (coarse + video - self.decode(self.base_latents(control, given)[:, :, 1:])[0]).clamp(-1, 1)

    def env_latents(self, envmaps: torch.Tensor, reference_env: torch.Tensor | None) -> torch.Tensor:
        """Camera-space envmaps (B, 3, T, h, w) in [-1, 1] (+ the reference's (B, 3, h, w), a leading frame) → VAE latents."""
        latents = self.encode(envmaps)
        if reference_env is not None:
            latents = torch.cat([self.encode(reference_env[:, :, None]), latents], dim=2)
        return latents

    def env_tokens(self, env_latents: torch.Tensor) -> torch.Tensor:
        """(B, 16, F', h, w) envmap latents → (B, F', h·w, D): one token per latent pixel, through the shared MLP.

        Kept apart from :meth:`env_latents` because the MLP trains while the (frozen) VAE encoding can be cached.
        """
        return self.env_mlp(env_latents.permute(0, 2, 3, 4, 1).flatten(2, 3).to(self.env_mlp[0].weight.dtype))

    # -- the network ------------------------------------------------------------------------------------------

    def prepare_for_inference(self, fuse_lora: bool = True) -> VideoRefiner:
        """Fold the LoRA into the DiT's weights and run the envmap layers in the DiT's dtype: 1.40× faster per step for
        the bfloat16 1.3B on an H100, and no further from the same weights run in float32 than bfloat16 itself is (1.52 %
        relative L2 of the velocity either way; benchmarks/refiner.py). For sampling only: the model cannot be trained or
        saved afterwards."""
        self.eval()
        if fuse_lora and self.config.lora_rank > 0:
            self.transformer.fuse_lora()
        dtype = _dtype(self.config.dtype)
        self.env_attention.to(dtype)
        self.env_mlp.to(dtype)
        self._inference_only = True
        return self

    def forward(self, latents: torch.Tensor, sigma: torch.Tensor, control: torch.Tensor, env: torch.Tensor | None) -> torch.Tensor:
        """Wan-convention velocity v = ε − x₀ for noisy latents (B, 16, F', h, w) at noise level σ (B,)."""
        if env is not None and env.shape[1] != latents.shape[2]:
            raise ValueError(f"{env.shape[1]} envmap latent frames for {latents.shape[2]} video latent frames")
        dtype = self.transformer.dtype
        self._env_tokens = env
        try:
            out = self.transformer(
                hidden_states=latents.to(dtype),
                timestep=(sigma * 1000).to(latents.device),
                encoder_hidden_states=self.prompt_embeds.expand(latents.shape[0], -1, -1).to(dtype),
                control_hidden_states=control.to(dtype),
                return_dict=False,
            )[0]
        finally:
            self._env_tokens = None
        return out.float()

    # -- files ------------------------------------------------------------------------------------------------

    def save(self, folder: str | Path) -> None:
        """``refiner.json`` + ``refiner.safetensors`` (trainable weights; a tiny model also stores its base weights)."""
        from gra_mi.core.weights import write_model

        if self._inference_only:
            raise RuntimeError("this refiner was prepared for inference (LoRA folded into the DiT): save it before that")
        state = self.state_dict() if self.config.size == "tiny" else self.trainable_state()
        write_model(folder, "refiner", FORMAT, self.config, state)

    @classmethod
    def load(cls, folder: str | Path, **overrides) -> VideoRefiner:
        from gra_mi.core.weights import read_model_config, read_weights

        folder = Path(folder)
        config = read_model_config(folder / "refiner.json", RefinerConfig, FORMAT, HINT, retired=RETIRED_KEYS, **overrides)
        config.validate(folder / "refiner.json")
        model = cls(config)
        weights = folder / "refiner.safetensors"
        tensors = read_weights(weights, HINT)
        try:
            missing, unexpected = model.load_state_dict(tensors, strict=False)
        except RuntimeError as exc:  # tensors of another size
            first = str(exc).strip().splitlines()[0][:200]
            raise GraMiInputError(weights, f"cannot load these weights into the refiner of refiner.json ({first})") from None
        trainable = {n for n, p in model.named_parameters() if p.requires_grad}
        if unexpected or (trainable & set(missing)):
            raise GraMiInputError(
                weights, f"does not match the refiner config: missing {sorted(trainable & set(missing))[:3]}, unexpected {unexpected[:3]}"
            )
        return model


FORMAT = "gra-mi-refiner/1"
"""refiner.json's format (:func:`gra_mi.core.weights.write_model`)."""
RETIRED_KEYS = frozenset({"extra"})
"""Fields refiner.json files from before 2026-12-02 hold that the config no longer has (ignored on load)."""
HINT = " (train one with `gra-mi train-refiner`)"


def seed_mask(frames: int, height: int, width: int, seeded: int) -> torch.Tensor:
    """(1, 1, T, H, W): 1 = reactive (refine), 0 = inactive (the first ``seeded`` frames are kept)."""
    mask = torch.ones(1, 1, frames, height, width)
    mask[:, :, :seeded] = 0
    return mask


def conditioning(
    model: VideoRefiner, coarse: torch.Tensor, mask: torch.Tensor, reference: torch.Tensor, env: torch.Tensor, reference_env: torch.Tensor
):
    """(control, env latents before the MLP) for one window; batch of 1. Videos (3, T, H, W) in [-1, 1]."""
    control = model.control(coarse[None], mask, reference[None])
    return control, model.env_latents(env[None], reference_env[None])


def parameter_counts(model: VideoRefiner) -> dict[str, int]:
    count = lambda ps: int(sum(p.numel() for p in ps))  # noqa: E731
    named = list(model.named_parameters())
    return {
        "total": count(p for _, p in named),
        "trainable": count(p for _, p in named if p.requires_grad),
        "lora": count(p for n, p in named if "lora_" in n),
        "vace": count(p for n, p in named if ".vace_" in f".{n}"),
        "env_attention": count(p for n, p in named if n.startswith(("env_attention.", "env_mlp."))),
    }


def latent_frames(pixel_frames: int) -> int:
    return (pixel_frames - 1) // TEMPORAL_FACTOR + 1


def pad_to_multiple(h: int, w: int, m: int = 16) -> tuple[int, int]:
    return int(math.ceil(h / m) * m), int(math.ceil(w / m) * m)


def cache_prompt_embedding(pipeline_folder: str | Path, prompt: str, out: str | Path) -> Path:
    """Encode ``prompt`` once with the umT5 text encoder of a local WAN2.1 diffusers folder (no download)."""
    from safetensors.torch import save_file

    from gra_mi.core.io import atomic_path

    folder = Path(pipeline_folder)
    for sub in ("tokenizer", "text_encoder"):
        if not (folder / sub).is_dir():
            raise GraMiInputError(folder / sub, "missing: a diffusers WAN2.1 folder has tokenizer/ and text_encoder/")
    from transformers import AutoTokenizer, UMT5EncoderModel

    tokenizer = AutoTokenizer.from_pretrained(folder / "tokenizer", local_files_only=True)
    encoder = UMT5EncoderModel.from_pretrained(folder / "text_encoder", local_files_only=True).eval()
    tokens = tokenizer([prompt], padding="max_length", max_length=512, truncation=True, return_tensors="pt")
    with torch.no_grad():
        hidden = encoder(tokens.input_ids, tokens.attention_mask).last_hidden_state
    length = int(tokens.attention_mask.sum())
    embeds = torch.zeros_like(hidden)
    embeds[:, :length] = hidden[:, :length]  # as WanPipeline: the prompt's tokens, zeros after
    with atomic_path(out) as tmp:
        save_file({"prompt_embeds": embeds.contiguous()}, str(tmp))
    return Path(out)
