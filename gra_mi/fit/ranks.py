"""One material fit over several processes (``torchrun --nproc_per_node N -m gra_mi.cli fit …``): data parallel.

The maps are one shared state, so a fit cannot be split into independent shards as per-frame commands are. Instead
every process holds the whole maps and works on its share of the training frames (every N-th, as ``--shard`` splits
them: their observations, footprints and LED loops, and the visibility of their poses), and every quantity that sums
over views is summed over the processes before it is used: the closed form's per-texel sums, the evidence, the
brightness calibration's totals, and at each Adam step the data term and its gradient. Every process then takes the
same step, so the maps stay identical (re-synchronised from rank 0 at each checkpoint); rank 0 writes the
checkpoints and outputs.

Sums cross processes in float64 through ``torch.distributed``, on a gloo group of the fit's own (CPU tensors, also
beside a GPU run's NCCL group). A fit over N processes equals the one-process fit up to the order of float additions
(within :data:`~gra_mi.fit.materials.RUN_TO_RUN`).
"""

from __future__ import annotations

import os
from datetime import timedelta

import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.shard import int_variable

WAIT = timedelta(hours=12)
"""How long a process waits at a sum for the others (shares of frames differ in cost; a process that fails stops the
others through torchrun, not through this)."""


class FitRanks:
    """This process's place among the fit's processes (one process: rank 0 of 1, every reduction the identity)."""

    def __init__(self, rank: int = 0, world: int = 1, group=None):
        self.rank, self.world, self.group = rank, world, group

    @classmethod
    def from_launcher(cls) -> FitRanks:
        """The processes torchrun started (``WORLD_SIZE`` > 1: joins the process group), else one."""
        if "WORLD_SIZE" not in os.environ or int_variable(os.environ, "WORLD_SIZE") <= 1:
            return cls()
        import torch.distributed as dist

        from gra_mi.core.training import init_distributed

        rank, world = init_distributed()
        if rank:
            os.environ["GRA_MI_QUIET"] = "1"  # one set of progress bars: rank 0's
        return cls(rank, world, dist.new_group(backend="gloo", timeout=WAIT))

    @property
    def main(self) -> bool:
        """Whether this process writes the fit's files."""
        return self.rank == 0

    @property
    def single(self) -> bool:
        return self.world == 1

    def take(self, frames: list) -> list:
        """This process's share of the training frames (every N-th from its rank); refuses more processes than frames."""
        if len(frames) < self.world:
            raise GraMiParameterError(
                "nproc_per_node", f"the fit has {len(frames)} training frames and {self.world} processes: each process fits "
                "whole frames, so start at most as many processes as frames"
            )  # fmt: skip
        return list(frames)[self.rank :: self.world]

    def sum(self, array) -> np.ndarray:
        """The element-wise float64 sum of ``array`` over the processes."""
        values = np.asarray(array, np.float64)
        if self.single:
            return values
        import torch
        import torch.distributed as dist

        tensor = torch.from_numpy(np.ascontiguousarray(values).copy())
        dist.all_reduce(tensor, group=self.group)
        return tensor.numpy()

    def total(self, value: float) -> float:
        return float(self.sum(np.array([value]))[0])

    def merged(self, items: dict) -> dict:
        """The union of every process's ``items`` (keys are distinct across processes: a view belongs to one)."""
        if self.single:
            return dict(items)
        import torch.distributed as dist

        parts: list = [None] * self.world
        dist.all_gather_object(parts, items, group=self.group)
        return {key: value for part in parts for key, value in part.items()}

    def from_main(self, array: np.ndarray) -> np.ndarray:
        """Rank 0's ``array`` on every process (the maps, re-synchronised: processes on different devices may round
        differently)."""
        if self.single:
            return array
        import torch
        import torch.distributed as dist

        tensor = torch.from_numpy(np.ascontiguousarray(array).copy())
        dist.broadcast(tensor, src=0, group=self.group)
        return tensor.numpy()

    def agree(self, value, what: str) -> None:
        """Refuse to go on unless every process has the same ``value`` (where it resumes from: processes that read
        different checkpoints would take different steps and wait for each other for ever)."""
        if self.single:
            return
        import torch.distributed as dist

        values: list = [None] * self.world
        dist.all_gather_object(values, value, group=self.group)
        if any(v != values[0] for v in values):
            said = ", ".join(f"process {rank}: {v}" for rank, v in enumerate(values))
            raise GraMiInputError(what, f"the fit's processes disagree ({said}): they must share the output folder (one file system)")

    def barrier(self) -> None:
        if not self.single:
            import torch.distributed as dist

            dist.barrier(group=self.group)

    def close(self) -> None:
        """Leave the fit's group and the process group once every process is here (before rank 0 writes the outputs
        alone)."""
        if not self.single:
            from gra_mi.core.training import leave_distributed

            leave_distributed(self.group)
