"""RelightNet's data records: a view as the network sees it (:class:`Sample`) and the splits views are scored in. One
floor below the training loop and the synthesized lightings that make them (:mod:`~gra_mi.relightnet.train`,
:mod:`~gra_mi.relightnet.lightings`)."""

from __future__ import annotations

from dataclasses import dataclass

import torch

SYNTHESIZED_SPLIT = "novel lighting (envmap, truth from OLATs)"
HELD_OUT = ("novel view", "novel lighting (envmap)", "novel lighting (OLAT)", SYNTHESIZED_SPLIT)
TEST_LIGHTING = ("novel lighting (envmap)", "novel lighting (OLAT)")  # the capture's test frames: what eval scores


@dataclass
class Sample:
    name: str
    split: str  # "train", "novel view", "novel lighting (envmap)" or "novel lighting (OLAT)"
    features: torch.Tensor  # (1, 15, R, R)
    mask: torch.Tensor  # (1, 1, R, R)
    env: torch.Tensor  # (1, 3, h, 2h)
    grid: torch.Tensor  # (1, H, W, 2)
    pixels: torch.Tensor  # (1, 1, H, W) subject pixels in both the render and the capture
    target: torch.Tensor  # (1, 3, H, W)
    selection: bool = False  # one of the held-out views that choose the weights (reported apart)

    @property
    def camera(self) -> str:
        return self.name.split("/")[0]


def stack(samples: list[Sample]) -> Sample:
    """A batch of views as one Sample (every view of a capture has the same UV and image size)."""
    cat = lambda name: torch.cat([getattr(s, name) for s in samples])  # noqa: E731
    return Sample("batch", "train", *(cat(n) for n in ("features", "mask", "env", "grid", "pixels", "target")))
