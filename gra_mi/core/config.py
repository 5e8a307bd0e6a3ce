"""Configs: dataclasses whose fields carry their help as a docstring right under them (as in nerfstudio), and, where
the command line spells them differently, an :func:`option` in their metadata. ``gra_mi.cli`` builds every command's
options from these, so a default, its help and its spelling are written once, next to the code that uses them."""

from __future__ import annotations

import ast
import dataclasses
import inspect
import textwrap
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from gra_mi.core.errors import GraMiParameterError


@dataclass(frozen=True)
class Option:
    """How a config field appears on the command line (the defaults: ``--field-name``, typed from its annotation)."""

    flag: str | None = None
    """The option's name where it is not ``--field-name`` (``--uv-resolution``)."""
    positional: bool = False
    """An argument without a flag (an input folder); optional when the field has a default."""
    parse: Callable[[str], object] | None = None
    """Turns the typed text into the value (comma lists, 'all'); raise ``argparse.ArgumentTypeError`` to refuse."""
    choices: tuple | None = None
    """The values allowed (shown in --help)."""
    repeat: bool = False
    """A list field whose option may be given several times, each adding one item."""
    metavar: str | None = None
    """The placeholder shown in --help (``X,Y,Z``)."""
    fields: tuple[str, ...] | None = None
    """For a nested config: which of its fields are options (default: all of them)."""
    renames: tuple[tuple[str, str], ...] = ()
    """For a nested config: (field, flag) pairs for its fields spelled differently here (``radius`` → ``--platform-radius``)."""
    writes: tuple[str, ...] = ()
    """An output file, not a folder: the suffixes its name may end in (``(".exr",)``), checked before anything runs."""


def option(**spelling) -> dict:
    """Field metadata: ``field(default=…, metadata=option(flag="--uv-resolution"))``."""
    return {"option": Option(**spelling)}


def option_of(f: dataclasses.Field) -> Option:
    return f.metadata.get("option", Option())


def field_help(cls) -> dict[str, str]:
    """The docstring under each field of a dataclass, whitespace collapsed (fields without one are left out)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        for node, after in zip(body, body[1:], strict=False):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant)
                and isinstance(after.value.value, str)
            ):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def comma_list(text: str) -> list[str]:
    """``a, b,c`` → ``["a", "b", "c"]`` (empty items dropped): the parser of list-valued options."""
    return [t.strip() for t in text.split(",") if t.strip()]


def name_list(text: str) -> list[str]:
    """:func:`comma_list` of names (cameras, maps, effects): a name given twice is refused (it would be scored, listed
    or held out twice, or once where the user counted two)."""
    import argparse

    names = comma_list(text)
    if twice := sorted({n for n in names if names.count(n) > 1}):
        raise argparse.ArgumentTypeError(f"{', '.join(repr(n) for n in twice)} given twice in '{text}'")
    return names


def changed_options(config, names: Iterable[str] | None = None) -> list[str]:
    """The fields of ``config`` (or the ``names`` among them) set to something other than their defaults: options that
    another choice of the same command would ignore, to be refused rather than dropped unsaid."""
    changed = []
    for f in dataclasses.fields(config):
        if names is not None and f.name not in names:
            continue
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if default is not dataclasses.MISSING and getattr(config, f.name) != default:
            changed.append(f.name)
    return changed


def options_need_switch(options, switched: bool, switch: str) -> None:
    """Refuse the options of a feature that is off (``--filter-radius`` without ``--deflicker``): they would be
    ignored unsaid."""
    if not switched and (given := changed_options(options)):
        raise GraMiParameterError(given[0], f"takes effect with {switch} only: add {switch}, or leave it out")
