"""Reading a model's weight file (safetensors) the one way both learned stages do: a damaged, empty or non-finite
file is a one-line :class:`GraMiInputError` naming it, never a traceback and never a model that renders NaN."""

from __future__ import annotations

from pathlib import Path

import torch

from gra_mi.core.errors import GraMiInputError


def read_weights(path: str | Path, hint: str = "") -> dict[str, torch.Tensor]:
    """The tensors of the safetensors file ``path``; refuses a missing, truncated or empty file and any tensor with a
    non-finite value (a diverged training run's). ``hint``: what makes the file, for the message."""
    from safetensors.torch import load_file

    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, f"file not found{hint}")
    try:
        tensors = load_file(str(path))
    except Exception as exc:  # SafetensorError (truncated, empty, not safetensors) derives from Exception only
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise GraMiInputError(path, f"unreadable weights ({first}){hint}") from None
    if not tensors:
        raise GraMiInputError(path, f"holds no tensors{hint}")
    broken = [name for name, t in tensors.items() if t.is_floating_point() and not bool(torch.isfinite(t).all())]
    if broken:
        raise GraMiInputError(
            path, f"{len(broken)} tensor(s) hold non-finite values (e.g. {broken[0]}): weights of a diverged training run?"
        )
    return tensors
