"""The one error type users see: bad input, named by file and field.

The CLI turns a :class:`GraMiInputError` into a single line on stderr (no traceback) and exit code 2.
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
