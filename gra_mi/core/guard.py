"""The doors between users' files and gra-mi's outputs: names read from inputs, and where a command may write.

- :func:`path_component`: every name that comes from an input file (a sensor id, a camera name, an envmap or pattern
  name, a light path's name) and becomes part of an output path passes through here. A separator, ``..``, an absolute
  path, an empty name or a control character is refused, naming the file and field it came from.
- :func:`writing_into`: while a command runs, every file gra-mi writes (every writer goes through
  :func:`gra_mi.core.io.atomic_path`) must resolve inside one of the command's output folders; anything else is
  refused before a byte is written. This is the second lock on the same door: a name that slipped past the first
  cannot write outside ``--out``.
- :func:`check_apart`: a command's output folder may not be, hold, or lie inside one of its inputs (the files a
  scene reads count: :func:`scene_references`).
"""

from __future__ import annotations

import contextlib
import contextvars
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from gra_mi.core.errors import GraMiInputError, GraMiParameterError

MAX_COMPONENT_BYTES = 200  # below every common file system's 255-byte limit, with room for suffixes
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_ROOTS: contextvars.ContextVar[tuple[Path, ...]] = contextvars.ContextVar("gra_mi_output_roots", default=())
_SCRATCH: set[Path] = set()  # temporary folders gra-mi made itself: always writable


def path_component(name, source: str | Path | None, field: str) -> str:
    """``name`` as one file or folder name, or a :class:`GraMiInputError` naming ``source`` and ``field``."""
    if not isinstance(name, str):
        raise GraMiInputError(source, f"expected a name (a string), got {type(name).__name__} {name!r}", field=field)
    problem = None
    if not name.strip():
        problem = "is empty"
    elif "/" in name or "\\" in name:
        problem = "contains a path separator"
    elif name in (".", ".."):
        problem = "is a relative folder reference"
    elif _CONTROL.search(name):
        problem = "contains a control character"
    elif len(name.encode("utf-8", "surrogateescape")) > MAX_COMPONENT_BYTES:
        problem = f"is longer than {MAX_COMPONENT_BYTES} bytes"
    if problem:
        raise GraMiInputError(
            source, f"the name {name!r} {problem}; gra-mi uses it as a file name in the output, so it must be a plain name", field=field
        )
    return name


@contextlib.contextmanager
def writing_into(roots: Iterable[str | Path]) -> Iterator[None]:
    """Within the block, :func:`check_output_path` refuses files outside ``roots`` (none given: no restriction)."""
    resolved = tuple(Path(r).resolve() for r in roots if r is not None)
    token = _ROOTS.set(resolved)
    try:
        yield
    finally:
        _ROOTS.reset(token)


def staging_folder(out: str | Path) -> Path:
    """The hidden sibling a command builds ``out`` in before publishing it by rename (``.NAME.partial``); while a
    command runs with ``out`` among its output folders, its staging folder is one too."""
    out = Path(out)
    staging = out.parent / f".{out.name}.partial"
    roots = _ROOTS.get()
    if roots and out.resolve() in roots and staging.resolve() not in roots:
        _ROOTS.set((*roots, staging.resolve()))
    return staging


def scratch_folder(prefix: str = "gra-mi-") -> Path:
    """A new temporary folder that the running command may write into (its caller removes it)."""
    folder = Path(tempfile.mkdtemp(prefix=prefix)).resolve()
    _SCRATCH.add(folder)
    return folder


@contextlib.contextmanager
def scratch_directory(prefix: str = "gra-mi-") -> Iterator[Path]:
    """:func:`scratch_folder` for the length of a block, removed after it."""
    folder = scratch_folder(prefix)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        _SCRATCH.discard(folder)


def _within(target: Path, root: Path) -> bool:
    """``target`` inside the output ``root``: a folder, or an output file (``--out edited.exr``), which may have
    siblings of its own stem (``edited.png``, its preview)."""
    if target == root or root in target.parents:
        return True
    is_file = bool(root.suffix) and not root.is_dir()
    return is_file and target.parent == root.parent and target.name.startswith(root.stem + ".")


def check_output_path(path: str | Path) -> None:
    """Refuse a file that would land outside the running command's output folders (symlinks resolved)."""
    roots = _ROOTS.get()
    if not roots:
        return
    target = Path(path).resolve()
    if not any(_within(target, root) for root in (*roots, *_SCRATCH)):
        said = ", ".join(str(r) for r in roots)
        raise GraMiInputError(
            path, f"gra-mi would write this file outside the output folder ({said}); a name taken from an input must not lead out of it"
        )


def _relation(out: Path, given: Path) -> str | None:
    """How the output folder ``out`` overlaps the input ``given`` (both resolved), or None."""
    if out == given:
        return "is"
    if out in given.parents:
        return "holds"
    if given.is_dir() and given in out.parents:
        return "lies inside"
    return None


def names_of(paths: Iterable[str | Path], parameter: str) -> dict[str, Path]:
    """Files named by their stem (an envmap, a pattern), each stem a plain name and used once: two files with one stem
    are refused naming both (one would overwrite or replace the other)."""
    named: dict[str, Path] = {}
    for path in map(Path, paths):
        stem = path_component(path.stem, path, "file name")
        if stem in named:
            raise GraMiParameterError(parameter, f"{named[stem]} and {path} are both named '{stem}': rename one")
        named[stem] = path
    return named


def check_apart(outputs: dict[str, Path], inputs: dict[str, Path], files: Iterable[str] = ()) -> None:
    """Refuse an output folder (or the output files named in ``files``) that is, holds or lies inside an input, before
    anything is written."""
    for out_name, out in outputs.items():
        out_r, kind = Path(out).resolve(), "file" if out_name in files else "folder"
        for in_name, given in inputs.items():
            relation = _relation(out_r, Path(given).resolve())
            if relation:
                raise GraMiInputError(
                    out,
                    f"the output {kind}{f' ({out_name})' if out_name else ''} {relation} {given} (the {in_name} input); "
                    f"write the output to another folder",
                )


def check_output_file(path: Path, suffixes: tuple[str, ...], parameter: str) -> None:
    """An output that is one file: refused where it names a folder or ends in another suffix than the format's (an
    EXR written as ``edited.png`` would be overwritten by its own preview; a name without one would be ambiguous)."""
    expected = " or ".join(suffixes)
    if path.is_dir():
        raise GraMiParameterError(parameter, f"{path} is a folder; give the file to write, a name ending {expected}")
    if path.suffix.lower() not in suffixes:
        raise GraMiParameterError(parameter, f"'{path}': give a file name ending {expected} (the format written)")


def scene_references(scene_file: Path) -> list[Path]:
    """The files and folders a Mitsuba scene reads — ``<include filename=…>``, ``<string name="filename" value=…>`` and
    ``<default>`` values that name a path (a lightstage scene's subject and calibration) — with ``$name`` replaced by
    the scene's defaults and resolved against its folder as Mitsuba resolves them: what an output folder must not
    hold."""
    try:
        text = scene_file.read_text(errors="replace")
    except OSError:
        return []
    defaults = dict(re.findall(r'<default\s+name\s*=\s*"([^"]+)"\s+value\s*=\s*"([^"]*)"', text))
    found = re.findall(r'<include\s+filename\s*=\s*"([^"]+)"', text)
    found += re.findall(r'name\s*=\s*"filename"\s+value\s*=\s*"([^"]+)"', text)
    found += re.findall(r'value\s*=\s*"([^"]+)"\s+name\s*=\s*"filename"', text)
    found += list(defaults.values())
    paths = []
    for value in found:
        for name, default in defaults.items():
            value = value.replace(f"${name}", default)
        path = scene_file.parent / value
        if "$" not in value and value and path.exists():
            paths.append(path)
    return paths
