"""Per-frame work sharded over processes: `--shard I/N` and the launchers' variables; shards write what one process
writes, byte for byte; per-shard locks; a folder keeps the shard count it was started with."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.provenance import different_outputs
from gra_mi.core.shard import Shard, parse_shard, resolve_shard, shard_from_environment

from .conftest import SCENES
from .test_cli import run_cli
from .test_presets import shrunk

TINY = SCENES / "tiny_lightstage.xml"


def test_shards_from_the_option_and_the_launchers():
    assert parse_shard("1/4") == Shard(1, 4) and Shard(1, 4).take(list(range(10))) == [1, 5, 9]
    assert resolve_shard(None, {}) == Shard() and resolve_shard(None, {}).whole
    assert shard_from_environment({"RANK": "2", "WORLD_SIZE": "3"}) == Shard(2, 3)
    slurm = {"SLURM_ARRAY_TASK_ID": "4", "SLURM_ARRAY_TASK_COUNT": "4", "SLURM_ARRAY_TASK_MIN": "1"}  # --array=1-4
    assert shard_from_environment(slurm) == Shard(3, 4)
    assert resolve_shard("0/2", {"RANK": "1", "WORLD_SIZE": "2"}) == Shard(0, 2), "the option wins"
    for text in ("3/2", "0/0", "a/b", "1", "-1/2"):
        with pytest.raises(GraMiInputError, match="shard"):
            parse_shard(text)
    for env, named in (({"RANK": "1"}, "$RANK"), ({"RANK": "x", "WORLD_SIZE": "2"}, "$RANK"), ({"RANK": "5", "WORLD_SIZE": "2"}, "$RANK")):
        with pytest.raises(GraMiInputError) as info:
            shard_from_environment(env)
        assert named in str(info.value)


def test_two_relight_shards_write_what_one_process_writes(tmp_path, llvm_variant):
    """Every EXR, PNG, conditioning and MP4 byte for byte: the previews' exposure comes from the selection's first
    frame whoever renders it, and the videos are made by the shard that finds every frame done."""
    from gra_mi.apps.relight import RelightConfig, collect_lights, relight_batch
    from gra_mi.render.light_path import LightPath
    from gra_mi.stage.envmap_library import reference_map
    from gra_mi.stage.scene import LightstageScene

    (tmp_path / "path.json").write_text(
        json.dumps({"lights": [{"keyframes": [{"frame": 0, "position": [0.6, 1.2, 0.4]}, {"frame": 4, "position": [-0.6, 1.2, 0.4]}]}]})
    )
    ls = LightstageScene.load(TINY)

    def relight(out: Path, shard: Shard | None) -> None:
        lights = collect_lights(ls.stage, {"sun": reference_map("sun", 16)}, [3], {}, paths=[LightPath.load(tmp_path / "path.json")])
        relight_batch(
            ls, out, lights, frames=list(range(5)), cameras=["cam00", "cam02"], config=RelightConfig(uv_resolution=32), shard=shard
        )

    relight(tmp_path / "one", None)
    relight(tmp_path / "two", Shard(1, 2))  # the shard without the first frame runs first
    assert not (tmp_path / "two" / "sun" / "cam00.mp4").exists(), "no video before every frame is there"
    relight(tmp_path / "two", Shard(0, 2))
    assert (tmp_path / "two" / "sun" / "cam00.mp4").is_file()
    assert different_outputs(tmp_path / "one", tmp_path / "two") == []


def test_two_capture_shards_write_what_one_process_writes(tmp_path, monkeypatch, llvm_variant):
    import fcntl

    from gra_mi.capture import synthetic
    from gra_mi.core.provenance import LOCK, PROVENANCE, release_folder

    monkeypatch.setitem(synthetic.PRESETS, "tiny", shrunk(synthetic.PRESETS["tiny"]))
    config = synthetic.CaptureConfig(preset="tiny", measure_noise=False)
    synthetic.generate_capture(tmp_path / "one", config)
    for index in (1, 0):
        synthetic.generate_capture(tmp_path / "two", config, shard=Shard(index, 2))
    release_folder(tmp_path / "two")
    assert different_outputs(tmp_path / "one", tmp_path / "two") == []  # provenance records the 2 shards: bookkeeping
    assert json.loads((tmp_path / "two" / PROVENANCE).read_text())["config"]["shards"] == 2
    # A folder started with 2 shards refuses 3; a shard whose lock another process holds is refused with its pid.
    with pytest.raises(GraMiInputError, match="shards: 2 then, 3 now"):
        synthetic.generate_capture(tmp_path / "two", config, shard=Shard(0, 3))
    with open(tmp_path / "two" / f"{LOCK}.shard-1-of-2", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        held.write("4242")
        held.flush()
        with pytest.raises(GraMiInputError, match="pid 4242.*shard 1/2"):
            synthetic.generate_capture(tmp_path / "two", config, shard=Shard(1, 2))


@pytest.mark.parametrize(
    "args, said",
    [
        (["relight", str(TINY), "--olat", "1", "--shard", "3/2"], "--shard"),
        (["relight", str(TINY), "--olat", "1", "--shard", "x"], "--shard"),
        (["capture", "--preset", "tiny", "--shard", "0/2", "--overwrite"], "--overwrite"),
        (["refiner-data", "--synthetic", "--shard", "0/2"], "--shard"),
        (["import", "humanolat", "nowhere", "--shard", "2/2"], "--shard"),
        (["eval-lighting", "nowhere", "--fit", "nowhere", "--shard", "0/0"], "--shard"),
    ],
)
def test_bad_shards_on_the_command_line(tmp_path, args, said):
    out = run_cli(*args, "--out", str(tmp_path / "out"))
    assert out.returncode == 2 and said in out.stderr and "Traceback" not in out.stderr, out.stderr


def test_each_local_rank_takes_its_own_gpu():
    # torchrun's LOCAL_RANK (or srun's SLURM_LOCALID) picks this process's GPU before CUDA starts; a launcher that
    # already gave each process one GPU is left alone; no launcher or no GPU: nothing changes.
    from gra_mi.core.runtime import bind_local_gpu

    env = {"LOCAL_RANK": "2"}
    assert bind_local_gpu(env, gpus=4) == "2" and env["CUDA_VISIBLE_DEVICES"] == "2"
    env = {"SLURM_LOCALID": "1", "CUDA_VISIBLE_DEVICES": "4,5,6"}
    assert bind_local_gpu(env) == "5" and env["CUDA_VISIBLE_DEVICES"] == "5"
    env = {"LOCAL_RANK": "0", "CUDA_VISIBLE_DEVICES": "3"}
    assert bind_local_gpu(env) == "3" and env["CUDA_VISIBLE_DEVICES"] == "3"
    env = {"LOCAL_RANK": "5"}
    assert bind_local_gpu(env, gpus=4) == "1", "more ranks than GPUs share them round-robin"
    assert bind_local_gpu({"LOCAL_RANK": "1"}, gpus=0) is None
    assert bind_local_gpu({}, gpus=4) is None
    with pytest.raises(GraMiInputError, match="LOCAL_RANK"):
        bind_local_gpu({"LOCAL_RANK": "x"}, gpus=2)


def test_an_interrupted_relight_resumes_to_what_one_run_writes(tmp_path, monkeypatch, llvm_variant, capsys):
    """`gra-mi relight` into its own folder again resumes: the views on disk are not rendered again, and the folder
    ends as an uninterrupted run's, byte for byte (previews exposed from the first frame whichever run renders it)."""
    from gra_mi.apps import relight
    from gra_mi.cli import main

    args = [
        "relight",
        str(TINY),
        "--olat",
        "3",
        "--envmap",
        str(write_sun(tmp_path)),
        "--frames",
        "0:4",
        "--cameras",
        "0,2",
        "--uv-resolution",
        "32",
    ]
    assert main([*args, "--out", str(tmp_path / "one")]) == 0
    add, calls = relight._Previews.add, []

    def interrupted(self, *a, **k):  # the run stops (Ctrl-C) after 5 of its 16 views
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(a)
        add(self, *a, **k)

    monkeypatch.setattr(relight._Previews, "add", interrupted)
    assert main([*args, "--out", str(tmp_path / "two")]) == 130
    assert "rerun to resume" in capsys.readouterr().err
    monkeypatch.setattr(relight._Previews, "add", add)
    assert main([*args, "--out", str(tmp_path / "two")]) == 0
    said = capsys.readouterr().out
    assert "wrote 11 renders" in said and "5 found written" in said, said
    assert different_outputs(tmp_path / "one", tmp_path / "two", ignore=lambda p: p.suffix == ".mp4") == []
    assert main([*args, "--out", str(tmp_path / "two"), "--cameras", "0,1,2"]) == 0, "another camera: the same run, extended"
    assert (tmp_path / "two" / "olat003" / "cam01" / "frame_0003.png").is_file()


def test_a_relight_resumed_with_other_inputs_or_options_is_refused(tmp_path, llvm_variant, capsys):
    from gra_mi.cli import main
    from gra_mi.core.io import write_exr

    albedo = tmp_path / "albedo.exr"
    write_exr(albedo, np.full((32, 32, 3), 0.5, np.float32))
    args = [
        "relight",
        str(TINY),
        "--olat",
        "3",
        "--frames",
        "0:2",
        "--albedo",
        str(albedo),
        "--uv-resolution",
        "32",
        "--out",
        str(tmp_path / "out"),
    ]
    assert main(args) == 0
    write_exr(albedo, np.full((32, 32, 3), 0.6, np.float32))  # edited before the rerun
    capsys.readouterr()
    assert main(args) == 2
    assert "input albedo" in capsys.readouterr().err
    for changed in (["--olat", "4"], ["--frames", "0:3"], ["--exposure", "2"]):  # another OLAT, frames, exposure
        assert main([*args, *changed]) == 2
        assert "made by another run" in capsys.readouterr().err
    assert main([*args, "--overwrite"]) == 0, "--overwrite starts over"


def write_sun(folder: Path) -> Path:
    from gra_mi.core.io import write_exr
    from gra_mi.stage.envmap_library import reference_map

    write_exr(folder / "sun.exr", reference_map("sun", 16))
    return folder / "sun.exr"
