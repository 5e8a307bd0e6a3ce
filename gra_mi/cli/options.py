"""Command-line options made from the typed configs, so that a default and its help live in one place.

A config is a dataclass whose fields carry their help as a docstring right under them (as in nerfstudio); this
module turns chosen fields into argparse options (``steps`` → ``--steps``, a ``False`` bool → ``--flag``, a
``True`` bool → ``--no-flag``, ``X | None`` → an optional ``X``) and reads them back into the config.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import textwrap
import types
import typing
from collections.abc import Callable, Iterable


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


def _value_type(annotation) -> tuple[type, bool]:
    """(the scalar type, whether None is allowed) of ``int``, ``float | None``, ``str``…"""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return args[0], True
    return annotation, False


def finite_float(text: str) -> float:
    """argparse type of every real-valued option: NaN and infinities are refused where they are typed."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if value != value or abs(value) == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number, got '{text}'")
    return value


def flag_name(field_name: str) -> str:
    return "--" + field_name.replace("_", "-")


def add_config_options(
    parser: argparse.ArgumentParser,
    cls,
    names: Iterable[str],
    *,
    flags: dict[str, str] | None = None,
    parsers: dict[str, Callable[[str], object]] | None = None,
    choices: dict[str, list] | None = None,
    help_extra: dict[str, str] | None = None,
) -> None:
    """Add one option per named field of ``cls``; ``dest`` is the field name, the default is the dataclass's."""
    flags, parsers, choices, help_extra = flags or {}, parsers or {}, choices or {}, help_extra or {}
    docs, hints = field_help(cls), typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    existing = {a.dest for a in parser._actions}
    for name in names:
        if name in existing:  # shared by two configs (e.g. the seed): one option sets both
            continue
        f = fields[name]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        kind, optional = _value_type(hints[name])
        text = " ".join(t for t in (docs.get(name, ""), help_extra.get(name, "")) if t).replace("%", "%%")  # argparse formats help
        if kind is bool:
            flag = flags.get(name, flag_name(name) if not default else "--no-" + name.replace("_", "-"))
            action = "store_false" if default else "store_true"
            parser.add_argument(flag, dest=name, action=action, default=default, help=f"Switch off: {text}" if default else text)
            continue
        shown = "" if "default" in text.lower() else f" Default: {'automatic' if default is None else default}."
        parser.add_argument(
            flags.get(name, flag_name(name)),
            dest=name,
            type=parsers.get(name, finite_float if kind is float else kind),
            default=default,
            choices=choices.get(name),
            metavar=None if name in choices else name.upper(),
            help=f"{text}{shown}".strip(),
        )


def config_from_args(cls, args: argparse.Namespace, **fixed):
    """A ``cls`` from the options :func:`add_config_options` added (fields not on the command line keep their default)."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    return cls(**{**values, **fixed})


def option_flags(parser: argparse.ArgumentParser) -> dict[str, str]:
    """dest → the flag a user types, for naming parameters in error messages."""
    return {a.dest: max(a.option_strings, key=len) for a in parser._actions if a.option_strings}
