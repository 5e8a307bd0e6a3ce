"""Reading a model's weight file (safetensors) the one way both learned stages do: a damaged, empty or non-finite
file is a one-line :class:`GraMiInputError` naming it, never a traceback and never a model that renders NaN."""

from __future__ import annotations

from pathlib import Path

import torch

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path, atomic_write_text, check_config_types, read_json


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


def write_model(folder: str | Path, name: str, format_id: str, config, tensors: dict[str, torch.Tensor]) -> None:
    """A model as both learned stages store one: ``NAME.safetensors`` (the tensors) and ``NAME.json`` (``format`` and
    the config dataclass's fields), each written atomically."""
    import dataclasses
    import json

    from safetensors.torch import save_file

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / f"{name}.safetensors") as tmp:
        save_file({k: v.detach().cpu().contiguous() for k, v in tensors.items()}, str(tmp))
    atomic_write_text(folder / f"{name}.json", json.dumps({"format": format_id, **dataclasses.asdict(config)}, indent=1) + "\n")


def read_model_config(path: str | Path, cls, format_id: str, hint: str = "", retired: frozenset[str] = frozenset(), **overrides):
    """The config dataclass ``cls`` from a model's JSON (:func:`write_model`): its ``format`` must be ``format_id``,
    every key must be a field (``retired``: fields an earlier version wrote and this one no longer has, ignored), and
    every value must have its default's type. ``overrides`` replace fields. Each failure names the file and field."""
    import dataclasses

    path = Path(path)
    data = read_json(path, hint)
    if not isinstance(data, dict):
        raise GraMiInputError(path, f"expected a JSON object with a 'format' field{hint}")
    found = data.pop("format", None)
    if found != format_id:
        raise GraMiInputError(path, f"expected {format_id!r}, got {found!r}{hint}", field="format")
    known = {f.name for f in dataclasses.fields(cls)}
    if unknown := sorted(set(data) - known - retired):
        raise GraMiInputError(path, f"unknown keys {unknown}; expected some of {sorted(known)}")
    data = {k: v for k, v in data.items() if k in known}
    check_config_types(cls, data, path)
    return cls(**{**data, **overrides})
