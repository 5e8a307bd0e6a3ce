"""Per-frame work split over processes and machines: ``--shard I/N``, or the rank a launcher gives.

A shard takes every N-th frame starting at I (round-robin keeps shards' loads even when frames differ in cost, and a
frame's work — its visibility, its cameras — stays in one process). Where no ``--shard`` is given, the launcher's
variables say it: torchrun's ``RANK`` / ``WORLD_SIZE``, or a SLURM job array's ``SLURM_ARRAY_TASK_ID`` /
``SLURM_ARRAY_TASK_COUNT`` (``SLURM_ARRAY_TASK_MIN`` is subtracted: arrays may start at 1). Each shard writes its
own frames into the shared output folder under a lock of its own; every output a frame does not decide alone (an
index, a video) is written by the shard that finds the others' frames done.
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field

from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError


@dataclass(kw_only=True)
class ShardOptions:
    """The ``--shard`` option of the commands whose work is per frame."""

    shard: str | None = field(default=None, metadata=option(metavar="I/N"))
    """Do only shard I of N of the frames (eval-lighting: of the maps whose truth it path-traces; I/N, from 0), into
    the same output folder as the other shards; run the N shards as separate processes or jobs (docs/guides/scale.md). Default: torchrun's RANK/WORLD_SIZE or a SLURM array's
    SLURM_ARRAY_TASK_ID/SLURM_ARRAY_TASK_COUNT when set, else all frames."""

    def validate(self) -> None:
        self.resolved()

    def resolved(self, env=None) -> Shard:
        return resolve_shard(self.shard, env)


@dataclass(frozen=True)
class Shard:
    index: int = 0
    count: int = 1

    def __post_init__(self):
        if not (self.count >= 1 and 0 <= self.index < self.count):
            raise GraMiParameterError("shard", f"expected I/N with 0 <= I < N, got {self.index}/{self.count}")

    @property
    def whole(self) -> bool:
        return self.count == 1

    def take(self, items: list) -> list:
        """This shard's part of ``items`` (every N-th, from I)."""
        return list(items)[self.index :: self.count]

    @property
    def lock_suffix(self) -> str:
        """What a shard adds to a folder's lock name: two processes of one shard collide, two shards do not."""
        return "" if self.whole else f".shard-{self.index}-of-{self.count}"

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text: str) -> Shard:
    """``I/N`` → :class:`Shard`."""
    match = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
    if not match:
        raise GraMiParameterError("shard", f"expected I/N (this process's index and the number of shards, e.g. 0/4), got '{text}'")
    return Shard(int(match.group(1)), int(match.group(2)))


def int_variable(env, name: str) -> int:
    """A launcher's integer variable; one that is not an integer names itself."""
    try:
        return int(env[name])
    except ValueError:
        raise GraMiInputError(f"${name}", f"expected an integer, got '{env[name]}'") from None


def shard_from_environment(env=None) -> Shard | None:
    """The shard a launcher's variables give (torchrun, SLURM arrays), or None outside one."""
    env = os.environ if env is None else env
    for index_name, count_name, first_name in (
        ("RANK", "WORLD_SIZE", None),
        ("SLURM_ARRAY_TASK_ID", "SLURM_ARRAY_TASK_COUNT", "SLURM_ARRAY_TASK_MIN"),
    ):
        if index_name not in env:
            continue
        if count_name not in env:
            raise GraMiInputError(f"${index_name}", f"is set but ${count_name} is not: a launcher gives both (or pass --shard I/N)")
        first = int_variable(env, first_name) if first_name and first_name in env else 0
        index, count = int_variable(env, index_name) - first, int_variable(env, count_name)
        if not (count >= 1 and 0 <= index < count):
            raise GraMiInputError(f"${index_name}", f"{index_name}={env[index_name]} is not a shard of {count_name}={count}")
        return Shard(index, count)
    return None


_ANNOUNCED: set[Shard] = set()
SHARDS_RECORD = ".gra-mi.shards"  # an output folder's shard count, where no provenance records it


def resolve_shard(option: str | None, env=None) -> Shard:
    """``--shard`` if given, else the launcher's (said on stderr, once: a job array's task that silently did only its
    share would look like a whole run), else the whole job."""
    if option is not None:
        return parse_shard(option)
    shard = shard_from_environment(env)
    if shard is None:
        return Shard()
    if not shard.whole and shard not in _ANNOUNCED:
        _ANNOUNCED.add(shard)
        print(
            f"gra-mi: shard {shard} from the launcher's variables: this process does only its share of the frames "
            "(--shard 0/1 does all of them)",
            file=sys.stderr,
            flush=True,
        )
    return shard


def record_shard_count(folder, shard: Shard) -> None:
    """Refuse a folder that shards of another count are writing (their frames would overlap and miss), else record
    this count. A whole run may always write a folder (it does every frame)."""
    from pathlib import Path

    from gra_mi.core.io import atomic_write_text

    if shard.whole:
        return
    path = Path(folder) / SHARDS_RECORD
    if path.is_file():
        old = path.read_text().strip()
        if old != str(shard.count):
            raise GraMiInputError(folder, f"is being written by {old} shards; this process is shard {shard}: use --shard I/{old}")
        return
    atomic_write_text(path, f"{shard.count}\n")


def free_port() -> int:
    """A TCP port nothing listens on now (torchrun's rendezvous, a viewer under test): fixed ports collide when runs
    overlap."""
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]
