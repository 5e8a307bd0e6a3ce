"""What made an output folder, so that a resume never mixes two runs, and a lock against two writers.

Every resumable folder (capture, fit, RelightNet, refiner data, refiner, refined video) holds ``provenance.json``:
the command, a content id of each input and the config. A rerun into the folder compares them first: the same run
resumes; a different one stops with the difference named (``overwrite=True`` / ``--overwrite`` starts over). Fields
listed as ``free`` (the step count, logging cadence) may change between runs: raising ``--steps`` continues training.

The lock is an advisory ``flock`` on ``.gra-mi.lock`` held until the process ends (Unix; re-entrant within one
process, so a pipeline that resumes its own stages is not blocked by itself).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
from pathlib import Path

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import check_apart
from gra_mi.core.io import atomic_write_text

logger = logging.getLogger(__name__)

PROVENANCE = "provenance.json"
LOCK = ".gra-mi.lock"
SMALL_FILE = 1 << 16  # inputs this small are hashed whole; larger ones by size and their first and last 64 KiB
SKIPPED = {PROVENANCE, LOCK, "cache", "checkpoint.pt", "checkpoint.npz", "optimize.npz", "__pycache__"}  # what a run writes for itself
REPORTS = {".json", ".md", ".png", ".csv", ".mp4", ".log", ".txt"}
"""Left out of a run's id: rewritten by a resume (timings, plots, scores)."""
DATA_TEXT = {"capture.json", "calibration.json", "dataset.json", "relightnet.json", "refiner.json", "index.json"}
"""JSON files that are data, not reports: part of a run's id with their whole content (with scene XML), so that an
edited calibration or capture record is a different input even where its size is unchanged."""
DERIVED = {"scene_gt_envmap.xml"}  # written into captures by gra-mi before 0.1.0's eval-lighting read the truth from memory
_HELD: dict[Path, int] = {}
_FRESH: set[Path] = set()  # folders a claim created: removed again if the run stops before writing anything


def content_id(path: str | Path) -> str | None:
    """A short id of an input: for a folder a gra-mi run made, the run that made it (its provenance record: the
    command, its inputs' ids and its config) and the names and sizes of its data files (a resumed run rewrites its
    plots, logs and reports, which are left out, and keeps this id; an edited or missing data file changes it);
    otherwise a hash of the content (small files whole, larger ones by size and ends). The data JSON and scene XML of
    a run's folder count with their content (:data:`DATA_TEXT`). None for a missing path.
    Copying or moving an input keeps its id."""
    path = Path(path)
    if not path.exists():
        return None
    digest = hashlib.sha256()
    record = path / PROVENANCE
    if path.is_dir() and record.is_file():
        try:
            made = json.loads(record.read_text())
            digest.update(json.dumps({k: made.get(k) for k in ("command", "inputs", "config")}, sort_keys=True).encode())
            for f in _files(path):
                text = f.name in DATA_TEXT or (f.suffix == ".xml" and f.name not in DERIVED)
                if f.suffix not in REPORTS or text:
                    digest.update(f"{f.relative_to(path)}:{f.stat().st_size}\n".encode())
                if text:
                    digest.update(f.read_bytes())
            return "run:" + digest.hexdigest()[:16]
        except ValueError:
            pass  # unreadable: fall back to the content
    files = [path] if path.is_file() else _files(path)
    for f in files:
        size = f.stat().st_size
        digest.update(f"{f.relative_to(path) if f != path else f.name}:{size}\n".encode())
        with open(f, "rb") as fh:
            if size <= SMALL_FILE:
                digest.update(fh.read())
            else:
                digest.update(fh.read(SMALL_FILE))
                fh.seek(-SMALL_FILE, os.SEEK_END)
                digest.update(fh.read())
    return digest.hexdigest()[:16]


def _files(folder: Path) -> list[Path]:
    """The files that make up an input folder: caches, checkpoints, the lock and the outputs of other runs nested
    in it (``fit`` written into ``capture/fit``) are left out."""
    nested = {p.parent for p in folder.rglob(PROVENANCE) if p.parent != folder}
    return sorted(
        p
        for p in folder.rglob("*")
        if p.is_file()
        and not SKIPPED & set(p.relative_to(folder).parts)
        and not is_lock(p.name)
        and not any(n in p.parents for n in nested)
    )


def _plain(config) -> dict:
    if dataclasses.is_dataclass(config):
        config = dataclasses.asdict(config)
    return json.loads(json.dumps(config or {}, default=str))  # tuples → lists, paths → str: what the file holds


def is_lock(name: str) -> bool:
    """The folder's writer lock, or a shard's (``.gra-mi.lock.shard-0-of-4``)."""
    return name == LOCK or name.startswith(LOCK + ".shard-")


def lock_folder(folder: Path, suffix: str = "") -> None:
    """Hold the folder's writer lock (a shard's own with ``suffix``) until the process ends; a second process with
    the same lock stops with its pid named."""
    folder = folder.resolve()
    if folder in _HELD:
        return
    folder.mkdir(parents=True, exist_ok=True)
    fd = os.open(folder / (LOCK + suffix), os.O_RDWR | os.O_CREAT, 0o644)
    try:
        import fcntl

        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except ImportError:  # not Unix: no advisory locks; the provenance check still applies
        pass
    except OSError:
        holder = os.read(fd, 32).decode(errors="replace").strip() or "?"
        os.close(fd)
        who = f"shard {suffix.split('-', 1)[1].replace('-of-', '/')} of this folder" if suffix else "this folder"
        raise GraMiInputError(
            folder, f"another gra-mi process (pid {holder}) is writing {who}; wait for it, or choose another output folder"
        ) from None
    os.ftruncate(fd, 0)
    os.write(fd, str(os.getpid()).encode())
    _HELD[folder] = fd


def release_folder(folder: Path) -> None:
    """Give up the lock early (library callers that run two stages on one folder one after another)."""
    fd = _HELD.pop(Path(folder).resolve(), None)
    if fd is not None:
        os.close(fd)


def claim_output(
    folder: str | Path,
    command: str,
    inputs: dict[str, str | Path | None],
    config=None,
    *,
    overwrite: bool = False,
    free: tuple[str, ...] = (),
    restart: bool = False,
    shard=None,
) -> Path:
    """Lock ``folder`` and check it was made by this same run (or is new, or empty); record what makes it.

    ``inputs``: name → path (its content id is recorded); ``config``: a dataclass or dict; ``free``: config keys
    allowed to differ on a resume. A folder made otherwise raises a :class:`GraMiInputError` naming the
    difference. ``overwrite`` empties the folder first, whoever made it (only a folder gra-mi made: one with
    provenance.json; a file a user's folder happens to share with gra-mi's outputs, ``checkpoint.pt`` or
    ``fit.json``, never makes it gra-mi's), so the run starts over.
    ``restart``: a command whose output is not resumable state (``refine``) starts over in a folder that it made
    itself with other inputs or options, instead of refusing. ``shard`` (:class:`gra_mi.core.shard.Shard`): one of N
    processes writing the folder together; it takes its shard's lock, and the folder records N (a folder started with
    another number of shards is refused). Shards cannot ``overwrite``: one would empty what the others write.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise GraMiInputError(folder, "is a file; expected an output folder")
    sharded = shard is not None and not shard.whole
    if sharded and overwrite:
        raise GraMiParameterError("overwrite", "cannot be combined with --shard: empty the folder once, then start the shards")
    # --overwrite empties the output folder, a resume rewrites it: never one that is, holds or lies in an input
    check_apart({"": folder}, {name: Path(given) for name, given in inputs.items() if isinstance(given, str | Path)})
    record = run_record(command, inputs, config, shard.count if sharded else None)
    path = folder / PROVENANCE
    if not folder.exists():
        _FRESH.add(folder.resolve())
    existing = [p for p in folder.iterdir() if not is_lock(p.name)] if folder.is_dir() else []
    if existing and not path.is_file():
        if overwrite:
            raise GraMiInputError(folder, "--overwrite empties only folders gra-mi made (with provenance.json); this one has none")
        raise GraMiInputError(folder, "is not empty and was not made by gra-mi (no provenance.json); choose an empty or new output folder")
    if existing:
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise GraMiInputError(path, f"unreadable ({exc}); remove the folder or use --overwrite") from None
        differences = _differences(old, record, free)
        if differences and restart and old.get("command") == command:
            logger.info("%s: starting over (%s)", folder, "; ".join(differences))
            overwrite = True
        if differences and not overwrite:
            raise GraMiInputError(
                path,
                f"this folder was made by another run ({'; '.join(differences)}): resuming would mix the two. "
                "Use --overwrite to start over, or choose another output folder",
            )
        if overwrite:
            _empty(folder)
    lock_folder(folder, shard.lock_suffix if sharded else "")
    atomic_write_text(path, json.dumps(record, indent=1) + "\n")
    return folder


def run_record(command: str, inputs: dict, config=None, shards: int | None = None) -> dict:
    """What provenance.json records of a run. An input may be a list of files (those a run read outside its input
    folders: one id over all of them)."""

    def ident(given):
        if isinstance(given, list | tuple):
            return hashlib.sha256("".join(f"{p}:{content_id(p)}\n" for p in given).encode()).hexdigest()[:16] if given else None
        return content_id(given) if given is not None else None

    def shown(given):
        if isinstance(given, list | tuple):
            return f"{len(given)} files" if given else None
        return str(given) if given is not None else None

    return {
        "command": command,
        "inputs": {name: ident(given) for name, given in inputs.items()},
        "input_paths": {name: shown(given) for name, given in inputs.items()},
        "config": _plain(config) | ({"shards": shards} if shards else {}),
    }


def run_differences(folder: str | Path, record: dict, free: tuple[str, ...] = ()) -> list[str] | None:
    """How the run that made ``folder`` differs from ``record`` (:func:`run_record`); None for a folder without
    provenance (absent, empty, or not made by gra-mi)."""
    path = Path(folder) / PROVENANCE
    if not path.is_file():
        return None
    try:
        return _differences(json.loads(path.read_text()), record, free)
    except ValueError as exc:
        raise GraMiInputError(path, f"unreadable ({exc}); remove the folder or use --overwrite") from None


def _empty(folder: Path) -> None:
    """Start over: remove everything in a folder gra-mi made (under its lock, so no one is writing)."""
    lock_folder(folder)
    for p in folder.iterdir():
        if not is_lock(p.name):
            shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()


def discard_unused_claims() -> None:
    """After a failed run: remove the folders its claims created that hold nothing but the claim (no partial
    output is left by an error found after the claim, such as a corrupt input read later)."""
    for folder in list(_FRESH):
        if folder.is_dir() and all(p.name == PROVENANCE or is_lock(p.name) for p in folder.iterdir()):
            release_folder(folder)
            shutil.rmtree(folder, ignore_errors=True)
        _FRESH.discard(folder)


def _flat(config: dict, prefix: str = "") -> dict:
    """Nested configs ({"train": {...}, "model": {...}}) as dotted keys, so each field is compared and named."""
    flat = {}
    for key, value in config.items():
        if isinstance(value, dict) and value and all(isinstance(k, str) for k in value):
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[prefix + key] = value
    return flat


def _differences(old: dict, new: dict, free: tuple[str, ...]) -> list[str]:
    said = []
    if old.get("command") != new["command"]:
        said.append(f"command {old.get('command')!r}, now {new['command']!r}")
    for name in sorted(set(old.get("inputs", {})) | set(new["inputs"])):
        if old.get("inputs", {}).get(name) != new["inputs"].get(name):
            was = old.get("input_paths", {}).get(name)
            said.append(f"input {name}: {was} then, {new['input_paths'].get(name)} now (different content)")
    old_config, new_config = _flat(old.get("config", {})), _flat(new["config"])
    for key in sorted(set(old_config) | set(new_config)):
        if key.rsplit(".", 1)[-1] not in free and old_config.get(key) != new_config.get(key):
            said.append(f"{key}: {old_config.get(key)!r} then, {new_config.get(key)!r} now")
            if key == "shards" and isinstance(old_config[key], int):  # the one difference a user resolves by a flag
                said[-1] += f" (it was started with {old_config[key]} shards: run each with --shard I/{old_config[key]})"
    return said


def different_outputs(a: Path, b: Path, ignore=lambda p: False) -> list[str]:
    """Relative paths that differ between two output folders (missing on one side, or other bytes), gra-mi's own
    bookkeeping aside (provenance, locks, the shards record) and what ``ignore`` names: are two runs' outputs the
    same (one process against shards, a rerun against the first run)?"""
    import filecmp

    from gra_mi.core.shard import SHARDS_RECORD

    def kept(p: Path) -> bool:
        return p.is_file() and not (p.name in (PROVENANCE, SHARDS_RECORD) or is_lock(p.name) or ignore(p))

    left = {p.relative_to(a) for p in a.rglob("*") if kept(p)}
    right = {p.relative_to(b) for p in b.rglob("*") if kept(p)}
    return sorted(str(p) for p in left ^ right) + sorted(str(p) for p in left & right if not filecmp.cmp(a / p, b / p, shallow=False))
