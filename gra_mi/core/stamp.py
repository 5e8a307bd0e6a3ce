"""What a measurement was made with: the commit, the machine, the date. Every generated results table carries one
(docs/results/README.md), so a number can be traced to the code and hardware that produced it."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[2]


def _git(*args: str) -> str | None:
    try:
        done = subprocess.run(["git", *args], cwd=REPOSITORY, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def run_stamp(**extra) -> dict:
    """{commit (+ "-dirty" with uncommitted changes; outside a git checkout: ``GRA_MI_COMMIT`` as the copy's sender
    said it, else None), machine, date} and ``extra`` (the preset, the Mitsuba variant…)."""
    commit = _git("rev-parse", "--short", "HEAD")
    if commit is not None and _git("status", "--porcelain", "--untracked-files=no"):
        commit += "-dirty"
    elif commit is None and os.environ.get("GRA_MI_COMMIT"):
        commit = f"{os.environ['GRA_MI_COMMIT']} (said, no .git)"
    cpu = platform.processor() or platform.machine()
    machine = f"{os.cpu_count()}-core {cpu} ({platform.system()})"
    return {"commit": commit, "machine": machine, "date": datetime.date.today().isoformat(), **extra}


def stamp_said(stamp: dict) -> str:
    """One line: ``commit abc1234, preset small, 2-core x86_64 (Linux), llvm_ad_rgb, 2026-12-02``."""
    parts = [f"commit {stamp.get('commit') or 'unknown'}"]
    parts += [f"{key} {stamp[key]}" for key in ("preset",) if key in stamp]
    parts += [str(stamp[key]) for key in ("machine", "variant", "date") if stamp.get(key)]
    return ", ".join(parts)


def publish_page(page: str, path=None) -> None:
    """A benchmark's Markdown page: printed, and written to ``path`` (docs/results/…) when given."""
    import sys
    from pathlib import Path

    print(page)
    if path is not None:
        Path(path).write_text(page)
        print(f"wrote {path}", file=sys.stderr)
