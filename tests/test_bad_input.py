"""The bad-input suite: every command, fed what a hostile but realistic user would feed it, stops with one line
naming the file or option and what was expected, exit code 2, no traceback, and writes nothing (issue 19).

Cases run in-process (``gra_mi.cli.main``) on tiny inputs written here, so the whole suite takes about a minute
once the shared tiny capture exists. Grow it with every new reader or option.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli import main
from gra_mi.core.io import read_exr, write_exr

from .conftest import SCENES

TINY = SCENES / "tiny_lightstage.xml"


def run(argv: list[str], capsys) -> tuple[int, list[str]]:
    """Exit code and the lines gra-mi itself printed on stderr (log records aside)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = exc.code
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    return code, [line for line in err.splitlines() if line.startswith("gra-mi")]


def assert_refused(argv: list[str], capsys, *needles: str, out: Path | None = None) -> str:
    code, lines = run(argv, capsys)
    assert code == 2, (argv, code, lines)
    assert len(lines) == 1, lines
    for needle in needles:
        assert needle.lower() in lines[0].lower(), (needle, lines[0])
    if out is not None:
        left = sorted(out.rglob("*")) if out.is_dir() else [out] if out.exists() else []
        assert not left, f"partial output: {left}"
    return lines[0]


# --------------------------------------------------------------------------------------------------------------
# Inputs: the tiny path-traced capture and its fit (shared with the other modules), and broken copies of them
# --------------------------------------------------------------------------------------------------------------


def _linked_copy(src: Path, dst: Path, copy: tuple[str, ...] = ()) -> Path:
    """A copy of a folder whose files are symlinks, except those under ``copy`` (relative paths), which are real."""
    dst.mkdir(parents=True)
    for path in sorted(src.rglob("*")):
        rel = path.relative_to(src)
        if path.name == ".gra-mi.lock":  # a lock belongs to the folder it locks (a copy makes a new one)
            continue
        target = dst / rel
        if path.is_dir():
            target.mkdir(parents=True, exist_ok=True)
        elif any(str(rel) == c or str(rel).startswith(c + "/") for c in copy):
            shutil.copy2(path, target)
        else:
            target.symlink_to(path)
    return dst


@pytest.fixture(scope="module")
def inputs(path_traced_fit, tmp_path_factory):
    root = tmp_path_factory.mktemp("bad")
    cap, fit = path_traced_fit / "cap", path_traced_fit / "fit"
    data = json.loads((cap / "capture.json").read_text())
    first = "images/cam00/frame_0001.exr"

    def capture(name: str, mutate_image=None, mutate_json=None, image: str = first) -> Path:
        folder = _linked_copy(cap, root / name, copy=("capture.json", image))
        if mutate_image is not None:
            write_exr(folder / image, mutate_image(read_exr(cap / image)))
        if mutate_json is not None:
            text = mutate_json(json.loads(json.dumps(data)))
            (folder / "capture.json").write_text(text if isinstance(text, str) else json.dumps(text))
        return folder

    def nan_all(a):
        a[..., :3] = np.nan
        return a

    def one_nan(a):
        a[3, 4, 1] = np.nan
        return a

    def negative(a):
        a[:2, :, :3] = -0.5
        return a

    def inf(a):
        a[0, 0, 0] = np.inf
        return a

    def bad_mask(a):
        a[..., 3] = 3.0
        return a

    paths = {
        "cap": cap,
        "fit": fit,
        "root": root,
        "cap_nan": capture("cap_nan", nan_all),
        "cap_one_nan": capture("cap_one_nan", one_nan),
        "cap_negative": capture("cap_negative", negative),
        "cap_inf": capture("cap_inf", inf),
        "cap_half": capture("cap_half", lambda a: a[::2, ::2]),
        "cap_rgb": capture("cap_rgb", lambda a: a[..., :3]),
        "cap_mask": capture("cap_mask", bad_mask),
        "cap_json_broken": capture("cap_json_broken", mutate_json=lambda d: '{"format": "gra-mi-capture/1", "frames": ['),
        "cap_json_format": capture("cap_json_format", mutate_json=lambda d: {**d, "format": "other/1"}),
        "cap_json_missing": capture("cap_json_missing", mutate_json=lambda d: {k: v for k, v in d.items() if k != "frames"}),
        "cap_json_frame_str": capture("cap_json_frame_str", mutate_json=lambda d: {**d, "frames": ["frame0"] + d["frames"][1:]}),
        "cap_json_frame_num": capture(
            "cap_json_frame_num", mutate_json=lambda d: {**d, "frames": [{**d["frames"][0], "frame": "zero"}] + d["frames"][1:]}
        ),
        "cap_json_kind": capture(
            "cap_json_kind", mutate_json=lambda d: {**d, "frames": [{**d["frames"][0], "kind": "disco"}] + d["frames"][1:]}
        ),
        "cap_json_split": capture(
            "cap_json_split", mutate_json=lambda d: {**d, "frames": [{**d["frames"][0], "split": "val"}] + d["frames"][1:]}
        ),
        "cap_json_cameras": capture("cap_json_cameras", mutate_json=lambda d: {**d, "train_cameras": "cam00"}),
        "cap_json_camera_name": capture("cap_json_camera_name", mutate_json=lambda d: {**d, "eval_cameras": ["cam99"]}),
        "cap_json_uv": capture("cap_json_uv", mutate_json=lambda d: {**d, "uv_resolution": "big"}),
        "cap_json_uv_neg": capture("cap_json_uv_neg", mutate_json=lambda d: {**d, "uv_resolution": -4}),
        "cap_json_unknown": capture("cap_json_unknown", mutate_json=lambda d: {**d, "calibration_date": "today"}),
        "cap_json_list": capture("cap_json_list", mutate_json=lambda d: "[1, 2]"),
        "cap_json_dup": capture("cap_json_dup", mutate_json=lambda d: {**d, "frames": d["frames"] + d["frames"][:1]}),
    }
    # A missing image, a truncated one, one that is not an EXR at all
    paths["cap_missing_image"] = capture("cap_missing_image")
    (paths["cap_missing_image"] / first).unlink()
    paths["cap_truncated"] = capture("cap_truncated")
    raw = (cap / first).read_bytes()
    (paths["cap_truncated"] / first).write_bytes(raw[: len(raw) // 3])
    paths["cap_text_image"] = capture("cap_text_image")
    (paths["cap_text_image"] / first).write_text("not an image")
    # A truncated tracked mesh sequence
    seq = _linked_copy(cap, root / "cap_seq", copy=("subject/sequence.npz",))
    raw = (cap / "subject" / "sequence.npz").read_bytes()
    (seq / "subject" / "sequence.npz").write_bytes(raw[: len(raw) // 2])
    paths["cap_seq"] = seq
    # Tracked meshes with zero normals, and with vertex positions stored as strings
    arrays = dict(np.load(cap / "subject" / "sequence.npz"))
    for name, edit in (
        ("cap_seq_normals", {"normals": np.zeros_like(arrays["normals"])}),
        ("cap_seq_strings", {"vertices": arrays["vertices"].astype(str)}),
    ):
        folder = _linked_copy(cap, root / name, copy=("subject/sequence.npz",))
        np.savez(folder / "subject" / "sequence.npz", **{**arrays, **edit})
        paths[name] = folder

    # Fits: a NaN albedo, a wrong-size roughness, a missing one
    for name, edit in (
        ("fit_nan", lambda f: write_exr(f / "albedo.exr", np.full((32, 32, 3), np.nan, np.float32))),
        ("fit_size", lambda f: write_exr(f / "roughness.exr", np.full((7, 9, 1), 0.5, np.float32))),
        ("fit_missing", lambda f: (f / "roughness.exr").unlink()),
    ):
        folder = _linked_copy(fit, root / name, copy=("albedo.exr", "roughness.exr"))
        edit(folder)
        paths[name] = folder

    # Envmaps, patterns, textures, masks
    write_exr(root / "nan.exr", np.where(np.arange(16 * 32 * 3).reshape(16, 32, 3) == 5, np.nan, 1).astype(np.float32))
    write_exr(root / "square.exr", np.ones((8, 8, 3), np.float32))
    write_exr(root / "white.exr", np.ones((8, 16, 3), np.float32))
    write_exr(root / "sub" / "white.exr", np.full((8, 16, 3), 2.0, np.float32))
    write_exr(root / "albedo_nan.exr", np.full((16, 16, 3), np.nan, np.float32))
    write_exr(root / "albedo_rect.exr", np.full((16, 8, 3), 0.5, np.float32))
    write_exr(root / "albedo.exr", np.full((16, 16, 3), 0.5, np.float32))
    write_exr(root / "one_texel.exr", np.full((1, 1, 3), 0.5, np.float32))  # no texel centre inside a body's UV layout
    write_exr(root / "mask.exr", np.ones((16, 16, 1), np.float32))
    (root / "not_exr.exr").write_text("hello")
    (root / "pattern_strings.json").write_text(json.dumps({"intensities": ["a"] * 64}))
    (root / "pattern_ragged.json").write_text(json.dumps({"intensities": [[1, 2, 3], [1, 2]] + [[0, 0, 0]] * 62}))
    (root / "pattern_short.json").write_text(json.dumps({"intensities": [0.1] * 5}))
    (root / "pattern_nan.json").write_text('{"intensities": [NaN' + ", 0.1" * 63 + "]}")
    (root / "pattern_negative.json").write_text(json.dumps({"intensities": [-1.0] * 64}))
    (root / "pattern_huge.json").write_text(json.dumps({"intensities": [1e30] * 64}))  # beyond float32 once × W/sr
    np.save(root / "pattern_complex.npy", np.ones((64, 3), np.complex64))
    (root / "pattern_binary.json").write_bytes(b"v/1\x01\x80\xff" * 8)  # an image named .json
    (root / "pattern_twice.json").write_text('{"intensities": [0.1], "intensities": [0.2]}')
    (root / "pattern_no_key.json").write_text(json.dumps({"leds": [0.1] * 64}))
    (root / "pattern_off.json").write_text(json.dumps({"intensities": [0.0] * 64}))
    np.save(root / "pattern_3d.npy", np.ones((2, 64, 3)))
    (root / "broken.xml").write_text("<scene version='3.0.0'><shape")
    (root / "calib_broken.json").write_text("{ nope")
    (root / "calib_fields.json").write_text(json.dumps({"leds": "many"}))
    (root / "a_file").write_text("I am a file, not a folder")
    # Frames to deflicker: good ones, one with a NaN, one of another size (the third: found after two good ones)
    for folder, edit in (("defl_frames", None), ("defl_stable", None), ("defl_nan", "nan"), ("defl_size", "size")):
        for k in range(3):
            frame = np.full((8, 8, 4), 0.5, np.float32)
            if k == 2 and edit == "nan":
                frame[3, 3, 1] = np.nan
            if k == 2 and edit == "size":
                frame = frame[:6]
            write_exr(root / folder / f"frame_{k:04d}.exr", frame)
    # Rigs: every LED at one point, an absurd image size, a calibration that its scene's LED XML disagrees with
    calib = json.loads((SCENES / "rigs" / "tiny" / "calibration.json").read_text())
    one_point = {**calib, "leds": [{**led, "position": calib["leds"][0]["position"]} for led in calib["leds"]]}
    (root / "calib_one_point.json").write_text(json.dumps(one_point))
    huge = {**calib, "cameras": [{**calib["cameras"][0], "image_size": [2_000_000, 1_000_000]}]}
    (root / "calib_huge.json").write_text(json.dumps(huge))
    moved = _linked_copy(SCENES, root / "scenes_moved", copy=("rigs/tiny/calibration.json",))
    shifted = json.loads(json.dumps(calib))
    shifted["leds"][3]["position"][0] += 0.05  # one LED moved 5 cm in the calibration only
    (moved / "rigs" / "tiny" / "calibration.json").write_text(json.dumps(shifted))
    # Weights: a RelightNet folder whose safetensors is truncated, one whose config is not a RelightNet's
    rn = root / "rn_truncated"
    rn.mkdir()
    (rn / "relightnet.json").write_text(json.dumps({"format": "gra-mi-relightnet/2", "base_channels": 8}))
    (rn / "relightnet.safetensors").write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{")
    rn = root / "rn_config"
    rn.mkdir()
    (rn / "relightnet.json").write_text("[1, 2")
    (rn / "relightnet.safetensors").write_bytes(b"")
    rn = root / "rn_types"
    rn.mkdir()
    (rn / "relightnet.json").write_text(json.dumps({"format": "gra-mi-relightnet/2", "base_channels": "16"}))
    rn = root / "rn_empty"
    rn.mkdir()
    (rn / "relightnet.json").write_text(json.dumps({"format": "gra-mi-relightnet/2"}))
    (rn / "relightnet.safetensors").write_bytes(b"")
    rn = root / "rn_format_2"  # what gra-mi wrote before the format became a string: named, with the fix
    rn.mkdir()
    (rn / "relightnet.json").write_text(json.dumps({"format": 2}))
    (rn / "relightnet.safetensors").write_bytes(b"")
    (rn / "relightnet.safetensors").write_bytes(b"")
    # Refiner data (a tiny synthetic set) and broken copies of its dataset.json; refiner folders with a bad refiner.json
    from gra_mi.refiner.synthetic import synthetic_dataset

    synthetic_dataset(root / "rd", {0: (1, 1)}, frames=5, height=16, width=16, env_height=4, test_frames=5)
    good = json.loads((root / "rd" / "dataset.json").read_text())
    for name, edit in {
        "rd_list": lambda d: [d],
        "rd_height": lambda d: {**d, "height": 20},
        "rd_exposure": lambda d: {**d, "exposure": "bright"},
        "rd_frames": lambda d: {**d, "sequences": [{**d["sequences"][0], "frames": 0}] + d["sequences"][1:]},
        "rd_split": lambda d: {**d, "sequences": [{**d["sequences"][0], "split": "val"}] + d["sequences"][1:]},
        "rd_twice": lambda d: {**d, "sequences": d["sequences"] + d["sequences"][:1]},
        "rd_box": lambda d: {**d, "frame": [16, 16], "sequences": [{**d["sequences"][0], "box": [4, 4, 2, 9]}] + d["sequences"][1:]},
        "rd_box_frame": lambda d: {**d, "sequences": [{**d["sequences"][0], "box": [0, 0, 4, 4]}] + d["sequences"][1:]},
    }.items():
        folder = _linked_copy(root / "rd", root / name, copy=("dataset.json",))
        (folder / "dataset.json").write_text(json.dumps(edit(json.loads(json.dumps(good)))))
        paths[name] = folder
    seq = _linked_copy(root / "rd", root / "rd_truncated", copy=(good["sequences"][0]["file"],))
    (seq / good["sequences"][0]["file"]).write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{")
    paths["rd_truncated"], paths["rd_first"] = seq, good["sequences"][0]["name"]
    # A sequence file without its envmaps, and a dataset.json that claims more frames than the file holds
    from safetensors.torch import load_file, save_file

    first_file = good["sequences"][0]["file"]
    noenv = _linked_copy(root / "rd", root / "rd_noenv", copy=(first_file,))
    save_file({k: v for k, v in load_file(str(root / "rd" / first_file)).items() if k != "env"}, str(noenv / first_file))
    more = _linked_copy(root / "rd", root / "rd_more", copy=("dataset.json",))
    (more / "dataset.json").write_text(json.dumps({**good, "sequences": [{**good["sequences"][0], "frames": 99}] + good["sequences"][1:]}))
    paths["rd_noenv"], paths["rd_more"] = noenv, more
    # A run folder (as `gra-mi demo` lays it out) whose fit lost its roughness map
    (root / "run_broken").mkdir()
    (root / "run_broken" / "capture").symlink_to(cap)
    (root / "run_broken" / "fit").symlink_to(paths["fit_missing"])
    paths["run_broken"] = root / "run_broken"
    # A RelightNet of another UV resolution than the shared fit's
    from gra_mi.relightnet.model import RelightNet, RelightNetConfig

    RelightNet(RelightNetConfig(resolution=64, base_channels=4)).save(root / "rn_64")
    models = {
        "model_window": {"format": "gra-mi-refiner/1", "window": "17"},
        "model_unknown": {"format": "gra-mi-refiner/1", "colour": 1},
        "model_list": [1, 2],
        "model_residual": {"format": "gra-mi-refiner/1", "residual_scale": -0.1},
    }
    for name, text in models.items():
        (root / name).mkdir()
        (root / name / "refiner.json").write_text(json.dumps(text))
        (root / name / "refiner.safetensors").write_bytes(b"")
    return paths


# --------------------------------------------------------------------------------------------------------------
# Family 1: bad numbers, options out of range
# --------------------------------------------------------------------------------------------------------------

RN = ["train-relightnet", "{cap}", "--fit", "{fit}"]
REFINE = ["refine", "{root}/nodata", "--model", "{root}/nomodel", "--sequence", "s"]  # options are checked before files
RD = ["refiner-data", "{cap}", "--fit", "{fit}"]
TR = ["train-refiner", "{root}/nodata"]
EDIT = ["edit-texture", "--albedo", "{root}/albedo.exr", "--mask", "{root}/mask.exr"]

OPTION_CASES = [
    # fit
    ("fit-iterations", ["fit", "{cap}", "--iterations", "-1"], ["--iterations", ">= 0"]),
    ("fit-irls", ["fit", "{cap}", "--irls-iterations", "-1"], ["--irls-iterations"]),
    ("fit-uv-zero", ["fit", "{cap}", "--uv-resolution", "0"], ["--uv-resolution"]),
    ("fit-uv-negative", ["fit", "{cap}", "--uv-resolution", "-8"], ["--uv-resolution"]),
    ("fit-lr-nan", ["fit", "{cap}", "--lr-albedo", "nan"], ["--lr-albedo", "finite"]),
    ("fit-lr-negative", ["fit", "{cap}", "--lr-roughness", "-1"], ["--lr-roughness"]),
    ("fit-smooth-nan", ["fit", "{cap}", "--smooth-albedo", "nan"], ["--smooth-albedo"]),
    ("fit-smooth-negative", ["fit", "{cap}", "--smooth-roughness", "-0.1"], ["--smooth-roughness"]),
    ("fit-min-view-cos", ["fit", "{cap}", "--min-view-cos", "2"], ["--min-view-cos"]),
    ("fit-min-view-cos-inf", ["fit", "{cap}", "--min-view-cos", "inf"], ["--min-view-cos"]),
    ("fit-candidates-empty", ["fit", "{cap}", "--roughness-candidates", ""], ["--roughness-candidates"]),
    ("fit-candidates-nan", ["fit", "{cap}", "--roughness-candidates", "0.3,nan"], ["--roughness-candidates"]),
    ("fit-candidates-range", ["fit", "{cap}", "--roughness-candidates", "0.3,1.5"], ["--roughness-candidates"]),
    ("fit-candidates-text", ["fit", "{cap}", "--roughness-candidates", "rough"], ["--roughness-candidates"]),
    ("fit-iterations-text", ["fit", "{cap}", "--iterations", "many"], ["--iterations"]),
    # relight
    ("relight-uv-zero", ["relight", TINY, "--olat", "0", "--uv-resolution", "0"], ["--uv-resolution"]),
    ("relight-uv-negative", ["relight", TINY, "--olat", "0", "--uv-resolution", "-3"], ["--uv-resolution"]),
    ("relight-uv-tiny", ["relight", TINY, "--olat", "0", "--uv-resolution", "4"], ["--uv-resolution", ">= 8"]),
    ("relight-albedo-one-texel", ["relight", TINY, "--olat", "0", "--albedo", "{root}/one_texel.exr"], ["--albedo", "no texel centre"]),
    ("relight-exposure-nan", ["relight", TINY, "--olat", "0", "--exposure", "nan"], ["--exposure"]),
    ("relight-exposure-zero", ["relight", TINY, "--olat", "0", "--exposure", "0"], ["--exposure"]),
    ("relight-no-light", ["relight", TINY], ["--envmap"]),
    ("relight-point-nan", ["relight", TINY, "--point-light", "nan,0,0"], ["--point-light"]),
    ("relight-point-count", ["relight", TINY, "--point-light", "1,2"], ["--point-light"]),
    ("relight-point-intensity", ["relight", TINY, "--point-light", "0,1,1", "--point-light-intensity", "-2"], ["--point-light-intensity"]),
    (
        "relight-point-intensity-nan",
        ["relight", TINY, "--point-light", "0,1,1", "--point-light-intensity", "nan"],
        ["--point-light-intensity"],
    ),
    ("relight-point-radius", ["relight", TINY, "--point-light", "0,1,1", "--point-light-radius", "-1"], ["--point-light-radius"]),
    ("relight-frames", ["relight", TINY, "--olat", "0", "--frames", "99"], ["frame", "99"]),
    ("relight-frames-text", ["relight", TINY, "--olat", "0", "--frames", "a:b"], ["--frames"]),
    ("relight-frames-item", ["relight", TINY, "--olat", "0", "--frames", "1,x"], ["--frames", "1,x"]),
    ("relight-frames-empty", ["relight", TINY, "--olat", "0", "--frames", "5:2"], ["--frames", "selects nothing"]),
    ("relight-cameras-empty", ["relight", TINY, "--olat", "0", "--cameras", ","], ["--cameras", "selects nothing"]),
    (
        "relight-envmap-same-name",
        ["relight", TINY, "--envmap", "{root}/white.exr", "--envmap", "{root}/sub/white.exr"],
        ["white.exr", "sub/white.exr", "both named 'white'"],
    ),
    ("render-variant-scalar", ["render", TINY, "--olat", "0", "--variant", "scalar_rgb"], ["--variant", "scalar_rgb"]),
    ("relight-camera", ["relight", TINY, "--olat", "0", "--cameras", "nope"], ["nope"]),
    ("relight-olat", ["relight", TINY, "--olat", "999"], ["999"]),
    ("relight-olat-negative", ["relight", TINY, "--olat", "-1"], ["-1"]),
    ("relight-envmap-height", ["relight", TINY, "--olat", "0", "--envmap-height", "1"], ["--envmap-height"]),
    ("relight-envmap-rotate", ["relight", TINY, "--olat", "0", "--envmap-rotate", "nan"], ["--envmap-rotate"]),
    ("relight-platform-spp", ["relight", TINY, "--olat", "0", "--platform-spp", "0"], ["--platform-spp"]),
    ("relight-platform-radius", ["relight", TINY, "--olat", "0", "--platform-radius", "-1"], ["--platform-radius"]),
    ("relight-platform-reflectance", ["relight", TINY, "--olat", "0", "--platform-reflectance", "1.5"], ["--platform-reflectance"]),
    ("relight-bounce-rays-alone", ["relight", TINY, "--olat", "0", "--bounce-rays", "64"], ["--bounce-rays", "--bounces 2"]),
    ("fit-bounce-smoothing-alone", ["fit", "{cap}", "--bounce-smoothing", "3"], ["--bounce-smoothing", "--bounces 2"]),
    ("relight-platform-alone", ["relight", TINY, "--olat", "0", "--platform-radius", "2"], ["--platform-radius", "with --composite only"]),
    ("relight-relightnet-missing", ["relight", TINY, "--olat", "0", "--stage", "relightnet"], ["--relightnet"]),
    # render
    ("render-seed", ["render", TINY, "--olat", "0", "--seed", "-5"], ["--seed"]),
    ("render-spp", ["render", TINY, "--olat", "0", "--spp", "-5"], ["--spp"]),
    ("render-spp-zero", ["render", TINY, "--olat", "0", "--spp", "0"], ["--spp"]),
    ("render-frame", ["render", TINY, "--olat", "0", "--frame", "50"], ["frame 50"]),
    ("render-frame-negative", ["render", TINY, "--olat", "0", "--frame", "-1"], ["frame -1"]),
    ("render-camera", ["render", TINY, "--olat", "0", "--camera", "nope"], ["nope"]),
    ("render-camera-index", ["render", TINY, "--olat", "0", "--camera", "77"], ["77"]),
    ("render-olat", ["render", TINY, "--olat", "999"], ["999"]),
    ("render-no-light", ["render", TINY], ["--envmap"]),
    ("render-integrator", ["render", TINY, "--olat", "0", "--integrator", "volpath"], ["--integrator"]),
    # rig
    ("rig-radius-nan", ["rig", "--radius", "nan"], ["--radius"]),
    ("rig-radius-negative", ["rig", "--radius", "-1"], ["--radius"]),
    ("rig-leds", ["rig", "--num-leds", "0"], ["--num-leds"]),
    ("rig-cameras", ["rig", "--num-cameras", "0"], ["--num-cameras"]),
    ("rig-distance", ["rig", "--camera-distance", "0"], ["--camera-distance"]),
    ("rig-width", ["rig", "--width", "0"], ["--width"]),
    ("rig-height", ["rig", "--height", "-2"], ["--height"]),
    ("rig-intensity", ["rig", "--max-led-intensity", "inf"], ["--max-led-intensity"]),
    ("rig-calibration-missing", ["rig", "--from-calibration", "{root}/nope.json"], ["nope.json", "not found"]),
    ("rig-calibration-broken", ["rig", "--from-calibration", "{root}/calib_broken.json"], ["calib_broken.json", "malformed JSON"]),
    ("rig-calibration-fields", ["rig", "--from-calibration", "{root}/calib_fields.json"], ["calib_fields.json"]),
    ("rig-leds-one-point", ["rig", "--from-calibration", "{root}/calib_one_point.json"], ["calib_one_point.json", "same position"]),
    ("rig-image-size-absurd", ["rig", "--from-calibration", "{root}/calib_huge.json"], ["calib_huge.json", "image_size"]),
    ("rig-leds-beyond-memory", ["rig", "--num-leds", "100000000"], ["--num-leds", "GiB"]),
    (
        "rig-layout-with-calibration",
        ["rig", "--from-calibration", "{cap}/rig/calibration.json", "--num-leds", "5"],
        ["--num-leds", "--from-calibration"],
    ),
    ("scene-calibration-disagrees", ["relight", "{root}/scenes_moved/tiny_lightstage.xml", "--olat", "0"], ["LED 3", "calibration"]),
    # scene, subject, envmaps
    ("scene-spp", ["scene", "--rig", "{cap}/rig", "--subject", "{cap}/subject", "--spp", "-5"], ["--spp"]),
    ("scene-rig-missing", ["scene", "--rig", "{root}/nope", "--subject", "{cap}/subject"], ["nope"]),
    ("scene-subject-missing", ["scene", "--rig", "{cap}/rig", "--subject", "{root}/nope"], ["nope"]),
    ("subject-frames", ["subject", "--kind", "tiny", "--frames", "0"], ["--frames"]),
    ("subject-frames-per-clip", ["subject", "--frames-per-clip", "0"], ["--frames-per-clip"]),
    ("subject-clip", ["subject", "--clips", "moonwalk"], ["moonwalk"]),
    ("subject-tiny-clips", ["subject", "--kind", "tiny", "--clips", "walk"], ["--clips", "--kind tiny"]),
    ("subject-anny-frames", ["subject", "--frames", "3"], ["--frames", "--kind anny"]),
    ("subject-tiny-memory", ["subject", "--kind", "tiny", "--frames", "100000000"], ["--frames", "GiB"]),
    ("envmaps-train", ["envmaps", "--train", "-1"], ["--train"]),
    ("envmaps-height", ["envmaps", "--height", "1"], ["--height"]),
    # capture
    ("capture-spp", ["capture", "--preset", "tiny", "--spp", "0"], ["--spp"]),
    ("capture-spp-power", ["capture", "--preset", "tiny", "--spp", "5"], ["--spp"]),
    ("capture-indirect-spp", ["capture", "--preset", "tiny", "--indirect-spp", "-4"], ["--indirect-spp"]),
    ("capture-without", ["capture", "--preset", "tiny", "--without", "gravity"], ["gravity"]),
    ("capture-test-envmap", ["capture", "--preset", "tiny", "--test-envmap", "{root}/nan.exr"], ["nan.exr", "NaN"]),
    ("capture-preset", ["capture", "--preset", "huge"], ["--preset"]),
    ("capture-lightings-olat", ["capture", "--preset", "olat", "--training-lightings", "64"], ["--training-lightings", "OLATs"]),
    ("capture-lightings-zero", ["capture", "--preset", "tiny", "--training-lightings", "0"], ["--training-lightings", ">= 1"]),
    ("capture-lightings-memory", ["capture", "--preset", "small", "--training-lightings", "10000000"], ["--training-lightings", "GiB"]),
    ("capture-spp-huge", ["capture", "--preset", "tiny", "--indirect-spp", "4194304"], ["--indirect-spp", "up to 1048576"]),
    ("capture-margin-unframed", ["capture", "--preset", "tiny", "--framing-margin", "0.1"], ["--framing-margin", "not framed"]),
    ("capture-margin-too-wide", ["capture", "--preset", "small", "--framing-margin", "0.5"], ["--framing-margin", "[0, 0.5)"]),
    # train-relightnet
    ("rn-steps", [*RN, "--steps", "0"], ["--steps"]),
    ("rn-lr", [*RN, "--lr", "nan"], ["--lr"]),
    ("rn-batch", [*RN, "--batch-size", "0"], ["--batch-size"]),
    ("rn-dropout", [*RN, "--env-dropout", "1.5"], ["--env-dropout"]),
    ("rn-dropout-nan", [*RN, "--env-dropout", "nan"], ["--env-dropout"]),
    ("rn-validate-every", [*RN, "--validate-every", "0"], ["--validate-every"]),
    ("rn-env-height-memory", [*RN, "--env-height", "100000"], ["--env-height", "GiB"]),
    ("rn-base-channels-wide", [*RN, "--base-channels", "1000"], ["--base-channels", "at most 128"]),
    ("rn-checkpoint-every", [*RN, "--checkpoint-every", "0"], ["--checkpoint-every"]),
    ("rn-channels", [*RN, "--base-channels", "0"], ["--base-channels"]),
    ("rn-patch", [*RN, "--patch", "-1"], ["--patch"]),
    ("rn-env-height", [*RN, "--env-height", "1"], ["--env-height"]),
    ("rn-views", [*RN, "--max-train-views", "0"], ["--max-train-views"]),
    ("rn-loss", [*RN, "--loss", "perceptual"], ["--loss", "display"]),
    ("rn-lightings-zero", [*RN, "--training-lightings", "0"], ["--training-lightings"]),
    ("rn-lightings-too-many", [*RN, "--training-lightings", "999"], ["--training-lightings", "asked for 999"]),
    ("rn-seed", [*RN, "--seed", "-1"], ["--seed"]),
    ("rn-weight-decay", [*RN, "--weight-decay", "-1"], ["--weight-decay"]),
    # refiner
    ("rd-scale", [*RD, "--scale", "0"], ["--scale"]),
    ("rd-scale-nan", [*RD, "--scale", "nan"], ["--scale"]),
    ("rd-train-length", [*RD, "--train-length", "0"], ["--train-length"]),
    ("rd-env-height", [*RD, "--env-height", "0"], ["--env-height"]),
    ("rd-train-cameras-zero", [*RD, "--train-cameras", "0"], ["--train-cameras"]),
    ("rd-train-cameras-too-many", [*RD, "--train-cameras", "99"], ["--train-cameras", "asked for 99"]),
    ("rd-zoom", [*RD, "--zoom", "0.5"], ["--zoom"]),
    ("rd-zoom-nan", [*RD, "--zoom", "nan"], ["--zoom"]),
    ("rd-resolution", ["refiner-data", "--synthetic", "--resolution", "20"], ["--resolution"]),
    ("rd-subjects", ["refiner-data", "--synthetic", "--subjects", "0"], ["--subjects"]),
    ("rd-no-fit", ["refiner-data", "{cap}"], ["--fit"]),
    ("tr-grad-accumulation", [*TR, "--grad-accumulation", "0"], ["--grad-accumulation"]),
    ("tr-steps", [*TR, "--steps", "0"], ["--steps"]),
    ("tr-lr", [*TR, "--lr", "nan"], ["--lr"]),
    ("tr-checkpoint-every", [*TR, "--checkpoint-every", "0"], ["--checkpoint-every"]),
    ("tr-lora-rank", [*TR, "--lora-rank", "-1"], ["--lora-rank"]),
    ("tr-bank", [*TR, "--bank-per-level", "0"], ["--bank-per-level"]),
    ("tr-env-blocks", [*TR, "--env-blocks", "one"], ["--env-blocks"]),
    ("tr-seed", [*TR, "--seed", "-3"], ["--seed"]),
    ("tr-selection-steps", [*TR, "--selection-steps", "0"], ["--selection-steps"]),
    ("tr-data-missing", ["train-refiner", "{root}/nodata"], ["nodata"]),
    ("tr-lora-rank-wide", [*TR, "--lora-rank", "100000"], ["--lora-rank", "[0, 256]"]),
    ("tr-tiny-vae-weights", [*TR, "--vae-weights", "{root}/albedo.exr"], ["--vae-weights", "real sizes"]),
    ("tr-weights-missing", [*TR, "--size", "1.3B", "--weights", "{root}/noweights"], ["noweights"]),
    ("refine-shift-nan", [*REFINE, "--shift", "nan"], ["--shift"]),
    ("refine-shift-zero", [*REFINE, "--shift", "0"], ["--shift"]),
    ("refine-steps", [*REFINE, "--steps", "0"], ["--steps"]),
    ("refine-denoise", [*REFINE, "--denoise", "1.5"], ["--denoise"]),
    ("refine-denoise-nan", [*REFINE, "--denoise", "nan"], ["--denoise"]),
    ("refine-mix", [*REFINE, "--mix", "1.5"], ["--mix"]),
    ("refine-mix-nan", [*REFINE, "--mix", "nan"], ["--mix"]),
    ("refine-frames", [*REFINE, "--frames", "-1"], ["--frames"]),
    ("refine-seed", [*REFINE, "--seed", "-1"], ["--seed"]),
    ("refiner-data-synthetic-option", ["refiner-data", "{cap}", "--fit", "{fit}", "--subjects", "3"], ["--subjects", "--synthetic only"]),
    ("refiner-data-capture-option", ["refiner-data", "--synthetic", "--zoom", "2"], ["--zoom", "--synthetic makes its own"]),
    ("refiner-data-synthetic-capture", ["refiner-data", "{cap}", "--synthetic"], ["--synthetic", "drop the capture"]),
    ("refiner-data-synthetic-memory", ["refiner-data", "--synthetic", "--resolution", "100000"], ["--resolution", "GiB"]),
    ("refiner-data-memory", ["refiner-data", "{cap}", "--fit", "{fit}", "--zoom", "1000"], ["sequences", "GiB"]),
    ("refine-filter-alone", [*REFINE, "--filter-radius", "8"], ["--filter-radius", "with --deflicker only"]),
    ("refine-platform-alone", [*REFINE, "--platform-spp", "4"], ["--platform-spp", "with --composite only"]),
    (
        "refine-eps",
        [*REFINE, "--deflicker", "--filter-eps", "nan"],
        ["--filter-eps"],
    ),
    (
        "refine-radius",
        [*REFINE, "--deflicker", "--filter-radius", "0"],
        ["--filter-radius"],
    ),
    (
        "refine-strength",
        [*REFINE, "--deflicker", "--strength", "2"],
        ["--strength"],
    ),
    (
        "refine-platform",
        [*REFINE, "--composite", "--platform-spp", "0"],
        ["--platform-spp"],
    ),
    ("refine-model-missing", ["refine", "{root}/nodata", "--model", "{root}/nomodel", "--sequence", "s"], ["no"]),
    # edit-texture, export, deflicker, eval
    ("edit-color-nan", [*EDIT, "--color", "nan,0,0"], ["--color"]),
    ("edit-color-count", [*EDIT, "--color", "1,0"], ["--color"]),
    ("edit-color-range", [*EDIT, "--color", "2,0,0"], ["--color"]),
    (
        "edit-opacity",
        [*EDIT, "--color", "1,0,0", "--opacity", "nan"],
        ["--opacity"],
    ),
    ("edit-nothing", ["edit-texture", "--albedo", "{root}/albedo.exr"], ["--image"]),
    (
        "edit-layer-nan",
        ["edit-texture", "--albedo", "{root}/albedo.exr", "--image", "{root}/albedo_nan.exr"],
        ["albedo_nan.exr", "non-finite"],
    ),
    (
        "edit-albedo-nan",
        ["edit-texture", "--albedo", "{root}/albedo_nan.exr", "--mask", "{root}/mask.exr", "--color", "1,0,0"],
        ["albedo_nan.exr"],
    ),
    (
        "edit-albedo-rect",
        ["edit-texture", "--albedo", "{root}/albedo_rect.exr", "--mask", "{root}/mask.exr", "--color", "1,0,0"],
        ["albedo_rect.exr"],
    ),
    (
        "edit-mask-missing",
        ["edit-texture", "--albedo", "{root}/albedo.exr", "--mask", "{root}/nomask.exr", "--color", "1,0,0"],
        ["nomask.exr"],
    ),
    (
        "edit-albedo-not-exr",
        ["edit-texture", "--albedo", "{root}/not_exr.exr", "--mask", "{root}/mask.exr", "--color", "1,0,0"],
        ["not_exr.exr"],
    ),
    (
        "gltf-frames",
        [
            "export",
            "--subject",
            "{cap}/subject",
            "--albedo",
            "{fit}/albedo.exr",
            "--roughness",
            "{fit}/roughness.exr",
            "--frames",
            "0",
        ],
        ["--frames"],
    ),
    (
        "gltf-subject",
        [
            "export",
            "--subject",
            "{root}/nosubject",
            "--albedo",
            "{fit}/albedo.exr",
            "--roughness",
            "{fit}/roughness.exr",
        ],
        ["nosubject"],
    ),
    ("deflicker-eps", ["deflicker", "{root}", "--stable", "{root}", "--filter-eps", "-1"], ["--filter-eps"]),
    ("deflicker-exposure", ["deflicker", "{root}", "--stable", "{root}", "--exposure", "nan"], ["--exposure"]),
    ("deflicker-missing", ["deflicker", "{root}/noframes", "--stable", "{root}"], ["noframes"]),
    ("deflicker-nan", ["deflicker", "{root}/defl_nan", "--stable", "{root}/defl_stable"], ["frame_0002.exr", "non-finite"]),
    ("deflicker-size-late", ["deflicker", "{root}/defl_size", "--stable", "{root}/defl_stable"], ["frame_0002.exr", "8×8"]),
    ("eval-scale", ["eval", "--capture", "{cap}", "--fit", "{fit}", "--scale", "0"], ["--scale"]),
    ("eval-lighting-maps-twice", ["eval-lighting", "{cap}", "--fit", "{fit}", "--maps", "sun,night,sun"], ["--maps", "'sun' given twice"]),
    ("eval-lighting-spp", ["eval-lighting", "{cap}", "--fit", "{fit}", "--spp", "99999999999"], ["--spp", "1048576"]),
    ("eval-lighting-map-memory", ["eval-lighting", "{cap}", "--fit", "{fit}", "--map-height", "100000"], ["--map-height", "GiB"]),
    ("fit-cameras-twice", ["fit", "{cap}", "--cameras", "cam00,cam01,cam00"], ["--cameras", "'cam00' given twice"]),
    ("eval-frames", ["eval", "--capture", "{cap}", "--fit", "{fit}", "--frames", "some"], ["--frames"]),
    ("eval-nothing", ["eval", "--fit", "{fit}"], ["--capture"]),
    ("eval-platform-alone", ["eval", "--capture", "{cap}", "--fit", "{fit}", "--platform-spp", "4"], ["--platform-spp", "--composite"]),
    ("eval-lighting-spp", ["eval-lighting", "{cap}", "--fit", "{fit}", "--spp", "0"], ["--spp"]),
    ("demo-preset", ["demo", "--preset", "huge"], ["--preset"]),
    ("variant-cuda", ["render", TINY, "--olat", "0", "--variant", "cuda_ad_rgb"], ["cuda"]),
    ("device-bogus", ["relight", TINY, "--olat", "0", "--device", "tpu:7"], ["--device"]),
]


def _fill(argv, paths: dict) -> list[str]:
    return [str(a).format(**paths) for a in argv]


FILE_OUTPUTS = {"scene": ".xml", "edit-texture": ".exr", "export": ".glb", "refiner-prompt": ".safetensors"}


@pytest.mark.parametrize("argv,needles", [pytest.param(a, n, id=i) for i, a, n in OPTION_CASES])
def test_bad_option(argv, needles, inputs, capsys, tmp_path, llvm_variant):
    out = tmp_path / ("out" + FILE_OUTPUTS.get(argv[0], ""))  # a command whose --out is one file: its format's name
    from gra_mi.core.runtime import cuda_available

    if "cuda_ad_rgb" in argv and cuda_available():
        pytest.skip("a CUDA device works here")
    assert_refused(_fill(argv, inputs) + ["--out", out], capsys, *needles, out=out)


# --------------------------------------------------------------------------------------------------------------
# Family 1: bad data in files (captures, fits, envmaps, patterns, textures, weights)
# --------------------------------------------------------------------------------------------------------------

DATA_CASES = [
    ("image-all-nan", ["fit", "{cap_nan}"], ["frame_0001.exr", "NaN"]),
    ("image-one-nan", ["fit", "{cap_one_nan}"], ["frame_0001.exr", "1 NaN"]),
    ("image-negative", ["fit", "{cap_negative}"], ["frame_0001.exr", "negative"]),
    ("image-inf", ["fit", "{cap_inf}"], ["frame_0001.exr", "inf"]),
    ("image-half-size", ["fit", "{cap_half}"], ["frame_0001.exr", "160x120", "320x240"]),
    ("image-rgb", ["fit", "{cap_rgb}"], ["frame_0001.exr", "RGBA"]),
    ("image-mask-range", ["fit", "{cap_mask}"], ["frame_0001.exr", "alpha"]),
    ("image-missing", ["fit", "{cap_missing_image}"], ["frame_0001.exr", "not found"]),
    ("image-truncated", ["fit", "{cap_truncated}"], ["frame_0001.exr", "OpenEXR"]),
    ("image-text", ["fit", "{cap_text_image}"], ["frame_0001.exr", "OpenEXR"]),
    ("image-nan-relightnet", ["train-relightnet", "{cap_nan}", "--fit", "{fit}"], ["frame_0001.exr", "NaN"]),
    ("image-half-refiner-data", ["refiner-data", "{cap_half}", "--fit", "{fit}"], ["frame_0001.exr", "320x240"]),
    ("sequence-truncated", ["fit", "{cap_seq}"], ["sequence.npz"]),
    ("sequence-zero-normals", ["fit", "{cap_seq_normals}"], ["sequence.npz", "normals", "zero-length"]),
    ("sequence-string-vertices", ["fit", "{cap_seq_strings}"], ["sequence.npz", "vertices", "dtype"]),
    ("capture-json-broken", ["fit", "{cap_json_broken}"], ["capture.json", "malformed JSON"]),
    ("capture-json-format", ["fit", "{cap_json_format}"], ["capture.json", "format"]),
    ("capture-json-missing", ["fit", "{cap_json_missing}"], ["capture.json", "frames", "missing"]),
    ("capture-json-frame-str", ["fit", "{cap_json_frame_str}"], ["capture.json", "frames[0]"]),
    ("capture-json-frame-num", ["fit", "{cap_json_frame_num}"], ["capture.json", "frames[0]", "frame"]),
    ("capture-json-kind", ["fit", "{cap_json_kind}"], ["capture.json", "frames[0]", "disco"]),
    ("capture-json-split", ["fit", "{cap_json_split}"], ["capture.json", "frames[0]", "val"]),
    ("capture-json-cameras", ["fit", "{cap_json_cameras}"], ["capture.json", "train_cameras", "list of camera names"]),
    ("capture-json-camera-name", ["fit", "{cap_json_camera_name}"], ["capture.json", "eval_cameras", "cam99"]),
    ("capture-json-uv", ["fit", "{cap_json_uv}"], ["capture.json", "uv_resolution"]),
    ("capture-json-uv-negative", ["fit", "{cap_json_uv_neg}"], ["capture.json", "uv_resolution"]),
    ("capture-json-unknown", ["fit", "{cap_json_unknown}"], ["capture.json", "calibration_date"]),
    ("capture-json-list", ["fit", "{cap_json_list}"], ["capture.json", "object"]),
    ("capture-json-duplicate", ["fit", "{cap_json_dup}"], ["capture.json", "frame 0", "twice"]),
    ("capture-missing", ["fit", "{root}/nocapture"], ["nocapture", "gra-mi capture"]),
    ("capture-is-file", ["fit", "{root}/a_file"], ["a_file"]),
    ("fit-nan-albedo", ["train-relightnet", "{cap}", "--fit", "{fit_nan}"], ["albedo.exr", "NaN"]),
    ("fit-size-roughness", ["train-relightnet", "{cap}", "--fit", "{fit_size}"], ["roughness.exr"]),
    ("fit-missing-roughness", ["train-relightnet", "{cap}", "--fit", "{fit_missing}"], ["roughness.exr", "not found"]),
    ("fit-missing-eval", ["eval", "--capture", "{cap}", "--fit", "{fit_missing}"], ["roughness.exr"]),
    ("eval-run-with-broken-fit", ["eval", "{run_broken}"], ["roughness.exr"]),
    ("envmap-nan", ["relight", TINY, "--envmap", "{root}/nan.exr"], ["nan.exr", "NaN"]),
    ("envmap-square", ["relight", TINY, "--envmap", "{root}/square.exr"], ["square.exr", "twice as wide"]),
    ("envmap-missing", ["relight", TINY, "--envmap", "{root}/none.exr"], ["none.exr", "not found"]),
    ("envmap-not-exr", ["render", TINY, "--envmap", "{root}/not_exr.exr"], ["not_exr.exr"]),
    ("pattern-strings", ["relight", TINY, "--pattern", "{root}/pattern_strings.json"], ["pattern_strings.json", "number"]),
    ("pattern-ragged", ["relight", TINY, "--pattern", "{root}/pattern_ragged.json"], ["pattern_ragged.json"]),
    ("pattern-short", ["render", TINY, "--pattern", "{root}/pattern_short.json"], ["pattern_short.json", "64"]),
    ("pattern-nan", ["relight", TINY, "--pattern", "{root}/pattern_nan.json"], ["pattern_nan.json"]),
    ("pattern-negative", ["relight", TINY, "--pattern", "{root}/pattern_negative.json"], ["pattern_negative.json"]),
    ("pattern-huge", ["relight", TINY, "--pattern", "{root}/pattern_huge.json"], ["pattern_huge.json", "at most"]),
    ("pattern-binary", ["relight", TINY, "--pattern", "{root}/pattern_binary.json"], ["pattern_binary.json", "not UTF-8 text"]),
    (
        "pattern-key-twice",
        ["relight", TINY, "--pattern", "{root}/pattern_twice.json"],
        ["pattern_twice.json", "given twice, with two values"],
    ),
    ("lights-binary", ["relight", TINY, "--lights", "{root}/pattern_binary.json"], ["pattern_binary.json", "not UTF-8 text"]),
    ("pattern-complex", ["relight", TINY, "--pattern", "{root}/pattern_complex.npy"], ["pattern_complex.npy", "complex numbers"]),
    ("pattern-no-key", ["relight", TINY, "--pattern", "{root}/pattern_no_key.json"], ["pattern_no_key.json", "intensities"]),
    ("pattern-3d", ["relight", TINY, "--pattern", "{root}/pattern_3d.npy"], ["pattern_3d.npy"]),
    ("scene-broken", ["relight", "{root}/broken.xml", "--olat", "0"], ["broken.xml", "malformed XML"]),
    ("scene-missing", ["relight", "{root}/noscene.xml", "--olat", "0"], ["noscene.xml"]),
    ("texture-nan", ["relight", TINY, "--olat", "0", "--albedo", "{root}/albedo_nan.exr"], ["albedo_nan.exr"]),
    ("texture-rect", ["relight", TINY, "--olat", "0", "--roughness", "{root}/albedo_rect.exr"], ["albedo_rect.exr"]),
    (
        "relightnet-truncated",
        ["relight", TINY, "--olat", "0", "--stage", "relightnet", "--relightnet", "{root}/rn_truncated"],
        ["rn_truncated", "relightnet.safetensors", "unreadable"],
    ),
    (
        "relightnet-config",
        ["relight", TINY, "--olat", "0", "--stage", "relightnet", "--relightnet", "{root}/rn_config"],
        ["relightnet.json"],
    ),
    ("relightnet-missing", ["relight", TINY, "--olat", "0", "--stage", "relightnet", "--relightnet", "{root}/norn"], ["norn"]),
    (
        "relightnet-types",
        ["relight", TINY, "--olat", "0", "--stage", "relightnet", "--relightnet", "{root}/rn_types"],
        ["base_channels", "integer"],
    ),
    (
        "relightnet-empty-weights",
        ["relight", TINY, "--olat", "0", "--stage", "relightnet", "--relightnet", "{root}/rn_empty"],
        ["relightnet.safetensors", "unreadable"],
    ),
    (
        "relightnet-format-int",
        ["relight", TINY, "--olat", "0", "--stage", "relightnet", "--relightnet", "{root}/rn_format_2"],
        ["relightnet.json", "format", "gra-mi-relightnet/2"],
    ),
    ("refiner-data-list", ["train-refiner", "{rd_list}"], ["dataset.json", "format"]),
    ("refiner-data-height", ["train-refiner", "{rd_height}"], ["dataset.json", "multiples of 16"]),
    ("refiner-data-exposure", ["train-refiner", "{rd_exposure}"], ["dataset.json", "exposure", "finite number"]),
    ("refiner-data-frames", ["train-refiner", "{rd_frames}"], ["dataset.json", "sequences[0].frames"]),
    ("refiner-data-split", ["train-refiner", "{rd_split}"], ["dataset.json", "sequences[0].split"]),
    ("refiner-data-twice", ["train-refiner", "{rd_twice}"], ["dataset.json", "listed twice"]),
    ("refiner-data-box", ["train-refiner", "{rd_box}"], ["dataset.json", "sequences[0].box"]),
    ("refiner-data-box-frame", ["train-refiner", "{rd_box_frame}"], ["dataset.json", "frame"]),
    ("refiner-data-truncated", ["train-refiner", "{rd_truncated}", "--steps", "1"], ["safetensors"]),
    ("refiner-data-no-env", ["train-refiner", "{rd_noenv}", "--steps", "1"], ["missing tensor", "env"]),
    (
        "refiner-data-more-frames",
        ["refine", "{rd_more}", "--model", "{root}/nomodel", "--sequence", "{rd_first}"],
        ["holds 5 frames", "99"],
    ),
    ("refiner-data-relightnet-size", [*RD, "--relightnet", "{root}/rn_64"], ["relightnet.json", "64²", "32²"]),
    (
        "refiner-json-types",
        ["refine", "{root}/rd", "--model", "{root}/model_window", "--sequence", "{rd_first}"],
        ["refiner.json", "window"],
    ),
    (
        "refiner-json-residual",
        ["refine", "{root}/rd", "--model", "{root}/model_residual", "--sequence", "{rd_first}"],
        ["refiner.json", "residual_scale"],
    ),
    (
        "refiner-json-unknown",
        ["refine", "{root}/rd", "--model", "{root}/model_unknown", "--sequence", "{rd_first}"],
        ["refiner.json", "unknown keys", "colour"],
    ),
    ("refiner-json-list", ["refine", "{root}/rd", "--model", "{root}/model_list", "--sequence", "{rd_first}"], ["refiner.json", "format"]),
]


@pytest.mark.parametrize("argv,needles", [pytest.param(a, n, id=i) for i, a, n in DATA_CASES])
def test_bad_data(argv, needles, inputs, capsys, tmp_path, llvm_variant):
    out = tmp_path / "out"
    # eval scores what it can and reports what it could not (exit 2): its report is complete, not partial
    assert_refused(_fill(argv, inputs) + ["--out", out], capsys, *needles, out=None if argv[0] == "eval" else out)


# --------------------------------------------------------------------------------------------------------------
# Family 2: a resumable folder made by other inputs or options is refused, never mixed; one writer at a time
# --------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def made(inputs):
    """Output folders as the pipeline leaves them (provenance.json included): the shared fit and capture, and a
    capture whose images differ (same layout, other content)."""
    root = inputs["root"]
    other = _linked_copy(inputs["cap"], root / "cap_other", copy=("images/cam00/frame_0001.exr",))
    image = read_exr(other / "images/cam00/frame_0001.exr")
    image[..., :3] *= 0.9
    image[: image.shape[0] // 2, :, :3] = 0  # other content, and another compressed size (what a run's id sees)
    write_exr(other / "images/cam00/frame_0001.exr", image)
    assert (other / "images/cam00/frame_0001.exr").stat().st_size != (inputs["cap"] / "images/cam00/frame_0001.exr").stat().st_size
    # The same capture with its calibration or capture record edited in place (same sizes: only content differs)
    edited = {}
    for name, rel in (("cap_calib", "rig/calibration.json"), ("cap_record", "capture.json")):
        folder = _linked_copy(inputs["cap"], root / name, copy=(rel,))
        text = (folder / rel).read_text()
        digit = next(i for i, c in enumerate(text) if c in "123456789" and text[i - 1] == ".")  # a decimal digit
        (folder / rel).write_text(text[:digit] + str(int(text[digit]) % 9 + 1) + text[digit + 1 :])
        assert (folder / rel).stat().st_size == (inputs["cap"] / rel).stat().st_size
        edited[name] = folder
    # Users' folders that hold a file named like a gra-mi output: never emptied by --overwrite
    for name, marker in (("user_fit", "fit.json"), ("user_rn", "checkpoint.pt")):
        (root / name).mkdir()
        (root / name / marker).write_text("mine")
        (root / name / "notes.txt").write_text("mine too")
    return {**inputs, **edited, "cap_other": other, "fit_copy": _linked_copy(inputs["fit"], root / "fit_copy")}


PROVENANCE_CASES = [
    ("fit-other-capture", ["fit", "{cap_other}", "--out", "{fit_copy}"], ["provenance.json", "input capture", "--overwrite"]),
    ("fit-edited-calibration", ["fit", "{cap_calib}", "--out", "{fit_copy}"], ["provenance.json", "input capture"]),
    ("fit-edited-capture-record", ["fit", "{cap_record}", "--out", "{fit_copy}"], ["provenance.json", "input capture"]),
    ("overwrite-users-fit-json", ["fit", "{cap}", "--out", "{root}/user_fit", "--overwrite"], ["user_fit", "only folders gra-mi made"]),
    ("overwrite-users-checkpoint", [*RN, "--out", "{root}/user_rn", "--overwrite"], ["user_rn", "only folders gra-mi made"]),
    ("resume-users-checkpoint", [*RN, "--out", "{root}/user_rn"], ["user_rn", "not made by gra-mi"]),
    ("fit-other-candidates", ["fit", "{cap}", "--out", "{fit_copy}", "--roughness-candidates", "5"], ["roughness_candidates"]),
    ("fit-other-uv", ["fit", "{cap}", "--out", "{fit_copy}", "--uv-resolution", "64"], ["resolution", "64 now"]),
    ("fit-other-solver", ["fit", "{cap}", "--out", "{fit_copy}", "--solver", "closed-form"], ["solver"]),
    ("fit-into-capture", ["fit", "{cap}", "--out", "{cap_other}"], ["command 'capture'", "now 'fit'"]),
    ("capture-other-renderer", ["capture", "--preset", "tiny", "--renderer", "onebounce", "--out", "{cap_other}"], ["renderer"]),
    ("capture-other-preset", ["capture", "--preset", "small", "--out", "{cap_other}"], ["preset: 'tiny' then, 'small' now"]),
    ("relightnet-into-fit", [*RN, "--out", "{fit_copy}"], ["command 'fit'"]),
    ("fit-into-foreign", ["fit", "{cap}", "--out", "{root}/cap_json_list/rig"], ["not made by gra-mi"]),
    ("fit-into-its-capture", ["fit", "{cap}", "--out", "{cap}", "--overwrite"], ["output folder (--out) is", "(the capture input)"]),
    ("fit-around-its-capture", ["fit", "{cap}", "--out", "{cap}/..", "--overwrite"], ["(the capture input)"]),
    ("fit-overwrite-foreign", ["fit", "{cap}", "--out", "{root}", "--overwrite"], ["only folders gra-mi made"]),
    ("fit-out-is-file", ["fit", "{cap}", "--out", "{root}/a_file"], ["a_file", "is a file"]),
    ("relightnet-out-is-file", [*RN, "--out", "{root}/a_file"], ["a_file", "is a file"]),
]


@pytest.mark.parametrize("argv,needles", [pytest.param(a, n, id=i) for i, a, n in PROVENANCE_CASES])
def test_folder_made_by_another_run(argv, needles, made, capsys, llvm_variant):
    argv = _fill(argv, made)
    out = Path(argv[argv.index("--out") + 1])
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*")} if out.is_dir() else None
    assert_refused(argv, capsys, *needles)
    if before is not None:  # nothing in the folder was touched
        assert {p: p.stat().st_mtime_ns for p in out.rglob("*")} == before


def test_fit_with_no_texel_seen_by_three_cameras_reports_it(inputs, capsys, tmp_path, llvm_variant):
    """Two training cameras: a valid fit, whose report scores no texel against the truth (it once crashed there)."""
    data = json.loads((inputs["cap"] / "capture.json").read_text())
    cap = _linked_copy(inputs["cap"], tmp_path / "cap", copy=("capture.json",))
    (cap / "capture.json").write_text(json.dumps({**data, "train_cameras": data["train_cameras"][:2]}))
    code, lines = run(["fit", cap, "--out", tmp_path / "fit", "--iterations", "5"], capsys)
    assert code == 0, lines
    report = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert not report["scored_texels"] and report["map_curve"] == []
    assert "texels seen by ≥ 3 cameras (scored below): 0" in (tmp_path / "fit" / "fit_report.md").read_text()


@pytest.mark.parametrize("flag", ["--lpips-weights", "--i3d-weights"])
def test_bad_perceptual_weights_stop_eval_before_any_work(flag, inputs, capsys, tmp_path, llvm_variant):
    out = tmp_path / "eval"
    assert_refused(
        ["eval", "--capture", inputs["cap"], "--fit", inputs["fit"], flag, inputs["root"] / "a_file", "--out", out], capsys, "a_file"
    )
    assert not out.exists(), "nothing evaluated, nothing written"


def test_deflicker_never_writes_over_its_input(inputs, capsys):
    frames = inputs["root"] / "defl_frames"
    before = {p: p.read_bytes() for p in frames.iterdir()}
    for folder in ("defl_frames", "defl_stable"):
        argv = ["deflicker", frames, "--stable", inputs["root"] / "defl_stable", "--out", inputs["root"] / folder]
        assert_refused(argv, capsys, folder, "input); write the output to another folder")
    assert {p: p.read_bytes() for p in frames.iterdir()} == before


def test_second_writer_is_locked_out(made, capsys, tmp_path, llvm_variant):
    """Two `train-refiner` (or any) runs on one folder: the second stops naming the first's pid."""
    import fcntl

    from gra_mi.core.provenance import LOCK

    folder = tmp_path / "busy"
    folder.mkdir()
    with open(folder / LOCK, "w") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fh.write("4242")
        fh.flush()
        assert_refused(["fit", made["cap"], "--out", folder], capsys, "another gra-mi process", "4242")


def test_overwrite_starts_over_and_same_run_resumes(made, capsys, tmp_path, llvm_variant):
    """--overwrite empties a folder gra-mi made; rerunning the same command there resumes (is not refused)."""
    from gra_mi.core.provenance import PROVENANCE, claim_output

    folder = tmp_path / "fit"
    claim_output(folder, "fit", {"capture": made["cap_other"]}, {"solver": "adam"})
    (folder / "old_result.exr").write_text("from the other run")
    from gra_mi.core.provenance import release_folder

    release_folder(folder)
    code, lines = run(["fit", made["cap"], "--out", folder, "--overwrite", "--solver", "closed-form", "--irls-iterations", "0"], capsys)
    assert code == 0, lines
    assert not (folder / "old_result.exr").exists() and (folder / "albedo.exr").is_file()
    record = json.loads((folder / PROVENANCE).read_text())
    assert record["command"] == "fit" and record["config"]["solver"] == "closed-form"
    code, lines = run(["fit", made["cap"], "--out", folder, "--solver", "closed-form", "--irls-iterations", "0"], capsys)
    assert code == 0, lines
    (folder / "left_over.txt").write_text("from before")  # --overwrite starts over even the same run
    code, lines = run(["fit", made["cap"], "--out", folder, "--overwrite", "--solver", "closed-form", "--irls-iterations", "0"], capsys)
    assert code == 0 and not (folder / "left_over.txt").exists() and (folder / "albedo.exr").is_file(), lines


# --------------------------------------------------------------------------------------------------------------
# Family 3: corrupt resumable state; lights that cannot light the subject (warned, not refused)
# --------------------------------------------------------------------------------------------------------------


def test_truncated_training_checkpoint_is_named(tmp_path):
    """A torch training checkpoint cut short: named, with how to start over (RelightNet and refiner training)."""
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.core.training import TrainingLoop

    (tmp_path / "checkpoint.pt").write_bytes(b"PK\x03\x04 cut short")
    with pytest.raises(GraMiInputError, match="unreadable checkpoint.*--overwrite") as error:
        TrainingLoop(tmp_path, 10, 5, 5, "train").resume("cpu")
    assert "checkpoint.pt" in str(error.value)


def test_truncated_checkpoint_is_named(made, capsys, tmp_path, llvm_variant):
    folder = _linked_copy(made["fit"], tmp_path / "fit", copy=("provenance.json",))
    for name in ("checkpoint.npz", "optimize.npz"):
        (folder / name).unlink(missing_ok=True)
        (folder / name).write_bytes(b"PK\x03\x04 cut short by a full disk")
    assert_refused(["fit", made["cap"], "--out", folder], capsys, "checkpoint.npz", "unreadable checkpoint", "--overwrite")


@pytest.mark.parametrize(
    "argv,warning",
    [
        pytest.param(["--point-light", "0,1,0"], "inside the subject", id="point-light-inside"),
        pytest.param(["--pattern", "{root}/pattern_off.json"], "every LED is off", id="all-leds-off"),
    ],
)
def test_lights_that_light_nothing_are_warned(argv, warning, inputs, capsys, caplog, tmp_path, llvm_variant):
    code, lines = run(["relight", TINY, "--frames", "0", "--uv-resolution", "32", *_fill(argv, inputs), "--out", tmp_path / "r"], capsys)
    assert code == 0, lines
    assert any(warning in r.getMessage() for r in caplog.records), [r.getMessage() for r in caplog.records]


def test_leds_inside_the_subject_are_warned(capsys, caplog, tmp_path, llvm_variant):
    """A rig whose LED sphere is smaller than the subject: rendering says how many LEDs light nothing."""
    rig = ["rig", "--out", tmp_path / "rig", "--radius", "0.3", "--camera-distance", "0.25", "--num-leds", "32", "--num-cameras", "2"]
    assert run(rig, capsys)[0] == 0
    assert run(["subject", "--kind", "tiny", "--frames", "1", "--out", tmp_path / "subject"], capsys)[0] == 0
    scene = tmp_path / "scene.xml"
    assert run(["scene", "--rig", tmp_path / "rig", "--subject", tmp_path / "subject", "--out", scene], capsys)[0] == 0
    (tmp_path / "on.json").write_text(json.dumps({"intensities": [1.0] * 32}))
    code, lines = run(["render", scene, "--pattern", tmp_path / "on.json", "--spp", "4", "--out", tmp_path / "r"], capsys)
    assert code == 0, lines
    assert any("lit LEDs are inside the subject" in r.getMessage() for r in caplog.records)


def test_a_rig_inside_the_subject_warns_far_field_relights(capsys, caplog, tmp_path, llvm_variant):
    """Every LED inside the body: far field still lights the subject (from the LEDs' directions) but at a small rig's
    irradiance, hundreds of times brighter than on a real stage; the warning says so."""
    rig = ["rig", "--out", tmp_path / "rig", "--radius", "0.08", "--camera-distance", "0.05", "--num-leds", "32", "--num-cameras", "2"]
    assert run(rig, capsys)[0] == 0
    assert run(["subject", "--kind", "tiny", "--frames", "1", "--out", tmp_path / "subject"], capsys)[0] == 0
    scene = tmp_path / "scene.xml"
    assert run(["scene", "--rig", tmp_path / "rig", "--subject", tmp_path / "subject", "--out", scene], capsys)[0] == 0
    write_exr(tmp_path / "sky.exr", np.ones((16, 32, 3), np.float32))
    code, lines = run(["relight", scene, "--envmap", tmp_path / "sky.exr", "--uv-resolution", "32", "--out", tmp_path / "r"], capsys)
    assert code == 0, lines
    said = [r.getMessage() for r in caplog.records if "inside the subject" in r.getMessage()]
    assert said and "32 of 32" in said[0] and "far brighter" in said[0], said


def test_writers_emit_what_readers_accept(capsys, tmp_path, llvm_variant):
    """Paths with XML-special characters: the scene writer escapes them, and the scene loads and renders."""
    odd = tmp_path / "a&b <c>"
    assert run(["rig", "--out", odd / "rig", "--num-leds", "16", "--num-cameras", "1", "--width", "32", "--height", "24"], capsys)[0] == 0
    assert run(["subject", "--kind", "tiny", "--frames", "1", "--out", odd / "subject"], capsys)[0] == 0
    scene = odd / "scene.xml"
    assert run(["scene", "--rig", odd / "rig", "--subject", odd / "subject", "--out", scene], capsys)[0] == 0
    code, lines = run(["render", scene, "--olat", "3", "--spp", "4", "--out", odd / "r"], capsys)
    assert code == 0, lines
    assert len(list((odd / "r").glob("*.exr"))) == 1
    # The scene file outside the odd folder: its relative paths then hold the odd characters themselves
    elsewhere = tmp_path / "plain" / "scene.xml"
    assert run(["scene", "--rig", odd / "rig", "--subject", odd / "subject", "--out", elsewhere], capsys)[0] == 0
    assert "a&amp;b &lt;c&gt;/rig" in elsewhere.read_text()
    code, lines = run(["render", elsewhere, "--olat", "3", "--spp", "4", "--out", tmp_path / "r2"], capsys)
    assert code == 0, lines


def test_full_disk_is_one_line_and_leaves_no_file(inputs, capsys, tmp_path, monkeypatch):
    """A write that fails (here: ENOSPC when the finished file is moved into place) is one line, exit 2, and leaves
    neither the file nor its temporary beside it."""
    import errno

    import gra_mi.core.io as io

    def full(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(io.os, "replace", full)
    out = tmp_path / "edited"
    argv = ["edit-texture", "--albedo", inputs["root"] / "albedo.exr", "--mask", inputs["root"] / "mask.exr", "--color", "1,0,0"]
    line = assert_refused([*argv, "--out", out / "red.exr"], capsys, "No space left on device")
    assert "red" in line
    assert not (out.exists() and any(out.rglob("*"))), sorted(out.rglob("*"))


def test_output_path_that_is_a_file(inputs, capsys, llvm_variant):
    """`--out` naming a file where a folder belongs: one line naming it (an OSError, not a traceback)."""
    assert_refused(["render", TINY, "--olat", "0", "--spp", "4", "--out", inputs["root"] / "a_file"], capsys, "a_file")


@pytest.mark.parametrize("damage", ["truncated", "missing"])
@pytest.mark.parametrize(
    ("attribute", "script"),
    [("loading.TINY_VAE_WEIGHTS", "pretrain_tiny_vae.py"), ("model.TINY_PRIOR_WEIGHTS", "pretrain_tiny_refiner.py")],
)
def test_shipped_weights_damaged_say_how_to_rebuild(damage, attribute, script, tmp_path, monkeypatch):
    """The tiny VAE and the tiny refiner prior shipped in gra_mi/data: a damaged or missing file is named with the
    script that rebuilds it."""
    import importlib

    from gra_mi.core.errors import GraMiInputError
    from gra_mi.refiner.config import RefinerConfig
    from gra_mi.refiner.model import VideoRefiner

    module_name, attribute = attribute.split(".")  # the module that reads the file
    module = importlib.import_module(f"gra_mi.refiner.{module_name}")
    weights = tmp_path / getattr(module, attribute).name
    if damage == "truncated":
        weights.write_bytes(getattr(module, attribute).read_bytes()[:1000])
    monkeypatch.setattr(module, attribute, weights)
    with pytest.raises(GraMiInputError, match=script) as error:
        VideoRefiner(RefinerConfig())
    assert str(weights) in str(error.value)
