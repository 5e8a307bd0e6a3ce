"""One typed schema layer for the files gra-mi reads: records parsed by pydantic v2, every error naming the file, the
field (and the line, where the format has lines) and what was expected.

pydantic rather than msgspec: the formats are small and read once (speed is not the point), while their checks are
not only types — finite numbers, positive focal lengths, rigid right-handed rotations, matrices of a shape —
and pydantic's annotated validators state each once and compose them, with an error path (``frames.3.fl_x``) that
becomes the field named to the user.

Shared building blocks: :data:`Finite`, :data:`Positive`, :data:`Count`, :func:`matrix` (a finite array of a shape),
:func:`rigid_rotation`. :func:`parse` validates a mapping and turns pydantic's error into a
:class:`~gra_mi.core.errors.GraMiInputError`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, TypeVar

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, ValidationError

from gra_mi.core.errors import GraMiInputError

Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Count = Annotated[int, Field(ge=0)]
PositiveCount = Annotated[int, Field(gt=0)]
ROTATION_TOLERANCE = 1e-4

Model = TypeVar("Model", bound=BaseModel)


class Record(BaseModel):
    """Base of every record: unknown keys are kept (formats carry extras), arrays allowed as field types."""

    model_config = ConfigDict(extra="allow", arbitrary_types_allowed=True)


def _as_matrix(value: Any, shape: tuple[int, ...]) -> np.ndarray:
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"expected {shape[0] if len(shape) == 1 else ' × '.join(map(str, shape))} numbers") from None
    if array.size == int(np.prod(shape)) and array.shape != shape and len(shape) == 1:
        array = array.reshape(shape)  # a 3 × 1 or 1 × 3 vector read as 3
    if array.shape != shape:
        expected = f"{shape[0]} numbers" if len(shape) == 1 else f"a {' × '.join(map(str, shape))} matrix"
        raise ValueError(f"expected {expected}, got shape {' × '.join(map(str, array.shape)) or 'scalar'}")
    if not np.isfinite(array).all():
        raise ValueError("expected finite numbers (no NaN or infinity)")
    return array


def matrix(*shape: int):
    """An annotated type: a finite float64 array of ``shape`` (a vector of n accepts n × 1 and 1 × n)."""
    return Annotated[np.ndarray, BeforeValidator(lambda v: _as_matrix(v, shape))]


def rigid_rotation(rotation: np.ndarray, what: str = "rotation") -> np.ndarray:
    """``rotation`` if it is orthonormal with determinant +1 (a camera's pose); a scaled, sheared or mirrored one is
    refused with what is wrong with it."""
    gram = rotation.T @ rotation
    det = float(np.linalg.det(rotation))
    if not np.allclose(gram, np.eye(3), atol=ROTATION_TOLERANCE):
        scales = np.sqrt(np.clip(np.diag(gram), 0, None))
        raise ValueError(f"the {what} is not orthonormal (axis lengths {np.round(scales, 4).tolist()}): a pose must be rigid")
    if det < 0:
        raise ValueError(f"the {what} has determinant {det:.3f}: a mirrored (left-handed) pose")
    return rotation


def intrinsic_matrix(k: np.ndarray) -> np.ndarray:
    """A pinhole K: focal lengths > 0, last row (0, 0, 1) (any positive multiple of it is normalised)."""
    if k[2, 0] != 0 or k[2, 1] != 0 or k[2, 2] <= 0:
        raise ValueError(f"expected a pinhole K with last row (0, 0, 1), got {k[2].tolist()}")
    k = k / k[2, 2]
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise ValueError(f"focal lengths must be > 0, got fx = {k[0, 0]:g}, fy = {k[1, 1]:g}")
    if k[1, 0] != 0:
        raise ValueError("expected K[1][0] = 0")
    return k


def _location(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def parse(
    model: type[Model], data: Any, source: str | Path | None, where: str = "", line: int | None = None, key_suffix: str = ""
) -> Model:
    """``data`` as a ``model`` record, or a :class:`GraMiInputError` naming ``source``, the field (``where`` plus the
    failing key, plus ``key_suffix`` where the file spells keys per item: ``K`` → ``K_cam01``) and the line where one
    is given."""
    if not isinstance(data, dict):
        raise GraMiInputError(source, f"expected an object, got {type(data).__name__}", field=where or None)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        error = exc.errors()[0]
        key = _location(error["loc"])
        key = f"{key}{key_suffix}" if key else key
        field = f"{where}.{key}" if where and key else (where or key or None)
        problem = error["msg"].removeprefix("Value error, ")
        given = error.get("input")
        if error["type"] != "missing" and not isinstance(given, dict | list | np.ndarray):
            problem += f" (got {given!r})"
        if line is not None:
            problem = f"line {line}: {problem}"
        raise GraMiInputError(source, problem, field=field) from None
