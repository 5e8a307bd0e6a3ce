"""The one error type users see: bad input, named by file and field, or by parameter.

The CLI turns a :class:`GraMiInputError` into a single line on stderr (no traceback) and exit code 2; for a
:class:`GraMiParameterError` it names the command-line flag of the parameter instead (``steps`` → ``--steps``).
"""

from __future__ import annotations

from pathlib import Path


class GraMiInputError(ValueError):
    """Bad user input: a file, a field in it, and what was expected."""

    def __init__(self, source: str | Path | None, problem: str, field: str | None = None):
        self.source = None if source is None else str(source)
        self.field = field
        self.problem = problem
        where = self.source or "<input>"
        if field:
            where = f"{where}: field '{field}'"
        super().__init__(f"{where}: {problem}")


class GraMiParameterError(GraMiInputError):
    """A bad value of a named parameter of a library function or config (``frames``, ``steps``): the Python API user
    sees the parameter's name, the CLI user the flag they typed."""

    def __init__(self, parameter: str, problem: str):
        self.parameter = parameter
        super().__init__(parameter, problem)


def require_positive(values: dict[str, float]) -> None:
    """Raise a :class:`GraMiParameterError` for the first value that is not a finite number > 0."""
    for name, value in values.items():
        if not (value == value and value > 0 and value != float("inf")):  # NaN compares unequal to itself
            raise GraMiParameterError(name, f"must be a finite number > 0, got {value}")


def require_seed(seed: int, name: str = "seed") -> None:
    """Random seeds are unsigned (NumPy, torch and Mitsuba's samplers all refuse negatives)."""
    if not 0 <= seed < 2**32:
        raise GraMiParameterError(name, f"must be an integer in [0, 2^32), got {seed}")
