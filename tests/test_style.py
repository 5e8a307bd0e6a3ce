"""The house rules (STYLE.md, issue 55) held by the suite, not by memory: ruff's lint and format over every Python
tree, no module in gra_mi/ over 600 lines, no function over 80."""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
TREES = ["gra_mi", "tests", "benchmarks", "scripts"]
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _ruff() -> str:
    beside = Path(sys.executable).with_name("ruff")  # the environment's own (pinned in pyproject's dev extras)
    found = str(beside) if beside.is_file() else shutil.which("ruff")
    if found is None:
        pytest.skip("ruff is not installed (pip install -e '.[dev]')")
    return found


@pytest.mark.parametrize("command", [["check"], ["format", "--check"]], ids=["lint", "format"])
def test_ruff_passes(command):
    done = subprocess.run([_ruff(), *command, *TREES], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"ruff {' '.join(command)}:\n{done.stdout[-4000:]}{done.stderr[-2000:]}"


def test_modules_and_functions_stay_short():
    too_long = []
    for path in sorted((REPO / "gra_mi").rglob("*.py")):
        text = path.read_text()
        name = path.relative_to(REPO)
        if len(text.splitlines()) > MAX_MODULE_LINES:
            too_long.append(f"{name}: {len(text.splitlines())} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text, str(path))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                too_long.append(
                    f"{name}:{node.lineno} {node.name}: {node.end_lineno - node.lineno + 1} lines (at most {MAX_FUNCTION_LINES})"
                )
    assert not too_long, "\n".join(too_long)
