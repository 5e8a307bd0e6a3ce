"""What every training command shares: the loop skeleton (``torchrun`` processes, resume, DDP, checkpoints, progress,
log) and the training log (CSV + plot). The stages (RelightNet, the refiner) supply only their step."""

from __future__ import annotations

import csv
import logging
import math
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import torch

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path, pyplot, save_figure
from gra_mi.core.progress import progress
from gra_mi.core.provenance import claim_output

logger = logging.getLogger(__name__)


TRAINING_CADENCE = ("steps", "checkpoint_every", "log_every", "validate_every")
"""Config fields a resumed training run may change: more steps continue it, cadence does not change the weights."""


def init_distributed() -> tuple[int, int]:
    """(rank, world size); joins the process group under ``torchrun`` (gloo on CPU, NCCL on GPU)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        torch.distributed.init_process_group(backend)
    rank = torch.distributed.get_rank() if world > 1 else 0
    return rank, world


def leave_distributed(*groups) -> None:
    """Once every process is here, leave ``groups`` and the ``torchrun`` process group (nothing outside torchrun): a
    process that exits holding gloo's connections can abort at interpreter exit ("terminate called without an active
    exception") while another process still reads them."""
    if not torch.distributed.is_initialized():
        return
    torch.distributed.barrier()
    for group in groups:
        torch.distributed.destroy_process_group(group)
    torch.distributed.destroy_process_group()


def write_training_log(out: Path, header: list[str], rows: list, title: str, ylabel: str) -> None:
    """``train_log.csv`` (columns ``header``) and ``loss.png`` (column 2 against column 1, log scale)."""

    plt = pyplot()
    with atomic_path(out / "train_log.csv") as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        writer.writerows(rows)
    if not rows:
        return
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([r[0] for r in rows], [r[1] for r in rows])
    ax.set_xlabel(header[0])
    ax.set_ylabel(ylabel)
    ax.set_yscale("log")
    ax.set_title(title)
    fig.tight_layout()
    save_figure(fig, out / "loss.png")


class TrainingLoop:
    """The skeleton every training command shares; the stage writes only its step.

    - joins the ``torchrun`` process group (:func:`init_distributed`); ``parallel`` wraps a model in DDP when needed;
    - ``resume`` reads ``OUT/checkpoint.pt`` (the step and the log, plus whatever the stage saved) so a rerun carries on;
    - ``steps`` yields the remaining step indices (a progress bar on rank 0); after each step it appends the mean of the
      losses given to ``add_loss`` to the log every ``log_every`` steps and, on rank 0, writes a checkpoint every
      ``checkpoint_every`` steps (atomic) from ``state_of()``;
    - ``diverged`` says, on every process alike, whether a loss or score has become non-finite: the stage stops there
      and keeps its last finite weights; ``divergence`` records the step and what went non-finite (checkpoint too);
    - ``finish`` writes the last checkpoint, waits for every process and says whether this one should write outputs.
    """

    def __init__(self, out: Path, total_steps: int, checkpoint_every: int, log_every: int, description: str):
        self.rank, self.world = init_distributed()
        self.out, self.checkpoint = Path(out), Path(out) / "checkpoint.pt"
        self.total_steps, self.checkpoint_every, self.log_every = total_steps, checkpoint_every, log_every
        self.description = description
        self.start = 0
        self.log_rows: list[tuple] = []
        self._losses: list[float] = []
        self._state_of = dict
        self._row_extra = tuple
        self._t0 = time.perf_counter()
        self.divergence: dict | None = None

    def claim(self, command: str, inputs: dict, config, overwrite: bool = False) -> None:
        """Check and record what makes ``out`` (:func:`gra_mi.core.provenance.claim_output`; the step count and
        logging cadence may change on a resume) before any rank reads a checkpoint from it."""

        if self.rank == 0:
            claim_output(self.out, command, inputs, config, overwrite=overwrite, free=TRAINING_CADENCE)
        if self.world > 1:
            torch.distributed.barrier()

    def resume(self, map_location) -> dict | None:
        """The saved state, or None on a fresh start."""
        if not self.checkpoint.is_file():
            return None
        try:
            state = torch.load(self.checkpoint, map_location=map_location, weights_only=False)
        except Exception as exc:  # truncated by a full disk or a copy cut short
            raise GraMiInputError(
                self.checkpoint, f"unreadable checkpoint ({str(exc)[:120]}); rerun with --overwrite to start over"
            ) from None
        self.start, self.log_rows = state["step"], state["log"]
        self.divergence = state.get("divergence")
        if self.divergence is not None and self.start < self.total_steps:
            raise GraMiInputError(
                self.checkpoint,
                f"this run diverged at step {self.divergence['step']} ({self.divergence['what']}) and cannot be continued; "
                "rerun with --overwrite (and a lower --lr)",
            )
        logger.info("%s: resuming from step %d", self.description, self.start)
        return state

    def parallel(self, model: torch.nn.Module) -> torch.nn.Module:
        return torch.nn.parallel.DistributedDataParallel(model) if self.world > 1 else model

    def add_loss(self, value: float) -> None:
        self._losses.append(value)

    def mark_diverged(self, step: int, what: str) -> None:
        """Record (once) that ``what`` became non-finite at ``step``; on rank 0 alone (validation) the next
        :meth:`diverged` call tells every process."""
        if self.divergence is None:
            self.divergence = {"step": int(step), "what": what}
            logger.warning(
                "%s diverged at step %d: %s is not finite; training stops there and keeps its last finite weights "
                "(lower --lr)", self.description, step, what,
            )  # fmt: skip

    def diverged(self, step: int, value: float, what: str = "the training loss") -> bool:
        """Whether ``value`` (this process's loss) or any other process's is non-finite, or a divergence was marked:
        the same answer on every process, so that all of them stop at the same step."""
        bad = not math.isfinite(value) or self.divergence is not None
        if self.world > 1:
            device = "cuda" if torch.distributed.get_backend() == "nccl" else "cpu"
            flag = torch.tensor([float(bad)], device=device)
            torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
            if flag.item() > 0 and not bad:
                what = "the training loss of another process"
            bad = bool(flag.item() > 0)
        if bad:
            self.mark_diverged(step, what)
        return bad

    def steps(self, state_of: Callable[[], dict], row_extra: Callable[[], tuple] = tuple) -> Iterator[int]:
        """Step indices from the resumed one on; ``state_of()`` is what a checkpoint holds besides step and log,
        ``row_extra()`` what a log row holds after (step, mean loss, seconds)."""

        self._state_of, self._row_extra = state_of, row_extra
        self._t0 = time.perf_counter()  # the log's seconds count training only
        remaining = range(self.start, self.total_steps)
        for step in progress(remaining, description=self.description) if self.rank == 0 else remaining:
            yield step
            done = step + 1
            if done % self.log_every == 0 or done == self.total_steps:
                self.log_rows.append((done, float(np.mean(self._losses)), time.perf_counter() - self._t0, *self._row_extra()))
                self._losses = []
            if done % self.checkpoint_every == 0:
                self.save_checkpoint(done)

    def save_checkpoint(self, step: int) -> None:
        if self.rank != 0:
            return
        with atomic_path(self.checkpoint) as tmp:
            torch.save({**self._state_of(), "step": step, "log": self.log_rows, "divergence": self.divergence}, tmp)

    def finish(self) -> bool:
        """Last checkpoint, then every process leaves the process group; True on the process that writes the outputs
        (rank 0)."""
        self.save_checkpoint(self.total_steps)
        leave_distributed()
        return self.rank == 0
