"""The reflectance field: a capture's image under any LED drive as the weighted sum of its OLATs, checked against the
images the capture rendered directly under white, gradient and environment-mapped drives (light is additive, so the
two agree to the renders' noise); held, float16 and streamed sums alike; and the bad input a user brings."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli import main

SHRUNK = dict(
    subject="tiny", num_leds=24, num_cameras=6, eval_cameras=2, width=72, height=96, uv_resolution=32, envmap_height=16,
    spp=4, indirect_spp=4, envmap_frames=2, camera_distance=1.2,
)  # fmt: skip


@pytest.fixture(scope="module")
def olat_captures(tmp_path_factory):
    """The same static OLAT capture rendered by the path tracer and by the one-bounce renderer."""
    from gra_mi.capture import synthetic
    from gra_mi.core.runtime import choose_variant

    choose_variant("llvm_ad_rgb")
    root = tmp_path_factory.mktemp("olat")
    original = synthetic.PRESETS["olat"]
    synthetic.PRESETS["olat"] = dataclasses.replace(original, **SHRUNK)
    try:
        return {
            renderer: synthetic.generate_capture(root / renderer, synthetic.CaptureConfig(preset="olat", measure_noise=False, renderer=renderer))
            for renderer in ("path", "onebounce")
        }  # fmt: skip
    finally:
        synthetic.PRESETS["olat"] = original


def _field(capture, camera: str, memory_gb: float = 4.0):
    from gra_mi.capture.reflectance import OlatIndex, ReflectanceField
    from gra_mi.stage.lightstage import load_calibration

    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    index = OlatIndex.of(capture, stage)
    return stage, index, ReflectanceField.load(capture, camera, index, memory_gb, progress_bar=False)


@pytest.mark.parametrize("renderer, tolerance", [("onebounce", 0.015), ("path", 0.08)])
def test_the_sum_of_olats_is_the_image_under_the_combined_drive(olat_captures, renderer, tolerance):
    """White, both gradients and the envmap-lit frames: Σ wᵢ · OLATᵢ against the capture's direct render of that drive
    (the one-bounce renderer is nearly noise-free; the path tracer's 4 spp are not)."""
    from gra_mi.capture.dataset import load_observation

    capture = olat_captures[renderer]
    stage, index, rf = _field(capture, "cam04")
    combined = [e for e in capture.frames if e.frame not in index.frames]
    assert [e.kind for e in combined] == ["pattern"] * 3 + ["envmap"] * 2
    for entry in combined:
        image = rf.relight(index.weights(capture.lighting(stage, entry), "drive"))[0]
        truth = load_observation(capture, "cam04", entry.frame)
        inside = truth[..., 3] > 0.5
        error = np.abs(image[inside, :3] - truth[inside, :3]).mean() / truth[inside, :3].mean()
        assert error < tolerance, (entry, error)
        assert image[..., :3].sum() == pytest.approx(truth[..., :3].sum(), rel=0.01)
        np.testing.assert_array_equal(image[..., 3], load_observation(capture, "cam04", int(index.frames[0]))[..., 3])


def test_held_float16_and_streamed_sums_agree(olat_captures):
    capture = olat_captures["path"]
    stage, index, held = _field(capture, "cam05")
    k, p = len(index.frames), held.pixels.size
    half = _field(capture, "cam05", memory_gb=3 * k * p * 3 / 2**30)[2]  # fits as float16, not as float32
    streamed = _field(capture, "cam05", memory_gb=0)[2]
    assert held.stack.dtype == np.float32 and half.stack.dtype == np.float16 and streamed.stack is None
    rng = np.random.default_rng(0)
    weights = rng.uniform(0, 2, (3, k, 3))
    a, b, c = held.relight(weights), half.relight(weights), streamed.relight(weights)
    np.testing.assert_allclose(c, a, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(b, a, rtol=2e-3, atol=1e-3 * a.max())


def test_the_sum_on_a_torch_device_is_numpys(olat_captures):
    """The products a GPU runs (torch; here on its CPU device, the same code), float32 and float16 stacks alike."""
    capture = olat_captures["path"]
    stage, index, held = _field(capture, "cam05")
    k, p = len(index.frames), held.pixels.size
    half = _field(capture, "cam05", memory_gb=3 * k * p * 3 / 2**30)[2]
    weights = np.random.default_rng(1).uniform(0, 2, (2, k, 3))
    assert held.summed_on == "host (NumPy)", "no GPU here: NumPy's sum"
    for field in (held, half):
        on_host = field._sum_held(weights)
        on_torch = field._sum_on_device(weights, field._device_stack("cpu"))
        np.testing.assert_allclose(on_torch, on_host, rtol=1e-5, atol=1e-6 * on_host.max())


def test_relight_field_writes_every_lighting_and_camera(olat_captures, tmp_path):
    capture = olat_captures["path"]
    out = tmp_path / "out"
    white = capture.folder / "patterns" / "white.json"
    envmap = capture.folder / capture.frames[3].envmap
    args = ["relight-field", str(capture.folder), "--pattern", str(white), "--envmap", str(envmap), "--olat", "3"]
    assert main([*args, "--cameras", "cam00,5", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["cameras"]) == {"cam00", "cam05"} and summary["olats"] == 24
    for light in ("white", envmap.stem, "olat003"):
        for camera in ("cam00", "cam05"):
            assert (out / light / f"{camera}.exr").is_file() and (out / light / f"{camera}.png").is_file()


def _drop_olats(capture, tmp_path: Path, leds: list[int]) -> Path:
    folder = tmp_path / "partial"
    shutil.copytree(capture.folder, folder)
    data = json.loads((folder / "capture.json").read_text())
    gone = {f"patterns/olat_{led:03d}.json" for led in leds}
    data["frames"] = [f for f in data["frames"] if f.get("pattern") not in gone]
    (folder / "capture.json").write_text(json.dumps(data))
    return folder


def test_missing_olats_warn_or_stop_by_the_light_they_carry(olat_captures, tmp_path, capsys, caplog):
    capture = olat_captures["path"]
    folder = _drop_olats(capture, tmp_path, [5])
    drive = np.full(24, 1.0)
    drive[5] = 0.01  # 0.04 % of the light: summed from the rest, with a warning naming LED 5
    (tmp_path / "mostly.json").write_text(json.dumps({"intensities": drive.tolist()}))
    base = ["relight-field", str(folder), "--cameras", "cam00", "--out", str(tmp_path / "out")]
    assert main([*base, "--pattern", str(tmp_path / "mostly.json")]) == 0
    assert "LEDs 5 have no OLAT" in caplog.text
    assert main([*base, "--olat", "5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "drives LEDs 5" in err[0] and "no OLAT in the capture" in err[0]


def test_an_led_s_light_moves_to_its_nearest_neighbours_with_the_same_irradiance():
    """Each of the 3 nearest usable LEDs takes a share inversely proportional to its angle, times its squared distance
    over the lost LED's (the same irradiance at the centre); LEDs further away take nothing."""
    from gra_mi.capture.reflectance import moved_to_neighbours

    angles = np.radians([0.0, 10.0, 20.0, -10.0, 90.0])
    directions = np.stack([np.sin(angles), np.zeros(5), np.cos(angles)], axis=1)
    distances = np.array([1.0, 1.0, 2.0, 1.0, 1.0])
    lighting = np.zeros((5, 3))
    lighting[0], lighting[4] = [1.0, 2.0, 3.0], 1.0
    usable = np.array([False, True, True, True, True])
    moved, gone, share = moved_to_neighbours(lighting, usable, directions, distances)
    expected = np.zeros((5, 3))
    expected[1] = expected[3] = 0.4 * lighting[0]  # 1/10° : 1/10° : 1/20° → 0.4, 0.4, 0.2
    expected[2] = 0.2 * 4.0 * lighting[0]  # twice as far: four times the intensity
    expected[4] = 1.0
    np.testing.assert_allclose(moved, expected, rtol=1e-12)
    assert gone.tolist() == [0] and share == pytest.approx(6.0 / 9.0)


def test_a_camera_without_one_olat_image_sums_the_rest_and_its_neighbours(olat_captures, tmp_path):
    """The camera's field loads without the lost image; a drive that puts a little light on that LED takes it from
    the neighbours' OLATs (close to the whole sum); the LED's own OLAT, all of whose light would be stood in for, is
    refused naming the camera."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.reflectance import OlatIndex, ReflectanceField
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.stage.lightstage import load_calibration

    capture = olat_captures["onebounce"]
    folder = tmp_path / "gap"
    shutil.copytree(capture.folder, folder)
    data = json.loads((folder / "capture.json").read_text())
    lost = next(f for f in data["frames"] if f.get("pattern") == "patterns/olat_005.json")
    lost["missing"] = ["cam04"]
    (folder / "capture.json").write_text(json.dumps(data))
    (folder / capture.image_path("cam04", lost["frame"]).relative_to(capture.folder)).unlink()
    gapped = Capture.load(folder)
    stage = load_calibration(folder / "rig" / "calibration.json")
    index = OlatIndex.of(gapped, stage)
    rf = ReflectanceField.load(gapped, "cam04", index, progress_bar=False)
    whole = _field(capture, "cam04")[2]
    assert index.leds[rf.lacking].tolist() == [5]
    drive = np.ones((24, 3))
    drive[5] = 0.2
    ours, truth = rf.relight(rf.weights(drive, "dim"))[0], whole.relight(index.weights(drive, "dim"))[0]
    dropped = whole.relight(index.weights(drive * (np.arange(24) != 5)[:, None], "dropped"))[0]
    subject = truth[..., 3] > 0.5

    def error(image):
        return np.abs(image[subject, :3] - truth[subject, :3]).mean() / truth[subject, :3].mean()

    assert error(ours) < 0.02 and error(ours) < error(dropped), (error(ours), error(dropped))  # 24 LEDs: 40° apart
    with pytest.raises(GraMiInputError, match="olat 5 on camera cam04: drives LEDs 5 \\(100.0 % of its light\\)"):
        rf.weights(np.eye(24)[5][:, None].repeat(3, axis=1), "olat 5")
    with pytest.raises(ValueError, match="use ReflectanceField.weights"):
        rf.relight(index.weights(drive, "dim"))


@pytest.mark.parametrize(
    "drive, needle",
    [
        (np.ones(23), "expected (24,) or (24, 3) LED intensities"),
        (np.r_[np.nan, np.ones(23)], "finite and non-negative"),
        (np.r_[-1.0, np.ones(23)], "finite and non-negative"),
    ],
)
def test_a_bad_drive_is_refused_naming_its_file(olat_captures, tmp_path, capsys, drive, needle):
    path = tmp_path / "drive.json"
    path.write_text(json.dumps({"intensities": [None if np.isnan(v) else v for v in drive.tolist()]}))
    args = ["relight-field", str(olat_captures["path"].folder), "--pattern", str(path), "--out", str(tmp_path / "out")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and needle in err[0], err
    assert not (tmp_path / "out").exists()


def test_a_capture_without_olats_is_refused(olat_captures, tmp_path, capsys):
    capture = olat_captures["path"]
    folder = _drop_olats(capture, tmp_path, list(range(24)))
    args = ["relight-field", str(folder), "--olat", "1", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "capture.json" in err[0] and "no OLAT frames" in err[0], err


def test_relightnet_trains_on_lightings_synthesized_from_the_olats(olat_captures, tmp_path):
    """Procedural envmaps on the LEDs become training pairs (the microfacet render → the OLAT sum); held-out OLATs
    stay out of every sum, and held-out procedural maps are a validation split of their own."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.reflectance import OlatIndex
    from gra_mi.relightnet.data import SYNTHESIZED_SPLIT
    from gra_mi.stage.lightstage import load_calibration

    capture = olat_captures["path"]
    assert main(["fit", str(capture.folder), "--out", str(tmp_path / "fit"), "--solver", "closed-form", "--roughness-candidates", "3"]) == 0
    out = tmp_path / "relightnet"
    args = ["train-relightnet", str(capture.folder), "--fit", str(tmp_path / "fit"), "--out", str(out), "--steps", "4"]
    assert main([*args, "--validate-every", "2", "--synthesized-lightings", "8", "--synthesized-validation", "2"]) == 0
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    held_out = [f for f in Capture.load(capture.folder).frames if f.split == "test" and f.kind == "pattern"]
    assert held_out, "the olat preset holds out every 10th OLAT"
    train_leds = OlatIndex.of(capture, stage, splits=("train",)).leds
    with np.load(out / "cache" / "synthesized_train.npz") as data:
        drives = data["drives"]
    assert drives.shape == (8, 24, 3) and len({d.tobytes() for d in drives}) == 8
    off = np.setdiff1d(np.arange(24), train_leds)
    assert off.size == len(held_out) and not drives[:, off].any() and drives[:, train_leds].max(axis=1).min() > 0
    splits = json.loads((out / "validation.json").read_text())["splits"]
    synthesized = {k: v for k, v in splits.items() if k.startswith(SYNTHESIZED_SPLIT)}
    assert sum(v["microfacet"]["views"] for v in synthesized.values()) == 2 * len(capture.eval_cameras)
    assert all(np.isfinite(v[m]["psnr"]) for v in splits.values() for m in ("microfacet", "relightnet"))


def test_eval_scores_held_out_olats_and_maps_whose_truth_is_the_olat_sum(olat_captures, tmp_path, capsys):
    """`gra-mi eval` on a static OLAT capture: the capture's held-out OLATs and envmaps (every frame scored, a lighting
    set is not a video), and a user's map and library maps with the reflectance field as truth."""
    from gra_mi.capture.dataset import load_observation
    from gra_mi.core.io import write_exr
    from gra_mi.eval.reflectance import FieldLighting, FieldTruth
    from gra_mi.stage.lightstage import load_calibration

    capture = olat_captures["path"]
    fit = tmp_path / "fit"
    assert main(["fit", str(capture.folder), "--out", str(fit), "--solver", "closed-form", "--roughness-candidates", "3"]) == 0
    sky = np.full((8, 16, 3), 0.2, np.float32)
    sky[:3] = 2.0  # bright above
    write_exr(tmp_path / "my_sky.exr", sky)
    out = tmp_path / "eval"
    args = ["eval", "--capture", str(capture.folder), "--fit", str(fit), "--out", str(out), "--library-envmaps", "2"]
    assert main([*args, "--envmap", str(tmp_path / "my_sky.exr")]) == 0
    report = json.loads((out / "eval.json").read_text())
    splits = report["protocol"]["splits"]
    cam = capture.eval_cameras[0]
    assert splits[f"field_{cam}"]["lighting"] == "my_sky, library_000, library_001"
    assert splits[f"field_{cam}"]["truth"].startswith("Σ OLAT") and splits[f"field_{cam}"]["scored"] == [0, 1, 2]
    olats = next(s for s in splits.values() if s["lighting"] == "OLATs")
    assert olats["scored"] == list(range(olats["frames"])) and olats["truth"] == "the capture's images"
    scores = report["stages"]["microfacet"]["splits"][f"field_{cam}"]
    assert 15 < scores["psnr"] < 60 and scores["frames_scored"] == 3
    assert "truth Σ OLAT" in (out / "eval.md").read_text()
    # the truth of a map the capture did photograph is that photograph, within the renders' noise
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    entry = next(f for f in capture.frames if f.kind == "envmap")
    summed = FieldTruth(capture)(cam, FieldLighting("probe", capture.lighting(stage, entry)))
    photo = load_observation(capture, cam, entry.frame)
    assert summed[..., :3].sum() == pytest.approx(photo[..., :3].sum(), rel=0.01)
    # the camera loses the OLAT image of an LED that carries little of these lightings' light: still scored, its
    # truth taking that light from the neighbours' OLATs, and scoring the fit as the whole truth does
    gapped = _lose_dimmest_olat(capture, stage, cam, {"my_sky": sky}, tmp_path / "gapped")
    again = ["eval", "--capture", str(gapped), "--fit", str(fit), "--out", str(tmp_path / "eval_gap"), "--library-envmaps", "2"]
    assert main([*again, "--envmap", str(tmp_path / "my_sky.exr")]) == 0
    report_gap = json.loads((tmp_path / "eval_gap" / "eval.json").read_text())
    assert "from their neighbours' OLATs" in report_gap["protocol"]["splits"][f"field_{cam}"]["truth"]
    assert report_gap["stages"]["microfacet"]["splits"][f"field_{cam}"]["psnr"] == pytest.approx(scores["psnr"], abs=0.2)


def _lose_dimmest_olat(capture, stage, camera: str, envmaps: dict, folder: Path) -> Path:
    """A copy of ``capture`` whose ``camera`` lacks the OLAT image of the LED with the least light in the evaluation's
    field lightings of ``envmaps`` (and 2 library maps), as an import records a lost image."""
    from gra_mi.eval.reflectance import field_lightings

    drives = np.stack([light.intensities for light in field_lightings(capture, stage, envmaps, 2)])
    share = (drives.sum(axis=2) / drives.sum(axis=(1, 2))[:, None]).max(axis=0)
    led = int(np.argmin(np.where(share > 0, share, np.inf)))
    assert 0 < share[led] <= 0.02, share
    shutil.copytree(capture.folder, folder)
    data = json.loads((folder / "capture.json").read_text())
    lost = next(f for f in data["frames"] if f.get("pattern") == f"patterns/olat_{led:03d}.json")
    lost["missing"] = [camera]
    (folder / "capture.json").write_text(json.dumps(data))
    (folder / capture.image_path(camera, lost["frame"]).relative_to(capture.folder)).unlink()
    return folder


def test_eval_refuses_a_reflectance_field_truth_without_olats(olat_captures, tmp_path, capsys):
    capture = olat_captures["path"]
    folder = _drop_olats(capture, tmp_path, list(range(24)))
    args = ["eval", "--capture", str(folder), "--out", str(tmp_path / "eval"), "--library-envmaps", "1"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "capture.json" in err[0] and "no OLAT frames" in err[0], err


def test_the_olat_demo_runs_end_to_end_shrunk(tmp_path, monkeypatch):
    """`gra-mi demo --preset olat` on a few pixels: capture → fit from the OLATs → RelightNet on synthesized lightings
    → eval (held-out envmaps and OLATs, library maps with the OLAT sum as truth) → report.md."""
    from gra_mi.apps import demo
    from gra_mi.capture import synthetic

    monkeypatch.setitem(synthetic.PRESETS, "olat_quick", dataclasses.replace(synthetic.PRESETS["olat_quick"], **SHRUNK))
    shrunk = dataclasses.replace(
        demo.PRESETS["olat"], roughness_candidates=3, relightnet_steps=4, synthesized_lightings=8, library_envmaps=2
    )
    monkeypatch.setitem(demo.PRESETS, "olat", shrunk)
    report = demo.run_demo("olat", tmp_path / "demo")
    record = json.loads((tmp_path / "demo" / "demo.json").read_text())
    splits = record["eval"]["protocol"]["splits"]
    assert {s for s in splits if s.startswith("field_")} == {f"field_{c}" for c in record["capture"]["eval_cameras"]}
    assert any(a["lighting"] == "OLATs" for a in splits.values())  # the held-out OLATs
    assert record["eval"]["stages"]["RelightNet"]["status"] == "done"
    assert "novel lighting (envmap, truth from OLATs)" in "".join(record["relightnet"]["splits"])
    text = report.read_text()
    assert "truth Σ OLAT" in (tmp_path / "demo" / "eval" / "eval.md").read_text() and "Σ OLAT" in text
    for name in ("fit/albedo.exr", "relightnet/relightnet.safetensors", "contact_truth_vs_relit.png", "avatar.glb"):
        assert (tmp_path / "demo" / name).is_file(), name


def test_a_fit_from_olats_beats_the_constant_maps(tmp_path):
    """Path-traced OLATs alone (64 LEDs, the white and gradient frames left out, at a size where a highlight spans a
    few pixels): the fitted roughness and albedo are closer to the true maps than the constant baseline (the true
    map's median), without the brightness calibration."""
    from gra_mi.capture import synthetic
    from gra_mi.fit.materials import FitConfig, run_fit

    sharper = SHRUNK | dict(num_leds=64, num_cameras=8, width=144, height=192, uv_resolution=64)
    original = synthetic.PRESETS["olat"]
    synthetic.PRESETS["olat"] = dataclasses.replace(original, **sharper)
    try:
        capture = synthetic.generate_capture(tmp_path / "capture", synthetic.CaptureConfig(preset="olat", measure_noise=False))
    finally:
        synthetic.PRESETS["olat"] = original
    data = json.loads((capture.folder / "capture.json").read_text())
    data["frames"] = [f for f in data["frames"] if "olat_" in (f.get("pattern") or "") or f["split"] == "test"]
    (capture.folder / "capture.json").write_text(json.dumps(data))
    run_fit(capture.folder, tmp_path / "fit", FitConfig(iterations=30, roughness_candidates=5, calibrate_brightness=False))
    record = json.loads((tmp_path / "fit" / "fit.json").read_text())
    ours, constant = record["regions"]["all"], record["baseline"]["all"]
    assert record["capture"]["training_frames"] == sum(f["split"] == "train" for f in data["frames"]) == 58
    assert ours["roughness_mae"] < constant["roughness_mae"] and ours["roughness_median_abs"] < constant["roughness_median_abs"]
    assert ours["albedo_mae"] < 0.5 * constant["albedo_mae"], (ours, constant)


@pytest.mark.parametrize(
    "args, needle",
    [
        (
            ["train-relightnet", "{cap}", "--fit", "{fit}", "--synthesized-lightings", "4"],
            "poses: a reflectance field needs a static capture",
        ),
        (["eval", "--capture", "{cap}", "--fit", "{fit}", "--library-envmaps", "2"], "poses: a reflectance field needs a static capture"),
        (["relight-field", "{cap}", "--olat", "1"], "poses: a reflectance field needs a static capture"),
    ],
)
def test_a_moving_capture_has_no_reflectance_field(path_traced_fit, tmp_path, capsys, args, needle):
    cap, fit = path_traced_fit / "cap", path_traced_fit / "fit"
    argv = [a.format(cap=cap, fit=fit) for a in args] + ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "capture.json" in err[0] and needle in err[0], err


@pytest.mark.parametrize(
    "extra, needle",
    [
        (["relight-field", "{cap}", "--olat", "1", "--memory-gb", "nan"], "--memory-gb"),
        (["relight-field", "{cap}", "--olat", "1", "--lighting-batch", "0"], "--lighting-batch"),
        (["eval", "--capture", "{cap}", "--library-envmaps", "-1"], "--library-envmaps"),
        (["train-relightnet", "{cap}", "--fit", "{cap}", "--synthesized-lightings", "-2"], "--synthesized-lightings"),
    ],
)
def test_bad_reflectance_field_options_are_refused(olat_captures, tmp_path, capsys, extra, needle):
    argv = [a.format(cap=olat_captures["path"].folder) for a in extra] + ["--out", str(tmp_path / "out")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not (tmp_path / "out").exists()


def test_held_out_frames_have_their_own_sample_counts(llvm_variant):
    """olat_quick renders the frames its scores use at 4x the samples of its 4-spp training frames (never fewer than
    the training frames that --spp asks for), and the renderer of each frame follows its split."""
    from gra_mi.capture.dataset import FrameLighting
    from gra_mi.capture.synthetic import CaptureConfig
    from gra_mi.capture.truth import ground_truth_renderers

    record = CaptureConfig(preset="olat_quick").record()
    assert (record["spp"], record["indirect_spp"], record["held_out_spp"], record["held_out_indirect_spp"]) == (4, 4, 16, 256)
    assert CaptureConfig(preset="olat_quick", spp=64).record()["held_out_spp"] == 64
    assert CaptureConfig(preset="olat_quick", without=["interreflection"]).record()["held_out_indirect_spp"] == 0
    assert "held_out_spp" not in CaptureConfig(preset="olat_quick", renderer="onebounce").record()
    assert "held_out_spp" not in CaptureConfig(preset="olat").record()
    renderer_for = ground_truth_renderers(record)
    entry = lambda split, kind: FrameLighting(frame=0, split=split, sequence=0, kind=kind, envmap=None, pattern=None)  # noqa: E731
    assert (renderer_for(entry("test", "pattern")).spp, renderer_for(entry("test", "envmap")).indirect_spp) == (16, 256)
    assert (renderer_for(entry("train", "pattern")).spp, renderer_for(entry("train", "pattern")).indirect_spp) == (4, 4)


def test_an_olat_captures_noise_is_measured_on_white_an_olat_and_a_held_out_olat(olat_captures):
    """The probes of a static OLAT capture: the white frame and, of the training and of the held-out OLATs, the one
    whose LED is nearest the measuring camera (the subject lit where it looks), each measured (finite, positive)."""
    from gra_mi.capture.truth import ground_truth_renderers, measure_ground_truth_noise, noise_probe_frames
    from gra_mi.stage.scene import LightstageScene

    capture = olat_captures["path"]
    source = LightstageScene.load(capture.folder / "scene_gt.xml")
    stage, camera = source.stage, source.stage.cameras[0].name
    probes = noise_probe_frames(capture, stage, camera)
    assert set(probes) == {"white", "OLAT", "held-out OLAT"} and probes["held-out OLAT"].split == "test"
    distance = lambda e: np.linalg.norm(stage.led_positions[np.argmax(capture.lighting(stage, e).sum(1))] - stage.camera(camera).position)  # noqa: E731
    for label, split in (("OLAT", "train"), ("held-out OLAT", "test")):
        olats = [f for f in capture.frames if f.split == split and "olat_" in (f.pattern or "")]
        assert distance(probes[label]) == min(distance(e) for e in olats)
    noise = measure_ground_truth_noise(capture, source, ground_truth_renderers(capture.ground_truth), camera)
    assert set(noise) == set(probes) and all(0 < row["relative_rmse"] < 1 for row in noise.values())
    assert noise["held-out OLAT"]["pattern"] == probes["held-out OLAT"].pattern
