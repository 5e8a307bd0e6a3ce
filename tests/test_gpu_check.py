"""The GPU check's parts that run on any machine (scripts/gpu_check.sh, scripts/gpu/): the packages it carries, the
page it writes from a run's folder, the stamp of a copy without .git, and a run on a machine without ffmpeg or
usd-core (as the GPU machine is) that completes and names what it did not make."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent


def script_module(name: str):
    spec = importlib.util.spec_from_file_location(f"gpu_{name}", REPO / "scripts" / "gpu" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_copy_without_git_is_stamped_with_the_commit_it_was_said_to_be(monkeypatch):
    from gra_mi.core import stamp

    monkeypatch.setattr(stamp, "_git", lambda *args: None)
    monkeypatch.delenv("GRA_MI_COMMIT", raising=False)
    assert stamp.run_stamp()["commit"] is None
    monkeypatch.setenv("GRA_MI_COMMIT", "abc1234")
    assert stamp.run_stamp()["commit"] == "abc1234 (said, no .git)", "said, and marked as said: nothing checked it"


def test_mp4_previews_without_ffmpeg_are_named_not_faked(monkeypatch, tmp_path):
    import imageio_ffmpeg

    from gra_mi.core import io

    frames = [np.full((6, 8, 3), v, np.float32) for v in (0.1, 0.5, 0.9)]
    assert io.write_mp4(tmp_path / "with.mp4", frames) and (tmp_path / "with.mp4").stat().st_size > 0

    def no_ffmpeg():
        raise RuntimeError("No ffmpeg exe could be found")

    monkeypatch.setattr(imageio_ffmpeg, "get_ffmpeg_exe", no_ffmpeg)
    monkeypatch.setattr(io, "PREVIEWS_NOT_MADE", {})
    assert not io.write_mp4(tmp_path / "without.mp4", frames), "says it did not write it"
    with io.Mp4Stream(tmp_path / "stream.mp4") as stream:
        for frame in frames:
            stream.append(frame)
    assert not stream.made
    assert sorted(p.name for p in tmp_path.iterdir()) == ["with.mp4"], "no empty or temporary file left behind"
    assert set(io.PREVIEWS_NOT_MADE) == {str(tmp_path / "without.mp4"), str(tmp_path / "stream.mp4")}
    assert all("imageio-ffmpeg" in why for why in io.PREVIEWS_NOT_MADE.values())


def _run_folder(folder: Path, *, tests_rc: int, demo_rc: int, stage_ms: float, failure: bool) -> Path:
    folder.mkdir()
    (folder / "env.txt").write_text("gpu: NVIDIA H200, 580.159.04, 143771 MiB")
    (folder / "parts.tsv").write_text(f"tests\t{tests_rc}\t60\t240\ndemo\t{demo_rc}\t150\t150\nstages\t0\t30\t120\n")
    (folder / "demo.log").write_text("INFO lots\n" * 40 + "Traceback: CUDA said no\n")
    bad = '<failure message="AssertionError: 0.2 &gt; 0.1&#10;more">trace</failure>' if failure else ""
    (folder / "tests.xml").write_text(
        f'<testsuites><testsuite tests="3" failures="{int(failure)}" errors="0" skipped="1" time="42.5">'
        '<testcase classname="tests.test_a" name="test_ok[cuda_ad_rgb]"/>'
        f'<testcase classname="tests.test_a" name="test_bad[cuda_ad_rgb]">{bad}</testcase>'
        "</testsuite></testsuites>"
    )
    stages = [
        {"stage": "microfacet per frame (the two above)", "ms": stage_ms, "paper": "microfacet"},
        {"stage": "viewer", "error": "RuntimeError: boom"} if failure else {"stage": "viewer", "ms": 10 * stage_ms},
    ]
    (folder / "stages.json").write_text(json.dumps({"stamp": f"commit x, {folder.name}", "device": folder.name, "stages": stages}))
    demo = {
        "timings": {"material fit": stage_ms / 100},
        "not_made": {"avatar.usdz": "no usd-core (pip install usd-core)"} if failure else {},
    }
    (folder / "demo.json").write_text(json.dumps(demo))
    if not failure:  # the GPU run below never got to the fit step
        (folder / "fit_step.md").write_text(
            f"# A page\n\nsome words\n\n| views shaded | ms per step |\n|---|---|\n| joined | {stage_ms} |\n"
        )
    return folder


def test_the_page_puts_each_gpu_figure_beside_the_cpus_and_says_what_failed(tmp_path):
    page = script_module("page")
    gpu = _run_folder(tmp_path / "gpu", tests_rc=1, demo_rc=124, stage_ms=50.0, failure=True)
    cpu = _run_folder(tmp_path / "cpu", tests_rc=0, demo_rc=0, stage_ms=500.0, failure=False)
    text = page.page(page.read_run(gpu), page.read_run(cpu))
    assert "**1 passed, 1 failed, 0 errors, 1 skipped**" in text
    assert "| `tests.test_a::test_bad[cuda_ad_rgb]` | AssertionError: 0.2 > 0.1 |" in text, "the failure's first line"
    assert "GPU: stopped at its 150 s limit; CPU: exit 0 after 150 s" in text
    assert "| microfacet per frame (the two above) | 50.0 | 500.0 | 10.0× | 404.6 |" in text, "beside the paper's H100 row"
    assert "| viewer | failed: RuntimeError: boom | 5000.0 | — |" in text
    assert "GPU, not made (no usd-core (pip install usd-core)): 1 file(s), `avatar.usdz`." in text
    assert "### The end of `demo.log` (stopped at its 150 s limit)" in text and "Traceback: CUDA said no" in text
    assert "GPU: no table (not run)." in text and "CPU:\n\n| views shaded | ms per step |\n|---|---|\n| joined | 500.0 |" in text
    assert page.page(page.read_run(tmp_path / "absent"), {}).count("not run") >= 1, "a run that left nothing says so"
    (gpu / "tests.xml").write_text('<testsuites><testsuite tests="3"')  # a run killed while writing
    (gpu / "stages.json").write_text('{"stamp": ')
    cut = page.page(page.read_run(gpu), page.read_run(cpu))
    assert "GPU run, unreadable (cut short?): stages.json" in cut and "tests.xml" in cut and "No test report" in cut


def test_the_carried_packages_are_what_the_image_lacks_at_this_environments_versions():
    pack = script_module("pack")
    needed = pack.needed("3.12")
    import mitsuba

    assert needed["mitsuba"] == mitsuba.__version__ and "drjit" in needed and "anny" in needed
    assert not {"torch", "numpy", "transformers", "peft"} & set(needed), "the image has them"
    assert not set(pack.TOO_BIG) & set(needed), "left behind, each with what the check does without it"


def test_packing_keeps_what_a_run_opened_small_files_and_a_variants_cuda_twin(tmp_path):
    pack = script_module("pack")
    big = b"x" * pack.KEEP_UNTRACED_BELOW
    wheel = tmp_path / "demo-1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as archive:
        for name, data in {
            "demo/__init__.py": b"",
            "demo/big_used.py": big,
            "demo/big_unused.bin": big,
            "demo/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so": big,
            "demo/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so": big,
            "demo/scalar_mono.cpython-312-x86_64-linux-gnu.so": big,
            "demo.libs/libgomp-a34b.so.1": big,
        }.items():
            archive.writestr(name, data)
    trace = tmp_path / "trace.txt"
    trace.write_text(
        "/v/lib/python3.11/site-packages/demo/__pycache__/big_used.cpython-311.pyc\n"
        "/v/lib/python3.11/site-packages/demo/llvm_ad_rgb.cpython-311-x86_64-linux-gnu.so\n"
        "/v/lib/python3.11/site-packages/demo/../demo.libs/libgomp-a34b.so.1\n"  # as the loader opens it (RPATH)
    )
    rows = pack.pack([wheel], pack.traced(trace), tmp_path / "site.tar.xz")
    import tarfile

    with tarfile.open(tmp_path / "site.tar.xz") as tar:
        kept = set(tar.getnames())
    assert kept == {
        "demo/__init__.py",
        "demo/big_used.py",
        "demo/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so",
        "demo/cuda_ad_rgb.cpython-312-x86_64-linux-gnu.so",
        "demo.libs/libgomp-a34b.so.1",
    }
    assert rows[0][2] == 2 * len(big), "what was left out is counted"


@pytest.mark.slow
def test_the_tiny_demo_without_ffmpeg_and_usd_core_completes_naming_what_it_did_not_make(tmp_path):
    """The GPU machine has neither (they do not fit its carry limit): the demo's other stages must still run there."""
    env = {**os.environ, "GRA_MI_QUIET": "1", "GRA_MI_HIDE_MODULES": "pxr,imageio_ffmpeg"}
    env["PYTHONPATH"] = os.pathsep.join([str(REPO / "scripts" / "gpu"), str(REPO), env.get("PYTHONPATH", "")])
    out = tmp_path / "demo"
    done = subprocess.run(
        [sys.executable, "-m", "gra_mi.cli", "demo", "--preset", "tiny", "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
        timeout=900,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    not_made = json.loads((out / "demo.json").read_text())["not_made"]
    assert not_made["avatar.usdz"].startswith("no usd-core") and "videos/cam07_test.mp4" in not_made
    assert "refiner/refined/test_cam07/comparison.mp4" in not_made
    assert not list(out.rglob("*.mp4")) and not (out / "avatar.usdz").exists()
    assert (out / "avatar.glb").is_file(), "what needs neither is made"
    assert "**Not made on this machine:**" in (out / "report.md").read_text()
    assert "not made: avatar.usdz" in done.stderr


def test_the_check_refuses_bad_options_and_never_empties_a_folder_it_did_not_make(tmp_path):
    script = REPO / "scripts" / "gpu_check.sh"

    def run(*args, **env):
        return subprocess.run(["bash", str(script), *args], capture_output=True, text=True, env={**os.environ, **env}, timeout=60)

    bad = run("--bogus")
    assert bad.returncode == 2 and "unknown option --bogus" in bad.stderr
    theirs = tmp_path / "gpu_check_run"  # where a GPU run keeps its parts (under TMPDIR)
    theirs.mkdir()
    (theirs / "keep.txt").write_text("a user's file")
    refused = run("--commit", "abc1234", TMPDIR=str(tmp_path))
    assert refused.returncode == 2 and "not a run folder this script made" in refused.stderr
    assert (theirs / "keep.txt").read_text() == "a user's file"


def test_the_benchmarks_and_the_packer_refuse_what_they_cannot_use(tmp_path):
    stages = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "stages.py"), "--repeats", "0"], capture_output=True, text=True, timeout=300
    )
    assert stages.returncode != 0 and "repeats: must be a finite number > 0, got 0" in stages.stderr
    packer = subprocess.run(
        [sys.executable, str(REPO / "scripts" / "gpu" / "pack.py"), "--out", str(tmp_path)], capture_output=True, text=True, timeout=60
    )
    assert packer.returncode != 0 and "trace.txt is missing" in packer.stderr and not (tmp_path / "site.tar.xz").exists()
    step = [sys.executable, str(REPO / "benchmarks" / "fit_step.py")]
    zero = subprocess.run([*step, "--repeats", "0"], capture_output=True, text=True, timeout=300)
    assert zero.returncode != 0 and "repeats: must be a finite number > 0, got 0" in zero.stderr
    (tmp_path / "not_a_capture").mkdir()
    folder = subprocess.run([*step, "--capture", str(tmp_path / "not_a_capture")], capture_output=True, text=True, timeout=300)
    assert folder.returncode != 0 and "capture.json: file not found" in folder.stderr


def test_the_parts_fit_in_one_device_call():
    """Every part may run to its limit (and 10 s to be killed) and the page must still be written within the device
    tool's 600 s call: the limits' sum, which the script's header states, leaves time for unpacking and the page."""
    import re

    script = (REPO / "scripts" / "gpu_check.sh").read_text()
    limits = [int(limit) for limit in re.findall(r"^part \w+ (\d+) ", script, flags=re.M)]
    assert len(limits) >= 4 and sum(limits) + 10 * len(limits) <= 560
    assert f"the parts' own limits add up to {sum(limits)} s" in script
