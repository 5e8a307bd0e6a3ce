"""One runtime per command: the Mitsuba variant and the torch device are chosen once, independently; the CLI is
made from the typed configs and names the flag of a bad parameter."""

from __future__ import annotations

import dataclasses

import pytest
import torch

import gra_mi.core.runtime as runtime
from gra_mi.cli import build_parser, main
from gra_mi.core.errors import GraMiParameterError


@pytest.fixture
def fresh_runtime(monkeypatch):
    """A process that has not started a runtime yet (each CLI call is a new process in real use)."""
    monkeypatch.setattr(runtime, "RUNTIME", runtime.Runtime())


def _spy(monkeypatch, module, name: str, seen: dict, result):
    def record(*args, **kwargs):
        seen[name] = runtime.torch_device()
        return result

    monkeypatch.setattr(module, name, record)


def test_torch_commands_use_the_gpu_when_torch_sees_one(monkeypatch, tmp_path, fresh_runtime):
    """The bug this fixes: the torch device was derived from the Mitsuba variant, and train-refiner / refine never
    chose one, so on a GPU machine they trained and sampled on the CPU."""
    import gra_mi.refiner.infer as infer
    import gra_mi.refiner.train as train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    seen: dict[str, str] = {}
    _spy(monkeypatch, train, "train_refiner", seen, tmp_path)
    _spy(monkeypatch, infer, "refine_to_folder", seen, {"frames": 1, "windows": 1, "frames_per_second": 1.0, "mix": 1.0})
    data = tmp_path / "data"  # beside the output: an output inside an input is refused
    data.mkdir()
    assert main(["train-refiner", str(data), "--out", str(tmp_path / "m")]) == 0
    monkeypatch.setattr(runtime, "RUNTIME", runtime.Runtime())
    assert main(["refine", str(tmp_path), "--model", str(tmp_path), "--sequence", "s"]) == 0
    assert seen == {"train_refiner": "cuda", "refine_to_folder": "cuda"}


def test_device_option_overrides_and_variant_is_independent(monkeypatch, tmp_path, fresh_runtime):
    """--device picks the torch device; the Mitsuba variant follows Dr.Jit's backends, not torch."""
    import mitsuba as mi

    import gra_mi.relightnet.train as train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(runtime, "cuda_available", lambda: False)
    seen: dict[str, str] = {}
    _spy(monkeypatch, train, "train_relightnet", seen, tmp_path / "validation.md")
    assert main(["train-relightnet", str(tmp_path), "--fit", str(tmp_path)]) == 0
    assert seen["train_relightnet"] == "cuda" and mi.variant() == "llvm_ad_rgb"
    monkeypatch.setattr(runtime, "RUNTIME", runtime.Runtime())
    assert main(["train-relightnet", str(tmp_path), "--fit", str(tmp_path), "--device", "cpu"]) == 0
    assert seen["train_relightnet"] == "cpu"


def test_unavailable_device_is_one_line_naming_the_flag(monkeypatch, tmp_path, capsys, fresh_runtime):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["refine", str(tmp_path), "--model", str(tmp_path), "--sequence", "s", "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--device: 'cuda' asked for" in err and "Traceback" not in err


def test_library_names_the_parameter_cli_names_the_flag(tmp_path, capsys):
    from gra_mi.fit.materials import FitConfig

    with pytest.raises(GraMiParameterError, match="irls_iterations") as info:
        FitConfig(irls_iterations=-1).validate()
    assert info.value.parameter == "irls_iterations"
    assert main(["fit", str(tmp_path), "--irls-iterations", "-1"]) == 2
    err = capsys.readouterr().err
    assert "--irls-iterations: must be >= 0" in err, err
    assert main(["train-refiner", str(tmp_path), "--grad-accumulation", "0"]) == 2
    assert "--grad-accumulation: must be a finite number > 0" in capsys.readouterr().err


def _subparser(name: str):
    parser = build_parser()
    return next(a for a in parser._actions if a.dest == "command").choices[name]


@pytest.mark.parametrize(
    ("command", "config_path"),
    [
        ("fit", "gra_mi.fit.materials:FitConfig"),
        ("train-relightnet", "gra_mi.relightnet.train:TrainConfig"),
        ("train-refiner", "gra_mi.refiner.train:RefinerTrainConfig"),
        ("train-refiner", "gra_mi.refiner.model:RefinerConfig"),
        ("refine", "gra_mi.refiner.infer:RefineConfig"),
        ("relight", "gra_mi.apps.relight:RelightConfig"),
    ],
)
def test_cli_defaults_are_the_configs_defaults(command, config_path):
    """A default lives in one place: the option's default and help come from the config field."""
    import importlib

    module, name = config_path.split(":")
    cls = getattr(importlib.import_module(module), name)
    defaults = {a.dest: a.default for a in _subparser(command)._actions}
    fields = [f for f in dataclasses.fields(cls) if f.name in defaults]
    assert fields, f"no option of `gra-mi {command}` comes from {name}"
    for f in fields:
        expected = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if f.name == "seed" and command == "train-refiner":
            continue  # one --seed sets both configs' seed (their defaults agree)
        assert defaults[f.name] == expected, (command, f.name)


@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["relight", "scene.xml", "--olat", "0", "--uv-resolution", "0"], "--uv-resolution: must be >= 8"),
        (["relight", "scene.xml", "--olat", "0", "--exposure", "nan"], "--exposure: must be a finite number"),
        (["refine", "data", "--model", "m", "--sequence", "s", "--shift", "nan"], "--shift: must be a finite number"),
        (["refine", "data", "--model", "m", "--sequence", "s", "--steps", "0"], "--steps: must be a finite number > 0"),
    ],
)
def test_bad_options_stop_before_any_file_is_read(argv, flag, tmp_path, capsys, monkeypatch):
    """The scene, model and data named here do not exist: the option is checked first, and named as typed."""
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert flag in err and err.count("\n") == 1, err
    assert not any(tmp_path.iterdir())


def test_one_command_parser_does_not_import_torch():
    """`gra-mi rig --help` builds only rig's options: building them all imports torch and diffusers (seconds)."""
    import subprocess
    import sys

    code = "import sys; from gra_mi.cli.main import build_parser; build_parser('rig'); print('torch' in sys.modules)"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "False"


def test_threaded_work_keeps_the_order_and_stops_at_a_failure():
    """gra_mi.core.progress.threaded: results in the items' order; a failure is raised at its item's turn and what had
    not started is never run (a long import stops at its bad image, not after the rest)."""
    import threading
    import time

    from gra_mi.core.progress import threaded

    assert list(threaded(lambda k: k * k, list(range(50)), "squares", 4)) == [k * k for k in range(50)]
    started, lock = [], threading.Lock()

    def work(k: int) -> int:
        with lock:
            started.append(k)
        if k == 3:
            raise ValueError("bad item 3")
        time.sleep(0.01)
        return k

    with pytest.raises(ValueError, match="bad item 3"):
        list(threaded(work, list(range(400)), "items", 2))
    assert len(started) < 100, f"{len(started)} of 400 items started after the failure"
