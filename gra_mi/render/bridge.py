"""The one place where tensors cross between Dr.Jit and torch.

Layout on the torch side: NCHW float32. UV-space features of one view are ``(1, 15, R, R)``:

    channels 0-2    coarse relit texture (linear RGB radiance toward the camera, one-bounce, fitted maps)
    channels 3-11   shading normals of frames t, t-1, t-2 (world, xyz each; earlier frames clamp to frame 0)
    channels 12-14  view direction (world, texel → camera)

with a ``(1, 1, R, R)`` mask of the texels the atlas covers; zeros elsewhere. Images are ``(1, 3, H, W)``.

Dr.Jit → torch uses ``TensorXf.torch()`` (zero-copy, DLPack). For differentiable rendering, :func:`torch_render`
wraps a Mitsuba render with ``dr.wrap`` so that gradients of a torch loss reach Dr.Jit scene parameters (the
albedo and roughness textures).
"""

from __future__ import annotations

import numpy as np

NUM_NORMAL_FRAMES = 3
IN_CHANNELS = 3 + 3 * NUM_NORMAL_FRAMES + 3  # = 15, the paper's RelightNet input


def to_torch(array, device: str = "cpu"):
    """A Dr.Jit tensor or a NumPy array as a torch tensor (Dr.Jit tensors without a copy where possible)."""
    import torch

    if isinstance(array, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(array, dtype=np.float32)).to(device)
    return array.torch().to(device)


def uv_features(atlas, coarse: np.ndarray, normals: list[np.ndarray], view_dir: np.ndarray, device: str = "cpu"):
    """Assemble the 15-channel input from per-texel arrays (M, 3): returns (features (1,15,R,R), mask (1,1,R,R))."""
    if len(normals) != NUM_NORMAL_FRAMES:
        raise ValueError(f"expected {NUM_NORMAL_FRAMES} normal frames, got {len(normals)}")
    per_texel = np.concatenate([coarse, *normals, view_dir], axis=1).astype(np.float32)
    if per_texel.shape != (atlas.num_texels, IN_CHANNELS):
        raise ValueError(f"expected ({atlas.num_texels}, {IN_CHANNELS}) texel features, got {per_texel.shape}")
    grid = atlas.scatter(per_texel)  # (R, R, 15)
    features = to_torch(grid, device).permute(2, 0, 1)[None].contiguous()
    mask = to_torch(atlas.mask.astype(np.float32), device)[None, None]
    return features, mask


def camera_uv_grid(ls, camera, device: str = "cpu"):
    """Where each pixel centre of ``camera`` lands in UV, as a ``grid_sample`` grid (1, H, W, 2) in [-1, 1], and
    a (1, 1, H, W) mask of pixels that hit the subject. Geometry only: computed once per frame and camera."""

    h, w = camera.height, camera.width
    si = ls.subject_hits(ls.camera_rays(camera))
    uv = np.array(si.uv).T.reshape(h, w, 2)
    valid = np.array(si.is_valid()).reshape(h, w)
    grid = to_torch(2.0 * uv - 1.0, device)[None]
    return grid, to_torch(valid.astype(np.float32), device)[None, None]


def sample_texture(texture, grid, mask=None):
    """Rasterise a (N, C, R, R) UV texture into a camera through its UV grid: (N, C, H, W). Differentiable.

    ``mask`` (1 or N, 1, R, R): the atlas's texels. Texels outside it do not bleed in: the lookup is normalised by the
    mask's own interpolation, as the evaluation's rasteriser (:func:`~gra_mi.render.rasterize.rasterize_to_camera`)
    does, so a texture trained through this lookup is seen the same way when it is scored. Without it, pixels on a
    chart's border would mix in the empty texels beyond it (a dark seam)."""
    import torch
    import torch.nn.functional as F

    grid = grid if grid.shape[0] == texture.shape[0] else grid.expand(texture.shape[0], -1, -1, -1)
    if mask is None:
        return F.grid_sample(texture, grid, mode="bilinear", padding_mode="border", align_corners=False)
    weight = mask.expand(texture.shape[0], 1, -1, -1).to(texture.dtype)
    looked_up = F.grid_sample(
        torch.cat([texture * weight, weight], dim=1), grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    coverage = looked_up[:, -1:]
    return torch.where(coverage > 1e-6, looked_up[:, :-1] / coverage.clamp_min(1e-6), torch.zeros_like(looked_up[:, :-1]))


def torch_render(scene, params, keys: dict[str, str], integrator, sensor: int = 0, spp: int = 4, seed: int = 0):
    """A function ``(albedo (R,R,3), roughness (R,R,1)) -> image (H,W,4)`` on torch tensors whose backward pass runs
    Mitsuba's adjoint rendering: gradients of a torch loss reach the textures."""
    import drjit as dr
    import mitsuba as mi

    @dr.wrap(source="torch", target="drjit")
    def render(albedo, roughness):
        params[keys["albedo"]] = albedo
        params[keys["roughness"]] = roughness
        params.update()
        return mi.render(scene, params, sensor=sensor, integrator=integrator, spp=spp, seed=seed)

    device = "cuda" if mi.variant().startswith("cuda") else "cpu"

    def render_on_the_variants_device(albedo, roughness):
        # dr.wrap maps CPU tensors to the LLVM backend and CUDA tensors to CUDA: move the textures to the variant's
        # device first (differentiably: gradients come back to the caller's tensors).
        return render(albedo.to(device), roughness.to(device))

    return render_on_the_variants_device
