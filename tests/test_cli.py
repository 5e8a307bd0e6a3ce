"""The gra-mi command line: help for every option, renders, and one-line errors on bad input."""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli import COMMANDS, build_parser
from gra_mi.core.io import read_exr, write_exr

from .conftest import SCENES

TINY = SCENES / "tiny_lightstage.xml"


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    env = {**os.environ, "GRA_MI_QUIET": "1"}
    return subprocess.run([sys.executable, "-m", "gra_mi.cli", *args], capture_output=True, text=True, env=env, cwd=cwd, timeout=600)


def _options(parser: argparse.ArgumentParser, name: str = "gra-mi"):
    """(command, action) for every option of every command and subcommand (``import mitsuba``)."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub, p in action.choices.items():
                yield from _options(p, f"{name} {sub}")
        elif action.dest != "help":
            yield name, action


def test_every_option_has_help_and_says_its_default():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(sub.choices) == set(COMMANDS)
    for name, action in _options(parser):
        assert action.help and len(action.help) > 10, f"{name} {action.option_strings}: no help"
        takes_value = action.nargs != 0 and not isinstance(action, argparse.BooleanOptionalAction)
        if takes_value and not action.required:  # a text that merely mentions "the default layout" hid it once
            said = re.search(r"default:|default none|\(default\)", action.help, re.IGNORECASE)
            assert said, f"{name} {action.option_strings or action.dest}: its help does not say its default"


def test_help_runs():
    out = run_cli("render", "--help")
    assert out.returncode == 0 and "--envmap" in out.stdout and "--variant" in out.stdout


def test_render_envmap_olat_and_pattern(tmp_path, llvm_variant):
    env = np.ones((16, 32, 3), np.float32)
    write_exr(tmp_path / "white.exr", env)
    out = run_cli(
        "render",
        str(TINY),
        "--frame",
        "2",
        "--camera",
        "1",
        "--envmap",
        str(tmp_path / "white.exr"),
        "--spp",
        "8",
        "--background",
        "--out",
        str(tmp_path / "r"),
    )
    assert out.returncode == 0, out.stderr
    image = read_exr(tmp_path / "r" / "cam01_f0002_white.exr")
    assert image.shape == (64, 96, 4) and image[..., 3].max() == 1.0 and image[..., :3].max() > 0
    assert (tmp_path / "r" / "cam01_f0002_white.png").exists() and (tmp_path / "r" / "cam01_f0002_white_composite.png").exists()
    out = run_cli("render", str(TINY), "--olat", "7", "--spp", "4", "--out", str(tmp_path / "r"))
    assert out.returncode == 0, out.stderr
    (tmp_path / "p.json").write_text(json.dumps({"intensities": [0.1] * 64}))
    out = run_cli(
        "render", str(TINY), "--pattern", str(tmp_path / "p.json"), "--camera", "cam03", "--spp", "4", "--out", str(tmp_path / "r")
    )
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "r" / "cam03_f0000_p.exr").exists()


def _assert_one_line_error(out: subprocess.CompletedProcess, *needles: str) -> None:
    assert out.returncode == 2, out.stderr
    lines = [line for line in out.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_bad_inputs_give_one_line_errors_and_write_nothing(tmp_path):
    out_dir = tmp_path / "out"
    nan_env = np.ones((8, 16, 3), np.float32)
    nan_env[1, 2, 0] = np.nan
    write_exr(tmp_path / "nan.exr", nan_env)
    write_exr(tmp_path / "square.exr", np.ones((8, 8, 3), np.float32))
    (tmp_path / "broken.xml").write_text("<scene version='3.0.0'><shape")
    cases = [
        (["render", str(TINY), "--envmap", str(tmp_path / "missing.exr")], ["missing.exr", "not found"]),
        (["render", str(TINY), "--envmap", str(tmp_path / "nan.exr")], ["nan.exr", "1 NaN"]),
        (["render", str(TINY), "--envmap", str(tmp_path / "square.exr")], ["square.exr", "twice as wide"]),
        (["render", str(tmp_path / "broken.xml"), "--olat", "0"], ["broken.xml", "malformed XML"]),
        (["render", str(TINY), "--olat", "999"], ["LED index 999"]),
        (["render", str(TINY), "--olat", "0", "--frame", "50"], ["frame 50 out of range"]),
        (["render", str(TINY), "--olat", "0", "--camera", "nope"], ["no camera named 'nope'"]),
    ]
    for args, needles in cases:
        _assert_one_line_error(run_cli(*args, "--out", str(out_dir)), *needles)
    (tmp_path / "calib.json").write_text("{ nope")
    _assert_one_line_error(
        run_cli("rig", "--out", str(out_dir), "--from-calibration", str(tmp_path / "calib.json")), "calib.json", "malformed JSON"
    )
    assert not out_dir.exists(), "nothing partial is written"


def test_repair_envmap_option(tmp_path):
    nan_env = np.ones((8, 16, 3), np.float32)
    nan_env[1, 2, 0] = np.nan
    write_exr(tmp_path / "nan.exr", nan_env)
    out = run_cli("render", str(TINY), "--envmap", str(tmp_path / "nan.exr"), "--repair-envmap", "--spp", "2", "--out", str(tmp_path / "r"))
    assert out.returncode == 0 and "repaired 1 NaN" in out.stderr


def test_rig_scene_subject_commands_compose(tmp_path):
    assert (
        run_cli(
            "rig", "--out", str(tmp_path / "rig"), "--num-leds", "30", "--num-cameras", "2", "--width", "32", "--height", "24"
        ).returncode
        == 0
    )
    assert run_cli("subject", "--kind", "tiny", "--frames", "3", "--out", str(tmp_path / "subj")).returncode == 0
    assert (
        run_cli("scene", "--rig", str(tmp_path / "rig"), "--subject", str(tmp_path / "subj"), "--out", str(tmp_path / "s.xml")).returncode
        == 0
    )
    out = run_cli("render", str(tmp_path / "s.xml"), "--olat", "3", "--frame", "2", "--spp", "2", "--out", str(tmp_path / "r"))
    assert out.returncode == 0, out.stderr


@pytest.mark.slow
def test_demo_tiny_runs_end_to_end(tmp_path):
    out = run_cli("demo", "--preset", "tiny", "--out", str(tmp_path / "demo"))
    assert out.returncode == 0, out.stderr
    record = json.loads((tmp_path / "demo" / "demo.json").read_text())
    stages = record["eval"]["stages"]
    assert all(stages[s]["status"] == "done" for s in ("microfacet", "RelightNet", "refined", "deflickered")), stages
    for split in record["eval"]["protocol"]["splits"]:
        assert all(np.isfinite(stages[s]["splits"][split]["psnr"]) for s in ("microfacet", "RelightNet", "refined"))
    assert record["fit"]["metrics"] and record["relightnet"]["splits"] and record["lighting"]["rows"]
    assert "envmaps/train/train_0000.exr" in record["capture"]["ground_truth"]["envmap_fidelity"]
    assert record["refiner"]["train"]["mix"]["scores"] and "psnr_refined" in record["refiner"]
    assert record["stamp"]["preset"] == "tiny" and record["timings"]
    report = (tmp_path / "demo" / "report.md").read_text()  # rendered from the record: the table opens it
    assert report.index("## Every stage against the truth") < report.index("## Pipeline stages")
    for rel in (
        "capture/scene.xml",
        "fit/albedo.exr",
        "fit/fit_report.md",
        "plots/rig.png",
        "videos/cam07_test.mp4",
        "contact_truth_vs_relit.png",
        "avatar.glb",
        "refiner/model/refiner.safetensors",
        "refiner/model/mix.md",
        "refiner/refined/test_cam07/comparison.mp4",
        "refiner/refined/test_cam07/refine.json",
        "refiner/refined/test_cam07/deflickered/deflickered.mp4",
        "eval/eval.md",
        "eval/contact_test_cam07.png",
        "eval/videos/test_cam07_composite.mp4",
        "composite.png",
    ):
        assert (tmp_path / "demo" / rel).exists(), rel
    # Resumable: a second run reuses the capture and the renders.
    renders = sorted((tmp_path / "demo" / "renders").rglob("frame_*.exr"))
    images = sorted((tmp_path / "demo" / "capture" / "images").rglob("*.exr"))
    before = {p: p.stat().st_mtime_ns for p in images}
    assert run_cli("demo", "--preset", "tiny", "--out", str(tmp_path / "demo")).returncode == 0
    assert renders and all(p.stat().st_mtime_ns == t for p, t in before.items())


@pytest.mark.slow
def test_demo_with_an_olat_test_sequence_first(tmp_path):
    """A capture whose first held-out sequence is lit by an LED pattern (no environment): the demo shows and composites
    its environment-lit sequence instead (it failed on the pattern's missing envmap before)."""
    script = (
        "import sys; from dataclasses import replace; from pathlib import Path; "
        "from gra_mi.capture import synthetic; from gra_mi.apps.demo import run_demo; "
        "synthetic.PRESETS['tiny'] = replace(synthetic.PRESETS['tiny'], test_clips=['tiny', 'tiny'], test_lighting=['olat', 'envmap']); "
        "run_demo('tiny', Path(sys.argv[1]))"
    )
    env = {**os.environ, "GRA_MI_QUIET": "1"}
    out = subprocess.run([sys.executable, "-c", script, str(tmp_path / "demo")], capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    from gra_mi.capture.dataset import Capture

    frames = Capture.load(tmp_path / "demo" / "capture").frames
    assert [f.kind for f in frames if f.split == "test"][0] == "pattern"
    assert (tmp_path / "demo" / "composite.png").is_file() and (tmp_path / "demo" / "report.md").is_file()


@pytest.mark.slow
def test_envmap_sweep_pipeline(tmp_path):
    repo = SCENES.parent
    assert run_cli("envmaps", "--out", str(tmp_path / "env"), "--train", "0", "--test", "2", "--height", "16").returncode == 0
    env = {**os.environ, "GRA_MI_QUIET": "1"}
    out = subprocess.run(
        [
            sys.executable,
            str(repo / "pipelines" / "envmap_sweep.py"),
            str(TINY),
            str(tmp_path / "env" / "test"),
            "--spp",
            "4",
            "--out",
            str(tmp_path / "sweep"),
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "sweep" / "contact_sheet.png").exists() and (tmp_path / "sweep" / "test_0001.exr").exists()


def test_bench_conclusions_follow_the_numbers():
    """The bench report's conclusions are computed from its results, not written in advance."""
    from gra_mi.apps.bench import Result, conclusions

    rows = [
        Result("LEDs", "all", 10, 10, 1, 0.0, 99, 0.0),
        Result("LEDs", "k=16", 2, 2, 1, 0.05, 30, 0.1),
        Result("LEDs", "k=64", 5, 5, 1, 0.005, 40, 0.01),
        Result("UV", "64²", 1, 1, 1, 0.2, 20, 0.3),
    ]
    lines = conclusions(rows, {1, 2, 3})
    assert lines[0] == "- **LEDs**: cheapest k=16 (2 ms, error 5.00 %); fastest within 1 % error: k=64 (5 ms)."
    assert lines[1] == "- **UV**: cheapest 64² (1 ms, error 20.00 %); none within 1 % error."
    assert lines[-1].endswith("64² (UV), k=16 (LEDs), k=64 (LEDs).")


@pytest.mark.slow
def test_bench_quick_writes_report(tmp_path):
    out = run_cli("bench", "--quick", "--out", str(tmp_path / "bench"))
    assert out.returncode == 0, out.stderr
    report = (tmp_path / "bench" / "report.md").read_text()
    for needle in (
        "subsample k=16",
        "importance k=64",
        "upsampled",
        "shared over 2 frames",
        "far field",
        "float16",
        "64² UV",
        "direct 16 spp",
        "2 bounces, 32 rays/texel, smoothing radius 2",
        "2 bounces, 32 rays/texel, not smoothed",
        "without the hull test",
    ):
        assert needle in report, needle
    rows = json.loads((tmp_path / "bench" / "results.json").read_text())
    reference = next(r for r in rows if r["group"] == "reference")
    assert reference["mean_rel_error"] == 0.0
    assert all(r["mean_rel_error"] > 0 for r in rows if r["group"] in ("LEDs", "lighting model", "Mitsuba direct"))
    bounces = [r for r in rows if r["group"] == "bounces"]  # path, 1 bounce, 2 with 8 and 32 rays, 32 not smoothed, no hull test
    assert len(bounces) == 6 and all(np.isfinite(r["mean_rel_error"]) and r["time_ms"] > 0 for r in bounces)
    assert (tmp_path / "bench" / "pareto.png").exists() and (tmp_path / "bench" / "results.csv").exists()
