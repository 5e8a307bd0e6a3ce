"""Progress bars for long work (rich), quiet when stderr is not a terminal or GRA_MI_QUIET is set."""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def progress(items: Iterable[T], description: str, total: int | None = None) -> Iterator[T]:
    """Iterate with a progress bar on stderr."""
    if os.environ.get("GRA_MI_QUIET") or not sys.stderr.isatty():
        yield from items
        return
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn())
    with Progress(*columns, transient=False) as bar:
        if total is None and hasattr(items, "__len__"):
            total = len(items)  # type: ignore[arg-type]
        task = bar.add_task(description, total=total)
        for item in items:
            yield item
            bar.advance(task)


MAX_THREADS = 8  # for work that releases the GIL: more rarely helps, and each thread holds its item's arrays


def thread_count(limit: int | None = None) -> int:
    """One thread per core, at most :data:`MAX_THREADS` and ``limit`` (e.g. what memory holds)."""
    return max(1, min(os.cpu_count() or 1, MAX_THREADS, MAX_THREADS if limit is None else limit))


def threaded(work: Callable[[T], R], items: list[T], description: str, workers: int | None = None) -> Iterator[R]:
    """``work`` of each item on ``workers`` threads (default :func:`thread_count`; for work that releases the GIL:
    decoding, compression, NumPy), the results in the items' order with a progress bar. A failure stops what has not
    started: it is raised when its item's turn comes, without waiting for the rest of a long list."""
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(thread_count() if workers is None else max(1, workers))
    try:
        yield from progress(pool.map(work, items), description, len(items))
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
