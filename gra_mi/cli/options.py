"""Command-line options generated from the typed configs (:mod:`gra_mi.core.config`): every field of a command's config
becomes one option (``steps`` → ``--steps``, a ``False`` bool → ``--flag``, a ``True`` bool → ``--no-flag``,
``X | None`` → an optional ``X``, a field without a default → a required one), a nested config's fields are options
of the same command, and :func:`config_from_args` reads them all back into the config."""

from __future__ import annotations

import argparse
import dataclasses
import re
import types
import typing
from collections.abc import Iterator
from pathlib import Path

from gra_mi.core.config import Option, field_help, option_of


def finite_float(text: str) -> float:
    """argparse type of every real-valued option: NaN and infinities are refused where they are typed."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if value != value or abs(value) == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number, got '{text}'")
    return value


def _value_type(annotation) -> tuple[object, bool]:
    """(the type without None, whether None is allowed) of ``int``, ``float | None``, ``list[Path]``…"""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return args[0], True
    return annotation, False


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    return dataclasses.MISSING


def _nested(kind) -> bool:
    return isinstance(kind, type) and dataclasses.is_dataclass(kind)


def add_config(parser: argparse.ArgumentParser, cls, *, only: tuple[str, ...] | None = None, renames: dict | None = None) -> None:
    """One option per field of ``cls`` (or the ``only`` ones); ``dest`` is the field's name. A field another config of
    the same command already added (the seed) is one option that sets both."""
    docs, hints, renames = field_help(cls), typing.get_type_hints(cls), renames or {}
    existing = {a.dest for a in parser._actions}
    own = cls.__dict__.get("__annotations__", {})
    for f in sorted(dataclasses.fields(cls), key=lambda f: f.name not in own):  # inherited (--overwrite) last
        if (only is not None and f.name not in only) or f.name in existing:
            continue
        spelling, (kind, _) = option_of(f), _value_type(hints[f.name])
        if _nested(kind):
            add_config(parser, kind, only=spelling.fields, renames=dict(spelling.renames))
            continue
        if f.name in renames:
            spelling = dataclasses.replace(spelling, flag=renames[f.name])
        _add_field(parser, f, kind, spelling, docs.get(f.name, ""))


def _add_field(parser: argparse.ArgumentParser, f: dataclasses.Field, kind, spelling: Option, text: str) -> None:
    default = _default(f)
    text = text.replace("%", "%%")  # argparse formats help
    flag = spelling.flag or "--" + f.name.replace("_", "-")
    if kind is bool and default is None:  # automatic unless switched either way
        parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=f"{text} (--no-… switches it off)")
        return
    if kind is bool:
        flag = spelling.flag or (flag if not default else "--no-" + f.name.replace("_", "-"))
        action = "store_false" if default else "store_true"
        parser.add_argument(flag, dest=f.name, action=action, default=default, help=f"Switch off: {text}" if default else text)
        return
    item = typing.get_args(kind)[0] if spelling.repeat else kind
    convert = spelling.parse or (finite_float if item is float else item)
    required = default is dataclasses.MISSING
    unset = "none" if item in (Path, str) else "automatic"
    said = re.search(r"default:|default none|\(default\)", text, re.IGNORECASE)  # the text states it (not "the default layout")
    shown = "" if required or said else f" Default: {unset if default is None else _shown(default)}."
    common = {"type": convert, "choices": spelling.choices, "help": f"{text}{shown}".strip()}
    if spelling.repeat:
        common["action"] = "append"
    if spelling.positional:
        nargs = None if required else "?"
        parser.add_argument(f.name, nargs=nargs, default=None if required else default, metavar=f.name.upper(), **common)
        return
    metavar = spelling.metavar or (None if spelling.choices else flag.lstrip("-").replace("-", "_").upper())
    extra = {"required": True} if required else {"default": default}
    parser.add_argument(flag, dest=f.name, metavar=metavar, **extra, **common)


def _shown(default) -> str:
    if isinstance(default, list | tuple):
        return ",".join(str(d) for d in default) if default else "none"
    return str(default) if not isinstance(default, Path) else default.as_posix()


def config_from_args(cls, args: argparse.Namespace, only: tuple[str, ...] | None = None):
    """A ``cls`` from the options :func:`add_config` added; nested configs are built the same way, and fields that are
    not options keep their defaults."""
    hints, values = typing.get_type_hints(cls), {}
    for f in dataclasses.fields(cls):
        kind, _ = _value_type(hints[f.name])
        if only is not None and f.name not in only:
            continue
        if _nested(kind):
            values[f.name] = config_from_args(kind, args, option_of(f).fields)
        elif hasattr(args, f.name):
            value = getattr(args, f.name)
            values[f.name] = list(value) if isinstance(value, list) else value  # an appended default is not shared
    return cls(**values)


def option_flags(parser: argparse.ArgumentParser) -> dict[str, str]:
    """dest → the flag a user types, for naming parameters in error messages."""
    return {a.dest: max(a.option_strings, key=len) for a in parser._actions if a.option_strings}


@dataclasses.dataclass(kw_only=True)
class CommandConfig:
    """A command's config: its inputs, output and options, validated before anything is read or written."""

    def validate(self) -> None:
        """The configs it holds validate themselves, and its output files' names; a command adds its own checks."""
        from gra_mi.core.guard import check_output_file

        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if dataclasses.is_dataclass(value) and hasattr(value, "validate"):
                value.validate()
            elif option_of(f).writes and isinstance(value, Path):
                check_output_file(value, option_of(f).writes, f.name)


@dataclasses.dataclass(kw_only=True)
class Restartable(CommandConfig):
    """A command whose output folder remembers the run that made it (core/provenance.py)."""

    overwrite: bool = False
    """Start over: empty the output folder first (only a folder gra-mi made). Without it, rerunning the same run
    resumes, and a folder made by a different run (other inputs or options; its provenance.json says which) is refused."""


# What a command reads and where it writes, from its config's Path fields: the guard's view (gra_mi.core.guard).
WRITTEN_FIELDS = ("out", "vis_cache")  # folders a command writes into (a cache is written as well as read)
RUN_PARTS = ("capture", "fit", "relightnet", "refiner")  # a run folder's inputs: its stages, not the folder itself


def _path_values(config, prefix: str = "") -> Iterator[tuple[str, Path]]:
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from _path_values(value, f"{prefix}{f.name}.")
        elif isinstance(value, Path):
            yield prefix + f.name, value
        elif isinstance(value, list | tuple):
            yield from ((f"{prefix}{f.name}[{i}]", v) for i, v in enumerate(value) if isinstance(v, Path))


def output_files(config) -> set[str]:
    """The options of ``config`` that name an output file rather than a folder (``Option.writes``)."""
    return {"--" + f.name.replace("_", "-") for f in dataclasses.fields(config) if option_of(f).writes}


def command_paths(config) -> tuple[dict[str, Path], dict[str, Path]]:
    """(output folders, inputs) of a command's config, by option name. The files a scene names count as inputs (an
    output folder holding the scene or its textures could overwrite them); a run folder's inputs are its stages' folders
    (its eval/ is an output). A config may name its output folder itself (``output_folder()``: a default that
    depends on other options)."""
    from gra_mi.core.guard import scene_references

    outputs, inputs = {}, {}
    for name, path in _path_values(config):
        if name.split(".")[-1] in WRITTEN_FIELDS:
            outputs["--" + name.replace("_", "-")] = path
        elif name == "run":
            inputs.update({f"run's {part}": path / part for part in RUN_PARTS if (path / part).exists()})
        else:
            inputs[name] = path
            if name == "scene" and path.is_file():
                for ref in scene_references(path):
                    label = f"scene's {ref.name}"
                    inputs[label if label not in inputs else f"{label} ({ref})"] = ref
    if hasattr(config, "output_folder"):
        outputs["--out"] = config.output_folder()
    if hasattr(config, "output_paths"):  # what a command writes besides --out (an export's textures beside its file)
        outputs.update(config.output_paths())
    return {k: v for k, v in outputs.items() if v is not None}, inputs
