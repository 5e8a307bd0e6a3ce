"""Latent flow matching (paper Sec. 3.3, Eq. 11 and 13-15) in Wan's convention, and the Euler sampler.

Wan / diffusers: x_σ = (1 − σ)·x₀ + σ·ε with σ = 1 noise and σ = 0 data, velocity v = ε − x₀. The paper writes
z_s = (1 − s)·z₀ + s·z₁ with z₀ noise and z₁ data, so s = 1 − σ and v_paper = −v (docs/conventions.md). Training
(:mod:`gra_mi.refiner.train`) and sampling (:mod:`gra_mi.refiner.infer`) both take the schedule from here.
"""

from __future__ import annotations

import torch


def shift_sigma(u: torch.Tensor | float, shift: float):
    """Wan / SD3 time shift: σ' = shift·σ / (1 + (shift − 1)·σ). shift = 1 is the identity."""
    return shift * u / (1 + (shift - 1) * u)


def sampling_sigmas(steps: int, shift: float) -> torch.Tensor:
    """σ from 1 (noise) to 0 (data) in ``steps`` Euler steps: steps + 1 values, exactly as diffusers'
    FlowMatchEulerDiscreteScheduler: linear from 1 to its (already shifted) smallest training σ, shifted, then a final 0."""
    linear = torch.linspace(1.0, shift_sigma(1.0 / 1000, shift), steps, dtype=torch.float64)
    return torch.cat([shift_sigma(linear, shift), torch.zeros(1, dtype=torch.float64)])


def noisy_latent(clean: torch.Tensor, noise: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """x_σ = (1 − σ)·x₀ + σ·ε (the paper's z_s = (1 − s) z₀ + s z₁ with s = 1 − σ, z₀ noise, z₁ data)."""
    return (1 - sigma) * clean + sigma * noise


def velocity_target(clean: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """Wan's target v = ε − x₀ (= −(z₁ − z₀), the paper's Eq. 11 target with the sign flipped)."""
    return noise - clean


def recycling_residuals(predicted: torch.Tensor, target: torch.Tensor, sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Error recycling residuals (paper Eq. 13-14) from a Wan-convention prediction: (e_noise, e_data).

    With the paper's ẑ₀ = z̃_s − s·v̂, ẑ₁ = z̃_s + (1 − s)·v̂ and v = −v_wan: e₀ = (1 − σ)(v̂_wan − v_wan),
    e₁ = −σ(v̂_wan − v_wan).
    """
    diff = predicted - target
    return (1 - sigma) * diff, -sigma * diff


@torch.no_grad()
def euler_sample(
    model,
    shape,
    control,
    env,
    steps: int,
    shift: float,
    generator: torch.Generator,
    known: torch.Tensor | None = None,
    start: torch.Tensor | None = None,
    denoise: float = 1.0,
) -> torch.Tensor:
    """Integrate dx/dσ = v(x, σ) from σ = 1 (noise) to 0 with Euler steps (as FlowMatchEulerDiscreteScheduler).

    known (1, 16, K, h, w): latents of the first K latent frames, which are given (the reference and the handed-off
    seed frames). They follow their exact flow path x_σ = (1 − σ)·z + σ·ε at every step instead of the model's
    estimate — the inputs the refiner saw for them in training — so the frames it generates continue what was given.

    denoise < 1 (with ``start``, the latents of the coarse input): the last ``denoise`` of the schedule only, from
    ``start`` noised to that level (SDEdit; diffusers' img2img ``strength``): the result keeps the input's layout.
    """
    sigmas = sampling_sigmas(steps, shift).to(torch.float32)
    noise = torch.randn(shape, generator=generator).to(model.device)
    first = 0
    if denoise < 1:
        first = min(int(round(steps * (1 - denoise))), steps - 1)
        x = (1 - sigmas[first]) * start + sigmas[first] * noise
    else:
        x = noise
    k = 0 if known is None else known.shape[2]
    for i in range(first, steps):
        if k:
            x[:, :, :k] = (1 - sigmas[i]) * known + sigmas[i] * noise[:, :, :k]
        v = model(x, sigmas[i : i + 1].to(model.device), control, env)
        x = x + (sigmas[i + 1] - sigmas[i]) * v
    if k:
        x[:, :, :k] = known
    return x
