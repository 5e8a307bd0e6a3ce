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


def _int_variable(env, name: str) -> int:
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
        first = _int_variable(env, first_name) if first_name and first_name in env else 0
        index, count = _int_variable(env, index_name) - first, _int_variable(env, count_name)
        if not (count >= 1 and 0 <= index < count):
            raise GraMiInputError(f"${index_name}", f"{index_name}={env[index_name]} is not a shard of {count_name}={count}")
        return Shard(index, count)
    return None


def resolve_shard(option: str | None, env=None) -> Shard:
    """``--shard`` if given, else the launcher's, else the whole job."""
    if option is not None:
        return parse_shard(option)
    return shard_from_environment(env) or Shard()
