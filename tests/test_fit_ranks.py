"""One material fit over several processes (torchrun): the same maps as one process, one folder, resumable."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.shard import free_port

from .test_cli import run_cli


def fit_on_processes(processes: int, capture, out, *options: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "GRA_MI_QUIET": "1", "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", str(processes), "--master_port", str(free_port()),
        "-m", "gra_mi.cli", "fit", str(capture), "--out", str(out), *options,
    ]  # fmt: skip
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)


def maps(folder) -> dict[str, np.ndarray]:
    from gra_mi.core.io import read_exr

    return {name: read_exr(folder / f"{name}.exr") for name in ("albedo", "roughness")}


CASES = [
    pytest.param(("--iterations", "20"), id="every-view-each-step"),
    pytest.param(("--batch-views", "3", "--iterations", "16"), id="streamed-minibatches", marks=pytest.mark.slow),
    pytest.param(("--levels", "16,32", "--iterations", "10", "--bounces", "2"), id="levels-two-bounces", marks=pytest.mark.slow),
]


@pytest.mark.parametrize("options", CASES)
def test_a_fit_over_two_processes_equals_the_one_process_fit(onebounce_capture, tmp_path, options):
    """Every sum over views (closed form, evidence, calibration, each Adam step's gradient) crosses the processes, so
    the maps are the one-process fit's up to the order of float additions, and the folder is the same: every view
    scored in fit.json in the same order, no process's scratch left, the report saying how it was fitted."""
    from gra_mi.fit.materials import RUN_TO_RUN

    run_cli("fit", str(onebounce_capture), "--out", str(tmp_path / "one"), *options)
    two = fit_on_processes(2, onebounce_capture, tmp_path / "two", *options)
    assert two.returncode == 0, two.stderr[-3000:]
    assert two.stdout.count("done: open") == 1, "rank 0 alone reports"
    one_maps, two_maps = maps(tmp_path / "one"), maps(tmp_path / "two")
    for name in one_maps:
        assert np.abs(one_maps[name] - two_maps[name]).max() < RUN_TO_RUN, name
    one, two_record = (json.loads((tmp_path / f / "fit.json").read_text()) for f in ("one", "two"))
    assert two_record["processes"] == 2 and one["processes"] == 1
    assert list(two_record["per_view_l1"]) == list(one["per_view_l1"])
    assert np.allclose(list(two_record["per_view_l1"].values()), list(one["per_view_l1"].values()), rtol=1e-3)
    assert two_record["capture"] == one["capture"]
    assert not list((tmp_path / "two").glob("views*.tmp")), "scratch views removed"
    assert "Fitted by 2 processes" in (tmp_path / "two" / "fit_report.md").read_text()


def test_a_two_process_fit_folder_is_resumed_by_one_process_and_overwritten_by_two(onebounce_capture, tmp_path):
    """The checkpoints hold the whole fit, not a process's share: one process resumes it (nothing left to do, the same
    maps); --overwrite under torchrun empties the folder before any process writes into it."""
    out = tmp_path / "fit"
    first = fit_on_processes(2, onebounce_capture, out, "--iterations", "6")
    assert first.returncode == 0, first.stderr[-3000:]
    before = maps(out)
    run_cli("fit", str(onebounce_capture), "--out", str(out), "--iterations", "6")
    assert all(np.allclose(before[k], v, atol=1e-6) for k, v in maps(out).items()), "a finished fit, resumed, is unchanged"
    again = fit_on_processes(2, onebounce_capture, out, "--iterations", "4", "--overwrite")
    assert again.returncode == 0, again.stderr[-3000:]
    assert json.loads((out / "fit.json").read_text())["config"]["iterations"] == 4


def test_more_processes_than_frames_are_refused(onebounce_capture, tmp_path):
    from gra_mi.fit.ranks import FitRanks

    with pytest.raises(GraMiParameterError, match="2 training frames and 3 processes"):
        FitRanks(rank=2, world=3).take(["frame 0", "frame 1"])
    assert FitRanks(rank=1, world=2).take(list(range(5))) == [1, 3], "every N-th frame from the rank, as --shard takes"
    refused = fit_on_processes(3, onebounce_capture, tmp_path / "fit", "--frame-step", "4", "--iterations", "2")
    assert refused.returncode != 0 and "start at most as many processes as frames" in refused.stderr
    assert not (tmp_path / "fit").exists(), "the claimed folder is removed again"


def _ranks_worker(rank: int, port: int, results) -> None:
    """Process ``rank`` of 2: what each reduction of FitRanks gives it."""
    os.environ |= {"RANK": str(rank), "WORLD_SIZE": "2", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}
    from gra_mi.fit.ranks import FitRanks

    ranks = FitRanks.from_launcher()
    said = {
        "sum": ranks.sum(np.array([1.0, 2.0]) * (rank + 1)).tolist(),
        "merged": ranks.merged({f"view {rank}": rank}),
        "from_main": ranks.from_main(np.full(2, 10.0 + rank)).tolist(),
    }
    ranks.agree("same", "a value all share")
    try:
        ranks.agree(rank, "where to resume")
    except GraMiInputError as exc:
        said["refused"] = str(exc)
    ranks.close()
    results.put((rank, said))


def test_the_reductions_across_two_processes():
    import torch.multiprocessing as mp

    results = mp.get_context("spawn").SimpleQueue()
    mp.spawn(_ranks_worker, args=(free_port(), results), nprocs=2, join=True)
    said = dict(results.get() for _ in range(2))
    for rank in (0, 1):
        assert said[rank]["sum"] == [3.0, 6.0]
        assert said[rank]["merged"] == {"view 0": 0, "view 1": 1}
        assert said[rank]["from_main"] == [10.0, 10.0]
        assert "process 0: 0, process 1: 1" in said[rank]["refused"] and "share the output folder" in said[rank]["refused"]


def test_a_launcher_variable_that_is_not_a_number_is_named(monkeypatch):
    from gra_mi.fit.ranks import FitRanks

    monkeypatch.setenv("WORLD_SIZE", "two")
    with pytest.raises(GraMiInputError, match="WORLD_SIZE: expected an integer, got 'two'"):
        FitRanks.from_launcher()
    monkeypatch.setenv("WORLD_SIZE", "1")
    assert FitRanks.from_launcher().single
