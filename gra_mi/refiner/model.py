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

import logging
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from gra_mi.core.errors import GraMiInputError
from gra_mi.refiner.conditioning import ControlChannels
from gra_mi.refiner.config import FORMAT, HINT, LORA_TARGETS, RETIRED_KEYS, TEMPORAL_FACTOR, TINY_PRIOR_WEIGHTS, RefinerConfig
from gra_mi.refiner.loading import build_backbone, torch_dtype

logger = logging.getLogger(__name__)

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


class VideoRefiner(nn.Module):
    """WAN2.1-VACE + LoRA + atemporal envmap attention, with the VAE and the cached prompt embedding."""

    def __init__(self, config: RefinerConfig, backbone=None, lora: bool = True):
        super().__init__()
        config.validate()
        self.config = config
        self.transformer, self.vae = backbone if backbone is not None else build_backbone(config)
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
        self.channels = ControlChannels(z_dim)  # the VACE context's layout
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
        channels = self.channels
        reactive = channels.mask(control).mean(dim=1, keepdim=True)
        base = reactive * channels.reactive(control) + (1 - reactive) * channels.inactive(control)
        if given:
            base = torch.cat([channels.inactive(control)[:, :, :given], base[:, :, given:]], dim=2)
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

    def conditioning(
        self, coarse: torch.Tensor, mask: torch.Tensor, reference: torch.Tensor, env: torch.Tensor, reference_env: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(control, env latents before the MLP) for one window; batch of 1. Videos (3, T, H, W) in [-1, 1]."""
        return self.control(coarse[None], mask, reference[None]), self.env_latents(env[None], reference_env[None])

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
        dtype = torch_dtype(self.config.dtype)
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
