"""Learned metrics that need weights the user already has on disk: LPIPS and FVD. gra-mi never downloads them.

- **LPIPS** (Zhang et al. 2018, v0.1, AlexNet): the backbone is written here (torchvision's AlexNet layout, so its
  checkpoint loads as is) with the five linear heads of the ``lpips`` package. ``--lpips-weights`` takes files or a
  folder holding both parts, in any of these layouts: torchvision's ``alexnet-owt-7be5be79.pth`` (backbone) plus the
  lpips package's ``weights/v0.1/alex.pth`` (heads), or one full ``lpips.LPIPS(net='alex').state_dict()``.
- **FVD** (Unterthiner et al. 2019): Fréchet distance between I3D features of real and generated clips.
  ``--i3d-weights`` takes the TorchScript I3D most FVD code uses (``i3d_torchscript.pt``: Kinetics-400, features before
  the classifier), called with clips resized to 224×224 in [-1, 1].

A file that is not what its flag says is a :class:`GraMiInputError` naming the file and what was found.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from gra_mi.core.color import to_display
from gra_mi.core.errors import GraMiInputError

LPIPS_CHANNELS = (64, 192, 384, 256, 256)
_ALEX_CONVS = {0: (3, 64, 11), 3: (64, 192, 5), 6: (192, 384, 3), 8: (384, 256, 3), 10: (256, 256, 3)}
# LPIPS taps AlexNet after each ReLU: features[0:2], [2:5], [5:8], [8:10], [10:12] (torchvision indices).
_SLICE_ENDS = (2, 5, 8, 10, 12)


def _alexnet_features() -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2),
        nn.ReLU(),
        nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1),
        nn.ReLU(),
        nn.Conv2d(384, 256, 3, padding=1),
        nn.ReLU(),
        nn.Conv2d(256, 256, 3, padding=1),
        nn.ReLU(),
    )


class LPIPS(nn.Module):
    """LPIPS v0.1 on AlexNet; :meth:`forward` gives the per-pixel distance map (the package's ``spatial=True``)."""

    def __init__(self):
        super().__init__()
        self.features = _alexnet_features()
        self.heads = nn.ModuleList(nn.Conv2d(c, 1, 1, bias=False) for c in LPIPS_CHANNELS)
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        x, out, start = (x - self.shift) / self.scale, [], 0
        for end in _SLICE_ENDS:
            x = self.features[start:end](x)
            out.append(x / (x.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10))
            start = end
        return out

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """``a``, ``b``: (N, 3, H, W) in [-1, 1] → (N, H, W) distance map."""
        size = a.shape[-2:]
        total = 0
        for head, fa, fb in zip(self.heads, self._taps(a), self._taps(b), strict=True):
            total = total + F.interpolate(head((fa - fb) ** 2), size=size, mode="bilinear", align_corners=False)
        return total[:, 0]


def _load_state(path: Path, flag: str) -> dict:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # pickle, zip and torch errors alike: the file is not a weights file
        raise GraMiInputError(path, f"{flag}: not a PyTorch weights file ({str(exc).splitlines()[0][:120]})") from None
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise GraMiInputError(path, f"{flag}: expected a state dict, found a {type(state).__name__}")
    return state


def load_lpips(paths: list[str | Path], device: str = "cpu") -> LPIPS:
    """LPIPS with weights from ``paths`` (files, or folders whose ``*.pth``/``*.pt`` files are all read); see the
    module doc for the layouts. Raises :class:`GraMiInputError` naming what is missing or of the wrong shape."""
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            files += sorted(q for q in p.iterdir() if q.suffix in (".pth", ".pt"))
        elif p.is_file():
            files.append(p)
        else:
            raise GraMiInputError(p, "--lpips-weights: file not found")
    model = LPIPS()
    wanted = [f"features.{i}.{k}" for i in _ALEX_CONVS for k in ("weight", "bias")] + [f"heads.{i}.weight" for i in range(5)]
    found: dict[str, tuple[torch.Tensor, Path]] = {}
    for file in files:
        for key, value in _load_state(file, "--lpips-weights").items():
            name = key.removeprefix("module.")
            if name.startswith("net.slice"):  # lpips.LPIPS: net.sliceK.<torchvision index>.weight
                name = "features." + name.split(".", 2)[2]
            elif name.startswith("lin") and ".model.1.weight" in name:  # lpips heads: linK.model.1.weight
                name = f"heads.{name[3]}.weight"
            if name in wanted and torch.is_tensor(value):
                found[name] = (value, file)
    missing = [k for k in wanted if k not in found]
    where = ", ".join(str(f) for f in files) or str(paths)
    if missing:
        part = "AlexNet backbone (features.*)" if any(k.startswith("features") for k in missing) else "linear heads (lin0…lin4)"
        raise GraMiInputError(
            where,
            f"--lpips-weights: no LPIPS {part} found; expected torchvision's alexnet-owt-7be5be79.pth and the lpips package's "
            "weights/v0.1/alex.pth, or a full lpips.LPIPS(net='alex') state dict",
        )
    state = model.state_dict()
    for name, (value, file) in found.items():
        if tuple(value.shape) != tuple(state[name].shape):
            raise GraMiInputError(
                file, f"--lpips-weights: '{name}' has shape {tuple(value.shape)}, AlexNet LPIPS expects {tuple(state[name].shape)}"
            )
        state[name] = value.float()
    model.load_state_dict(state)
    return model.eval().to(device)


def lpips_distance(model: LPIPS, image: np.ndarray, reference: np.ndarray, mask: np.ndarray, exposure: float) -> float:
    """Mean LPIPS over the mask, both images shown at ``exposure`` (:func:`gra_mi.core.metrics.to_display`)."""

    device = next(model.parameters()).device

    def tensor(x):
        return torch.from_numpy(2 * to_display(x, exposure) - 1).float().permute(2, 0, 1)[None].to(device)

    distance = model(tensor(image), tensor(reference))[0].cpu().numpy()
    return float(distance[mask].mean()) if mask.any() else 0.0


# --------------------------------------------------------------------------------------------------------------
# FVD
# --------------------------------------------------------------------------------------------------------------

I3D_SIZE = 224


def load_i3d(path: str | Path, device: str = "cpu"):
    """The TorchScript I3D feature extractor at ``path``, checked on a dummy clip (400 or 1024 features per clip)."""
    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "--i3d-weights: file not found")
    try:
        model = torch.jit.load(str(path), map_location=device).eval()
    except Exception as exc:
        raise GraMiInputError(
            path, f"--i3d-weights: not a TorchScript model ({str(exc).splitlines()[0][:120]}); expected i3d_torchscript.pt as used for FVD"
        ) from None
    try:
        with torch.no_grad():
            probe = model(torch.zeros(1, 3, 9, I3D_SIZE, I3D_SIZE, device=device), rescale=False, resize=False, return_features=True)
    except Exception as exc:
        raise GraMiInputError(
            path,
            f"--i3d-weights: the model does not take (clips, rescale=, resize=, return_features=) like i3d_torchscript.pt ({str(exc).splitlines()[0][:120]})",
        ) from None
    if probe.ndim != 2 or probe.shape[0] != 1:
        raise GraMiInputError(path, f"--i3d-weights: expected one feature vector per clip, got shape {tuple(probe.shape)}")
    return model


@torch.no_grad()
def i3d_features(model, clips: list[np.ndarray]) -> np.ndarray:
    """Clips of display frames ((T, H, W, 3) in [0, 1]) → (N, D) I3D features (float64)."""
    device = next(iter(model.parameters()), torch.zeros(0)).device
    out = []
    for clip in clips:
        x = torch.from_numpy(np.asarray(clip, np.float32)).permute(0, 3, 1, 2)  # (T, 3, H, W)
        x = F.interpolate(x, size=(I3D_SIZE, I3D_SIZE), mode="bilinear", align_corners=False) * 2 - 1
        out.append(
            model(x.permute(1, 0, 2, 3)[None].to(device), rescale=False, resize=False, return_features=True).double().cpu().numpy()[0]
        )
    return np.stack(out)


def frechet_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to feature sets ``a`` and ``b`` (N, D): |μa − μb|² + tr(Σa + Σb − 2(ΣaΣb)^½)."""
    import scipy.linalg

    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    cov_a = np.atleast_2d(np.cov(a, rowvar=False)) if len(a) > 1 else np.zeros((a.shape[1], a.shape[1]))
    cov_b = np.atleast_2d(np.cov(b, rowvar=False)) if len(b) > 1 else np.zeros((b.shape[1], b.shape[1]))
    root, _ = scipy.linalg.sqrtm(cov_a @ cov_b, disp=False)
    return float(np.sum((mu_a - mu_b) ** 2) + np.trace(cov_a + cov_b - 2 * np.real(root)))
