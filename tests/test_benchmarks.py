"""Every script in benchmarks/ runs through the one harness (gra_mi/apps/harness.py): its arguments, timing and
stamped page; none changes ``sys.path`` or parses its own arguments."""

from __future__ import annotations

import ast
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gra_mi.apps.harness import run_benchmark, side_by_side, table_page, timed

BENCHMARKS = sorted((Path(__file__).resolve().parent.parent / "benchmarks").glob("*.py"))


def calls_in(tree: ast.AST) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            names.add(f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", ""))
    return names


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda p: p.stem)
def test_every_benchmark_runs_through_the_harness(script):
    text = script.read_text()
    tree = ast.parse(text)
    assert "run_benchmark" in calls_in(tree), f"{script.name}: publish through gra_mi.apps.harness.run_benchmark"
    assert "sys.path" not in text, f"{script.name}: gra-mi is installed; shared helpers live in gra_mi"
    assert "ArgumentParser" not in calls_in(tree), f"{script.name}: give the harness an arguments() function"
    assert "from benchmarks" not in text and "from tests" not in text, f"{script.name}: shared scenes live in gra_mi"


def test_every_benchmark_explains_its_options():
    for script in BENCHMARKS:
        done = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, f"{script.name}: {done.stderr[-1500:]}"
        assert "--write" in done.stdout and "--work" in done.stdout, script.name


def test_the_harness_publishes_a_stamped_page_and_cleans_its_work(tmp_path):
    seen = {}

    def measure(run):
        seen["work"] = run.work
        (run.work / "scratch.txt").write_text("x")
        return f"# A page\n\nGenerated ({run.stamp('test preset')}): {run.args.size}\n"

    page = tmp_path / "page.md"
    run_benchmark("doc", measure, arguments=lambda p: p.add_argument("--size", type=int, default=3), argv=["--write", str(page)])
    text = page.read_text()
    assert "test preset" in text and "commit" in text and text.rstrip().endswith(": 3")
    assert not seen["work"].exists(), "a temporary work folder is removed after the run"
    kept = tmp_path / "kept"
    run_benchmark(
        "doc", measure, arguments=lambda p: p.add_argument("--size", type=int), mitsuba=False, argv=["--work", str(kept), "--size", "5"]
    )
    assert (kept / "scratch.txt").is_file(), "--work keeps what the benchmark wrote"


def test_side_by_side_alternates_and_times_each_call():
    order = []
    slow = lambda: (order.append("slow"), time.sleep(0.02))  # noqa: E731
    fast = lambda: order.append("fast")  # noqa: E731
    medians = side_by_side({"slow": slow, "fast": fast}, repeats=3)
    assert order == ["slow", "fast"] * 4, "one untimed call each, then the calls alternated"
    assert medians["slow"] >= 0.02 > medians["fast"]
    seconds, value = timed(lambda: 7, repeats=2, warmup=True)
    assert value == 7 and seconds >= 0


def test_a_table_page_is_markdown_a_reader_sees_as_a_table():
    page = table_page("Speed", "x.py", "commit abc", [("a", "1 ms", ""), ("b", 2, "goal")], ["one note", "another"])
    lines = page.splitlines()
    assert lines[0] == "# Speed" and "`benchmarks/x.py` (commit abc)" in lines[2]
    assert lines[4] == "one note" and lines[5] == "" and lines[6] == "another"
    assert lines[-3:] == ["|---|---|---|", "| a | 1 ms |  |", "| b | 2 | goal |"]


def test_a_measured_command_reports_its_own_peak_memory_not_its_parents():
    import numpy as np

    from gra_mi.apps.harness import run_measured

    held = np.ones(300 << 20, np.uint8)  # this process: 300 MB more than the commands it starts
    small = run_measured([sys.executable, "-c", "print('hi')"])
    large = run_measured([sys.executable, "-c", "import numpy as np; a = np.ones(200 << 20, np.uint8); print(int(a.sum()))"])
    assert held.sum() == 300 << 20
    assert small["stdout"] == "hi\n" and small["peak_mb"] < 100, small
    assert large["stdout"].strip() == str(200 << 20) and 200 <= large["peak_mb"] < 300, large
    with pytest.raises(RuntimeError, match="boom"):
        run_measured([sys.executable, "-c", "import sys; sys.exit('boom')"])
