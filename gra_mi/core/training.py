"""What every training command shares: joining a ``torchrun`` process group, and the training log (CSV + plot)."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import torch

from gra_mi.core.io import atomic_path


def init_distributed() -> tuple[int, int]:
    """(rank, world size); joins the process group under ``torchrun`` (gloo on CPU, NCCL on GPU)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        torch.distributed.init_process_group(backend)
    rank = torch.distributed.get_rank() if world > 1 else 0
    return rank, world


def write_training_log(out: Path, header: list[str], rows: list, title: str, ylabel: str) -> None:
    """``train_log.csv`` (columns ``header``) and ``loss.png`` (column 2 against column 1, log scale)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

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
    with atomic_path(out / "loss.png") as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
