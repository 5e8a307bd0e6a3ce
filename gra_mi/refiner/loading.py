"""Loading the refiner's backbone as diffusers splits it from the model: the tiny DiT with the shipped tiny VAE, a
local diffusers WAN2.1-VACE folder, or an original-format checkpoint (converted with diffusers' own converters);
never a download. Also the one-off prompt embedding cache (``gra-mi refiner-prompt``)."""

from __future__ import annotations

import json
import logging
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path
from gra_mi.refiner.config import TINY_VAE_WEIGHTS, TRANSFORMER_CONFIGS, VAE_CONFIGS, RefinerConfig

logger = logging.getLogger(__name__)


def torch_dtype(name: str) -> torch.dtype:
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


def build_backbone(config: RefinerConfig):
    """(transformer, VAE) of ``config``'s size: tiny (random DiT, shipped VAE), or real weights from disk."""
    if config.size == "tiny":
        return _tiny_backbone(config.seed)
    if not config.weights:
        raise GraMiInputError(
            "--weights",
            f"the {config.size} refiner needs WAN2.1-VACE-{config.size} weights on disk (a local diffusers folder, or an "
            "original-format checkpoint); nothing is downloaded. Use size 'tiny' to run without weights.",
        )
    path = Path(config.weights)
    if not path.exists():
        raise GraMiInputError(path, f"WAN2.1-VACE-{config.size} weights not found (expected a diffusers folder or a checkpoint file)")
    return _diffusers_folder(path, config) if path.is_dir() else _original_checkpoint(path, config)


def _tiny_backbone(seed: int):
    from diffusers import WanVACETransformer3DModel
    from safetensors import safe_open
    from safetensors.torch import load_file

    from gra_mi.refiner.tiny_vae import TinyVideoAutoencoder

    torch.manual_seed(seed)
    transformer = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"])  # random: a stand-in for pretrained weights
    if not TINY_VAE_WEIGHTS.is_file():
        raise GraMiInputError(
            TINY_VAE_WEIGHTS, "missing: the pretrained tiny VAE ships with gra-mi (make it with pipelines/pretrain_tiny_vae.py)"
        )
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


def _diffusers_folder(path: Path, config: RefinerConfig):
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel

    for sub in ("transformer", "vae"):
        if not (path / sub / "config.json").is_file():
            raise GraMiInputError(
                path / sub / "config.json", "missing: a diffusers WAN2.1-VACE folder has transformer/ and vae/ with config.json"
            )
    # from_pretrained with torch_dtype keeps diffusers' fp32-sensitive modules in fp32; the VAE stays fp32 (hand-off colour).
    dtype = torch_dtype(config.dtype)
    transformer = WanVACETransformer3DModel.from_pretrained(path / "transformer", torch_dtype=dtype, local_files_only=True)
    _check_size(transformer, config.size, path / "transformer" / "config.json")
    vae = AutoencoderKLWan.from_pretrained(path / "vae", torch_dtype=torch.float32, local_files_only=True)
    return transformer, vae


def _original_checkpoint(path: Path, config: RefinerConfig):
    """Wan-AI's original-format transformer and VAE files, converted by diffusers' single-file converters."""
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel
    from diffusers.loaders.single_file_utils import convert_wan_transformer_to_diffusers, convert_wan_vae_to_diffusers

    if not config.vae_weights or not Path(config.vae_weights).is_file():
        raise GraMiInputError(
            "--vae-weights", "an original-format transformer checkpoint needs the Wan2.1 VAE checkpoint file (Wan2.1_VAE.pth)"
        )
    state, dtype = convert_wan_transformer_to_diffusers(_read_checkpoint(path)), torch_dtype(config.dtype)
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


def cache_prompt_embedding(pipeline_folder: str | Path, prompt: str, out: str | Path) -> Path:
    """Encode ``prompt`` once with the umT5 text encoder of a local WAN2.1 diffusers folder (no download)."""
    from safetensors.torch import save_file

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
