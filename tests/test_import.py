"""`gra-mi import humanolat`, tested on files laid out as HumanOLAT ships them: a synthetic static-pose OLAT capture
written in that layout (AVIF, cameras.calib in millimetres with OpenCV camera-to-world, LED positions, the firing
order, an OBJ in millimetres in a Z-up frame with an offset centre) and read back; the round trip against the native
capture; the convention mistakes and broken files a real dataset brings, each stopped with one line."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli import main
from gra_mi.core.io import read_exr

SHRUNK = dict(
    subject="tiny", num_leds=24, num_cameras=8, eval_cameras=2, width=72, height=96, uv_resolution=32, envmap_height=16,
    spp=4, indirect_spp=4, envmap_frames=2, camera_distance=1.2,
)  # fmt: skip


@pytest.fixture(scope="module")
def olat_capture(tmp_path_factory):
    """A static pose under white, gradient, envmap and 24 OLAT lightings (8 cameras), natively and as HumanOLAT."""
    from gra_mi.capture import synthetic
    from gra_mi.capture.humanolat import write_humanolat
    from gra_mi.core.runtime import choose_variant

    choose_variant("llvm_ad_rgb")
    root = tmp_path_factory.mktemp("olat")
    original = synthetic.PRESETS["olat"]
    synthetic.PRESETS["olat"] = dataclasses.replace(original, **SHRUNK)
    try:
        capture = synthetic.generate_capture(root / "native", synthetic.CaptureConfig(preset="olat", measure_noise=False))
    finally:
        synthetic.PRESETS["olat"] = original
    subject = write_humanolat(capture, root / "layout")
    return root, capture, subject


def _imported(root: Path, subject: Path, name: str = "imported", *extra: str) -> Path:
    truth = json.loads((subject / "synthetic.json").read_text())
    out = root / name
    args = ["import", "humanolat", str(subject), "--out", str(out), "--uv-resolution", "32", "--test-olat-every", "5"]
    assert main([*args, "--led-intensity", str(truth["import_led_intensity"]), *extra]) == 0
    return out


@pytest.fixture(scope="module")
def imported(olat_capture):
    root, _, subject = olat_capture
    return _imported(root, subject)


def test_the_layout_is_written_as_the_dataset_ships_it(olat_capture):
    from gra_mi.capture.humanolat import olat_numbers, read_calib

    _, capture, subject = olat_capture
    cams = sorted(p.name for p in (subject / "POSE_00" / "images_processed").iterdir())
    assert cams == [f"Cam{i:02d}" for i in range(1, 9)]
    numbers = sorted(int(p.name.split(".")[1]) for p in (subject / "POSE_00" / "images_processed" / "Cam01").glob("*.avif"))
    olats, bright = olat_numbers(24)
    assert numbers == list(range(max(olats) + 1)) and bright[:2] == [14, 34] and olats[:2] == [15, 16] and 34 not in olats
    calib = read_calib(subject / "shared" / "cameras.calib")
    assert len(calib) == 8 and abs(calib[0].extrinsic[:3, 3]).max() > 100  # millimetres
    assert (subject / "POSE_00" / "segmentations" / "masks" / "000" / "Cam08.png").is_file()
    assert "v " in (subject / "POSE_00" / "model" / "model.obj").read_text()[:2000]


def test_import_brings_the_pose_into_gra_mis_frame(olat_capture, imported):
    from gra_mi.capture.dataset import Capture
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    _, native, _ = olat_capture
    capture = Capture.load(imported)
    report = json.loads((imported / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
    assert report["frame"]["up_estimated"] and report["frame"]["up_off_axis_deg"] < 0.01
    stage, truth = load_calibration(imported / "rig" / "calibration.json"), load_calibration(native.folder / "rig" / "calibration.json")
    np.testing.assert_allclose(stage.center[[0, 2]], 0, atol=1e-6)
    assert load_sequence(imported / "subject").vertices[0][:, 1].min() == pytest.approx(0, abs=1e-6)
    # Rigid: every camera keeps its distance to the LED sphere's centre and its intrinsics
    for a, b in zip(stage.cameras, truth.cameras, strict=True):
        assert np.linalg.norm(a.position - stage.center) == pytest.approx(np.linalg.norm(b.position - truth.center), abs=1e-5)
        assert (a.fx, a.cx, a.width) == pytest.approx((b.fx, b.cx, b.width), abs=1e-6)
    assert capture.source["format"] == "humanolat" and len(capture.source["transform"]) == 4
    assert {f.pose for f in capture.frames} == {0} and len(capture.frames) == 25  # white + 24 OLATs, one pose


def test_imported_images_match_the_native_ones_within_8_bit(olat_capture, imported):
    from gra_mi.capture.dataset import Capture, load_observation

    _, native, subject = olat_capture
    exposure = json.loads((subject / "synthetic.json").read_text())["exposure"]
    capture = Capture.load(imported)
    white = next(f.frame for f in native.frames if Path(f.pattern or "").stem == "white")
    for cam, name in (("cam00", "Cam01"), ("cam05", "Cam06")):
        a, b = load_observation(native, cam, white), load_observation(capture, name, 0)
        inside = (a[..., 3] > 0.99) & (b[..., 3] > 0.5)
        error = np.abs(b[..., :3] - exposure * a[..., :3])[inside].mean() / (exposure * a[..., :3][inside].mean())
        assert error < 0.02, (cam, error)


def test_the_report_says_how_many_levels_an_olat_spans(olat_capture, imported):
    """8-bit OLATs are a coarse truth: the report counts the distinct values a single OLAT takes on the subject (the
    median over the linearity camera's OLATs), here against the codes Pillow decodes from the AVIF files."""
    from PIL import Image

    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers
    from gra_mi.capture.source_files import read_mask

    _, _, subject = olat_capture
    lin = json.loads((imported / "import_report.json").read_text())["linearity"]
    images = images_of(subject / "POSE_00" / "images_processed" / lin["camera"])
    mask = read_mask(subject / "POSE_00" / "segmentations" / "masks" / "000" / f"{lin['camera']}.png")
    codes = [len(np.unique(np.asarray(Image.open(images[n]).convert("RGB"))[mask])) for n in olat_numbers(24)[0]]
    assert lin["olat_levels"] == np.median(codes) and 1 < lin["olat_levels"] < 256, (lin, codes)
    assert f"takes a median of {lin['olat_levels']:.0f} distinct values" in (imported / "import_report.md").read_text()
    assert lin["camera"] == camera_name(0)


def test_a_subject_that_moved_during_the_olats_is_said(olat_capture, imported, tmp_path):
    """HumanOLAT fires every LED at full brightness every 21st image through the OLATs: a still subject and steady
    LEDs give those frames alike. The report measures how far they stray and says so past 5 % (here one of them
    brightened by a quarter, as LEDs that drifted would)."""
    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers, write_avif
    from gra_mi.capture.source_files import read_image

    _, _, subject = olat_capture
    still = json.loads((imported / "import_report.json").read_text())["linearity"]
    assert still["steady_frames"] == 2 and still["steady_change"] < 0.01
    assert "Moved or drifted" not in (imported / "import_report.md").read_text()
    moved = tmp_path / "layout" / subject.name
    shutil.copytree(subject, moved, ignore=shutil.ignore_patterns("json_*"))
    later = olat_numbers(24)[1][1]
    path = images_of(moved / "POSE_00" / "images_processed" / camera_name(0))[later]
    write_avif(path, read_image(path)[0] * 1.25)
    out = _imported(tmp_path, moved, "moved")
    lin = json.loads((out / "import_report.json").read_text())["linearity"]
    assert lin["steady_worst"] == later and lin["steady_change"] == pytest.approx(0.25, abs=0.03), lin
    assert "**Moved or drifted**: the 2 full-bright frames" in (out / "import_report.md").read_text()


def test_non_square_pixels_are_resampled_with_the_error_stated(olat_capture):
    from gra_mi.capture.humanolat import write_humanolat
    from gra_mi.stage.lightstage import load_calibration

    root, capture, _ = olat_capture
    subject = write_humanolat(capture, root / "aniso", pixel_aspect=1.25)
    out = _imported(root, subject, "imported_aniso")
    report = json.loads((out / "import_report.json").read_text())
    assert all(c["anisotropy"] == pytest.approx(1.25) and 0 < c["resampling_error"] < 0.1 for c in report["cameras"])
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"])
    cam = load_calibration(out / "rig" / "calibration.json").cameras[0]
    assert cam.fx == cam.fy and cam.width == 72


def test_a_fit_of_the_imported_capture_matches_the_native_one(olat_capture, imported, tmp_path):
    """The same training OLATs fitted natively and after the round trip through 8-bit AVIF: the maps agree within
    the quantisation's effect (albedo 2.5 % median and 8.6 % 90th-percentile relative difference, roughness 0.007,
    when measured)."""
    from gra_mi.fit.materials import FitConfig, run_fit

    root, native, _ = olat_capture
    imported_capture = json.loads((imported / "capture.json").read_text())
    train = {f["pattern"] for f in imported_capture["frames"] if f["split"] == "train"}
    same = tmp_path / "native_same"
    shutil.copytree(native.folder, same)
    data = json.loads((same / "capture.json").read_text())
    data["frames"] = [f for f in data["frames"] if f["pattern"] in train or f["split"] == "test"]
    names = {f"cam{i:02d}": f"Cam{i + 1:02d}" for i in range(8)}
    data["eval_cameras"] = [c for c, n in names.items() if n in imported_capture["eval_cameras"]]
    data["train_cameras"] = [c for c in names if c not in data["eval_cameras"]]
    (same / "capture.json").write_text(json.dumps(data))
    config = FitConfig(roughness_candidates=5, iterations=30)
    fits = {name: run_fit(folder, tmp_path / f"fit_{name}", config)[0] for name, folder in (("native", same), ("imported", imported))}
    a, b = fits["native"], fits["imported"]
    both = (a.albedo.max(-1) > 0) & (b.albedo.max(-1) > 0)
    # relative: an OLAT fit has no brightness calibration (its gain, clipped at 0.5 here, had halved both albedos)
    relative = (np.abs(a.albedo - b.albedo) / np.maximum(a.albedo, 1e-3))[both]
    assert np.median(relative) < 0.05 and np.quantile(relative, 0.9) < 0.15, (np.median(relative), np.quantile(relative, 0.9))
    assert np.median(np.abs(a.roughness[..., 0] - b.roughness[..., 0])[both]) < 0.02
    relight = json.loads((tmp_path / "fit_imported" / "fit.json").read_text())["relight"]["held-out cameras"]
    assert relight["psnr"] > 20, relight  # held-out OLATs and the white frame, relit from held-out cameras


def test_a_capture_with_a_missing_image_imports_with_the_gap_recorded_and_fits(olat_capture, tmp_path):
    """A real capture's gap (one OLAT of one camera lost): --missing-images skip imports the rest, capture.json and
    the report name the gap; the fit and RelightNet leave that view out (reading it would stop them), a stage that
    needs it refuses before any work, naming camera and frame."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.fit.materials import FitConfig, run_fit
    from gra_mi.relightnet.train import view_jobs

    root, _, _ = olat_capture
    subject = _broken(olat_capture, tmp_path, _drop_olat)
    out = _imported(tmp_path, subject, "gap", "--missing-images", "skip")
    capture = Capture.load(out)
    gaps = [f for f in capture.frames if f.missing]
    assert len(gaps) == 1 and gaps[0].missing == ["Cam02"]
    assert gaps[0].split == "train" and "Cam02" in capture.train_cameras  # a view the fit would otherwise read
    report = json.loads((out / "import_report.json").read_text())
    assert {c["camera"]: c["missing_frames"] for c in report["cameras"]}["Cam02"] == [gaps[0].frame]
    assert "Missing images, skipped" in (out / "import_report.md").read_text()
    assert not any(c == "Cam02" and e.frame == gaps[0].frame for e, c, _ in view_jobs(capture))
    with pytest.raises(GraMiInputError, match=f"camera Cam02 has no image of frame {gaps[0].frame}"):
        load_observation(capture, "Cam02", gaps[0].frame)
    with pytest.raises(GraMiInputError, match="the refiner's sequences needs every one"):
        capture.require_images(["Cam02"], gaps, "the refiner's sequences")
    result, _ = run_fit(out, tmp_path / "fit", FitConfig(solver="closed-form", roughness_candidates=3))
    assert np.isfinite(result.albedo).all() and (result.albedo.max(-1) > 0).mean() > 0.2


def test_the_evaluation_scores_a_held_out_camera_on_the_images_it_has(imported, tmp_path):
    """A held-out camera that lost a held-out OLAT and the white frame (a real capture's gaps): `gra-mi eval` scores
    it on the frames it has, exactly as if the lost frame had never been captured; a sequence it has no image of is
    not scored and said so; every other split scores as on the whole capture. The refiner, which needs an unbroken
    video, still refuses the camera."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate
    from gra_mi.fit.materials import FitConfig, run_fit

    capture = Capture.load(imported)
    camera = capture.eval_cameras[0]
    olats = [f.frame for f in capture.frames if f.split == "test" and f.sequence == 1]
    lost, white = olats[len(olats) // 2], next(f.frame for f in capture.frames if f.split == "test" and f.sequence == 0)
    gapped, never = tmp_path / "gapped", tmp_path / "never"
    for folder in (gapped, never):
        shutil.copytree(imported, folder)
        data = json.loads((folder / "capture.json").read_text())
        if folder == gapped:  # as `gra-mi import --missing-images skip` records them
            for entry in data["frames"]:
                entry["missing"] = [camera] if entry["frame"] in (lost, white) else []
            for frame in (lost, white):
                (folder / capture.image_path(camera, frame).relative_to(imported)).unlink()
        else:  # the lost OLAT never captured at all
            data["frames"] = [e for e in data["frames"] if e["frame"] != lost]
        (folder / "capture.json").write_text(json.dumps(data))
    run_fit(imported, tmp_path / "fit", FitConfig(solver="closed-form", roughness_candidates=3))
    reports = {
        name: evaluate(EvalInputs(folder, tmp_path / "fit"), tmp_path / f"eval_{name}", EvalConfig())
        for name, folder in (("whole", imported), ("gapped", gapped), ("never", never))
    }
    splits = {name: r["stages"]["microfacet"]["splits"] for name, r in reports.items()}
    metrics = ("psnr", "ssim", "flip", "brightness")
    ours = f"test1_{camera}"
    assert set(splits["gapped"]) == set(splits["whole"]) - {f"test0_{camera}"}
    assert {m: splits["gapped"][ours][m] for m in metrics} == {m: splits["never"][ours][m] for m in metrics}
    assert splits["gapped"][ours]["frames_scored"] == splits["whole"][ours]["frames_scored"] - 1
    for split in set(splits["gapped"]) - {ours}:
        np.testing.assert_equal(splits["gapped"][split], splits["whole"][split], err_msg=split)  # NaN: one frame, no pair
    protocol = reports["gapped"]["protocol"]
    assert protocol["splits"][ours]["missing"] == [lost] and f"test0_{camera}" in protocol["unscored"]
    said = (tmp_path / "eval_gapped" / "eval.md").read_text()
    assert "(1 more without an image, left out)" in said and f"test0_{camera}: not scored: camera {camera} has no image" in said
    with pytest.raises(GraMiInputError, match="the refiner's sequences needs every one"):
        Capture.load(gapped).require_images([camera], Capture.load(gapped).frames, "the refiner's sequences")
    # truth from the reflectance field (the sum of every OLAT): the camera that lost one is left out, the other scored
    fields = evaluate(EvalInputs(gapped, tmp_path / "fit"), tmp_path / "eval_field", EvalConfig(library_envmaps=1))
    other = next(c for c in capture.eval_cameras if c != camera)
    assert f"field_{other}" in fields["stages"]["microfacet"]["splits"] and f"field_{camera}" in fields["protocol"]["unscored"]
    data = json.loads((gapped / "capture.json").read_text())
    for entry in data["frames"]:  # no held-out camera has an image of any held-out frame: nothing to score, said
        entry["missing"] = list(capture.eval_cameras) if entry["split"] == "test" else []
    (gapped / "capture.json").write_text(json.dumps(data))
    with pytest.raises(GraMiInputError, match="no held-out camera has an image of the held-out lighting"):
        evaluate(EvalInputs(gapped, tmp_path / "fit"), tmp_path / "eval_none", EvalConfig())
    assert not (tmp_path / "eval_none" / "eval.json").exists()


def test_a_camera_that_lost_an_olat_takes_that_led_s_light_from_its_neighbours(imported, tmp_path, caplog, capsys):
    """A camera's reflectance field sums every OLAT. One a real capture's gap lost is stood in for by the OLATs of
    that LED's nearest neighbours while its LED carries a small share of a lighting's light (RelightNet's synthesized
    lightings, `relight-field`): closer to the whole capture's sum than leaving its light out. Where the LED carries
    more, the camera is left out of `relight-field` over every camera and refused where it is named."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.io import read_exr
    from gra_mi.fit.materials import FitConfig, run_fit
    from gra_mi.stage.lightstage import load_calibration

    capture = Capture.load(imported)
    entry = next(f for f in capture.frames if f.split == "train" and f.pattern and "olat_" in f.pattern)
    led = int(np.argmax(capture.lighting(load_calibration(imported / "rig" / "calibration.json"), entry).max(axis=1)))
    gapped = tmp_path / "gapped"
    shutil.copytree(imported, gapped)
    data = json.loads((gapped / "capture.json").read_text())
    for frame in data["frames"]:
        frame["missing"] = ["Cam01"] if frame["frame"] == entry.frame else []
    (gapped / "capture.json").write_text(json.dumps(data))
    (gapped / capture.image_path("Cam01", entry.frame).relative_to(imported)).unlink()
    run_fit(gapped, tmp_path / "fit", FitConfig(solver="closed-form", roughness_candidates=3))
    args = ["train-relightnet", str(gapped), "--fit", str(tmp_path / "fit"), "--steps", "2", "--validate-every", "1"]
    args += ["--base-channels", "4", "--patch", "2", "--synthesized-lightings", "2", "--synthesized-validation", "1"]
    with caplog.at_level(logging.WARNING):
        assert main([*args, "--out", str(tmp_path / "rn")]) == 0
    assert any(f"camera Cam01 has no image of the OLAT of LEDs {led}" in r.message for r in caplog.records)

    drives = {"dim": np.ones(24), "dropped": np.ones(24)}
    drives["dim"][led], drives["dropped"][led] = 0.2, 0.0  # 0.86 % of the light on the lost LED; none
    for name, drive in drives.items():
        (tmp_path / f"{name}.json").write_text(json.dumps({"intensities": drive.tolist()}))
    field = ["relight-field", "--cameras", "Cam01", "--pattern"]
    assert main([field[0], str(gapped), *field[1:], str(tmp_path / "dim.json"), "--out", str(tmp_path / "rf_gap")]) == 0
    for name in drives:
        assert main([field[0], str(imported), *field[1:], str(tmp_path / f"{name}.json"), "--out", str(tmp_path / f"rf_{name}")]) == 0
    summary = json.loads((tmp_path / "rf_gap" / "summary.json").read_text())["cameras"]["Cam01"]
    assert summary["lacking_olat_frames"] == [entry.frame] and abs(summary["light_from_neighbours"]["dim"] - 0.2 / 23.2) < 1e-9
    whole, stood_in, dropped = (read_exr(tmp_path / run / name / "Cam01.exr") for run, name in
                                (("rf_dim", "dim"), ("rf_gap", "dim"), ("rf_dropped", "dropped")))  # fmt: skip
    subject = whole[..., 3] > 0.5

    def error(image):
        return float(np.sqrt(np.mean((image[subject, :3] - whole[subject, :3]) ** 2) / np.mean(whole[subject, :3] ** 2)))

    # 24 LEDs stand about 40° apart (a real stage's 331: 10°, where the error is a third of leaving the light out:
    # docs/results/missing-olats.md)
    assert error(stood_in) < 0.6 * error(dropped) and error(stood_in) < 0.01, (error(stood_in), error(dropped))

    olat = ["relight-field", str(gapped), "--olat", str(led)]
    assert main([*olat, "--out", str(tmp_path / "rf")]) == 0  # every camera: Cam01 would take all of it from neighbours
    summary = json.loads((tmp_path / "rf" / "summary.json").read_text())
    assert "Cam01" in summary["skipped"] and "Cam01" not in summary["cameras"] and len(summary["cameras"]) == 7
    _one_line_error(capsys, [*olat, "--cameras", "Cam01", "--out", str(tmp_path / "rf1")], f"drives LEDs {led} (100.0 % of its light)",
                    "no OLAT image of this camera")  # fmt: skip


@pytest.mark.parametrize(
    "missing, needles",
    [(["CamXX"], ["frames[3].missing", "CamXX"]), ("Cam02", ["frames[3].missing", "list of camera names"]), (None, ["every camera"])],
)
def test_a_capture_json_with_bad_gaps_is_refused(imported, tmp_path, missing, needles):
    from gra_mi.capture.dataset import Capture
    from gra_mi.core.errors import GraMiInputError

    copy = tmp_path / "cap"
    shutil.copytree(imported, copy)
    data = json.loads((copy / "capture.json").read_text())
    data["frames"][3]["missing"] = data["train_cameras"] + data["eval_cameras"] if missing is None else missing
    (copy / "capture.json").write_text(json.dumps(data))
    with pytest.raises(GraMiInputError) as refused:
        Capture.load(copy)
    for needle in needles:
        assert needle in str(refused.value)


def test_an_interrupted_import_resumes_to_the_same_capture(olat_capture, imported):
    root, _, subject = olat_capture
    again = root / "again"
    shutil.copytree(imported, again)
    for path in list((again / "images" / "Cam03").glob("frame_001*.exr")):
        path.unlink()
    _imported(root, subject, "again")
    for path in sorted((imported / "images" / "Cam03").glob("*.exr")):
        np.testing.assert_array_equal(read_exr(path), read_exr(again / "images" / "Cam03" / path.name))


def test_clipped_pixels_are_marked_and_left_out_of_the_fit(olat_capture, tmp_path):
    """An OLAT whose subject is clipped to 255 in its upper half: the import marks those pixels (a PNG next to the
    image), the fit's observation drops them from the mask, and the fit gathers no texel from them."""
    from PIL import Image

    from gra_mi.capture.dataset import Capture, load_fit_observation, load_observation
    from gra_mi.capture.humanolat import images_of
    from gra_mi.fit.materials import FitConfig, MaterialFitter

    root, _, subject = olat_capture
    clipped = tmp_path / "clipped"
    shutil.copytree(subject, clipped)
    image_path = images_of(clipped / "POSE_00" / "images_processed" / "Cam02")[16]  # the second OLAT (training)
    with Image.open(image_path) as image:
        pixels = np.asarray(image.convert("RGB")).copy()
    rows = np.nonzero(pixels.max(axis=-1).max(axis=1) > 0)[0]
    top = pixels[: (rows[0] + rows[-1]) // 2]
    top[top.max(axis=-1) > 0] = 255
    Image.fromarray(pixels).save(image_path, format="AVIF", quality=100, subsampling="4:4:4")
    out = _imported(tmp_path, clipped, "imported", "--cameras", "Cam01,Cam02,Cam03", "--eval-cameras", "Cam03")
    marked = [p for p in sorted((out / "images").rglob("*.saturated.png")) if p.name != "frame_0000.saturated.png"]
    assert [p.parent.name for p in marked] == ["Cam02"], marked  # the white frame (0) clips a little by itself
    capture = Capture.load(out)
    frame = int(marked[0].name.split("_")[1].split(".")[0])
    assert next(f for f in capture.frames if f.frame == frame).split == "train"
    full, fit = load_observation(capture, "Cam02", frame), load_fit_observation(capture, "Cam02", frame)
    dropped = (full[..., 3] > 0.5) & (fit[..., 3] == 0)
    assert 0.3 < dropped.sum() / (full[..., 3] > 0.5).sum() < 0.7
    report = json.loads((out / "import_report.json").read_text())
    assert next(c for c in report["cameras"] if c["camera"] == "Cam02")["saturated_fraction"] > 0
    fitter = MaterialFitter(capture, FitConfig(cameras=["Cam02"]))
    fitter.train = [f for f in fitter.train if f.frame in (frame, frame + 1)]
    views = {v.frame: v.count for v in fitter.gather_views(progress_bar=False)}
    assert 0.3 < views[frame] / views[frame + 1] < 0.8, views  # the next OLAT, unclipped, sees the whole subject


def _broken(olat_capture, tmp_path, damage) -> Path:
    _, _, subject = olat_capture
    copy = tmp_path / subject.name
    shutil.copytree(subject, copy)
    damage(copy)
    return copy


def _one_line_error(capsys, args: list[str], *needles: str) -> None:
    capsys.readouterr()
    assert main(args) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]


def _drop_camera_folder(s: Path) -> None:
    shutil.rmtree(s / "POSE_00" / "images_processed" / "Cam08")


def _drop_olat(s: Path) -> None:
    next((s / "POSE_00" / "images_processed" / "Cam02").glob("*.000017.avif")).unlink()


def _short_spiral(s: Path) -> None:
    path = s / "shared" / "LSX3_light_z_spiral.txt"
    path.write_text("\n".join(path.read_text().split()[:-1]) + "\n")


def _corrupt_avif(s: Path) -> None:
    next((s / "POSE_00" / "images_processed" / "Cam01").glob("*.000000.avif")).write_bytes(b"not an avif")


def _faceless_mesh(s: Path) -> None:
    path = s / "POSE_00" / "model" / "model.obj"
    path.write_text("\n".join(line for line in path.read_text().splitlines() if not line.startswith("f ")) + "\n")


def _world_to_camera(s: Path) -> None:
    """Camera 1's extrinsic written as world-to-camera: the classic mistake."""
    from gra_mi.capture.humanolat import read_calib, write_calib

    calib = read_calib(s / "shared" / "cameras.calib")
    m = np.eye(4)
    m[:3] = calib[0].extrinsic
    calib[0].extrinsic = np.linalg.inv(m)[:3]
    write_calib(s / "shared" / "cameras.calib", calib)


@pytest.mark.parametrize(
    ("damage", "needles"),
    [
        (_drop_camera_folder, ["cameras.calib", "8 cameras", "7 image folders"]),
        (_drop_olat, ["Cam02", "000017", "OLAT", "--missing-images skip"]),
        (_short_spiral, ["LSX3_light_z_spiral.txt", "24 LEDs"]),
        (_corrupt_avif, [".000000.avif", "not a readable image"]),
        (_faceless_mesh, ["model.obj", "no faces"]),
        (_world_to_camera, ["Cam01", "IoU", "world-to-camera"]),
    ],
    ids=["camera-count", "missing-olat", "led-count", "corrupt-avif", "faceless-mesh", "world-to-camera"],
)
def test_broken_sources_stop_with_one_line_and_nothing_written(olat_capture, tmp_path, capsys, damage, needles):
    subject = _broken(olat_capture, tmp_path, damage)
    out = tmp_path / "out"
    _one_line_error(capsys, ["import", "humanolat", str(subject), "--out", str(out)], *needles)
    assert not out.exists() or not any(out.iterdir())


def test_every_later_stage_runs_on_the_imported_capture(imported, tmp_path, capsys):
    from gra_mi.capture.dataset import Capture

    capture = Capture.load(imported)
    fit = tmp_path / "fit"
    args = ["fit", str(imported), "--out", str(fit), "--iterations", "5", "--roughness-candidates", "3"]
    assert main([*args, "--cameras", "Cam01,Cam02,Cam04", "--frame-step", "2"]) == 0  # a subset bounds a large capture's fit
    record = json.loads((fit / "fit.json").read_text())["capture"]
    train = sum(f.split == "train" for f in capture.frames)
    assert record["training_cameras"] == 3 and record["training_frames"] == (train + 1) // 2
    _one_line_error(capsys, [*args[:2], "--out", str(tmp_path / "fit_eval_camera"), "--cameras", "Cam03"], "--cameras", "Cam03")
    test_olat = next(f for f in capture.frames if f.split == "test" and f.sequence == 1)
    args = ["relight", str(imported / "scene.xml"), "--pattern", str(imported / test_olat.pattern), "--cameras", "Cam03"]
    args += ["--albedo", str(fit / "albedo.exr"), "--roughness", str(fit / "roughness.exr"), "--out", str(tmp_path / "relit")]
    assert main(args) == 0
    relightnet = tmp_path / "relightnet"
    args = ["train-relightnet", str(imported), "--fit", str(fit), "--out", str(relightnet), "--steps", "2", "--validate-every", "1"]
    assert main([*args, "--base-channels", "4", "--patch", "2"]) == 0 and (relightnet / "relightnet.safetensors").is_file()
    assert (
        main(["eval", "--capture", str(imported), "--fit", str(fit), "--relightnet", str(relightnet), "--out", str(tmp_path / "eval")]) == 0
    )
    report = json.loads((tmp_path / "eval" / "eval.json").read_text())
    assert report["stages"]["microfacet"]["status"] == report["stages"]["RelightNet"]["status"] == "done"
    glb = tmp_path / "avatar.glb"
    args = ["export", "--out", str(glb), "--subject", str(imported / "subject"), "--albedo", str(fit / "albedo.exr")]
    assert main([*args, "--roughness", str(fit / "roughness.exr")]) == 0 and glb.stat().st_size > 0


# --------------------------------------------------------------------------------------------------------------
# transforms.json: the JSON HumanOLAT's tools write (and nerfstudio's spelling of the same)
# --------------------------------------------------------------------------------------------------------------


def write_transforms_as_humanolat_tools_do(subject: Path, folder: Path, nerfstudio: bool = False) -> None:
    """transforms_train/_test.json as HumanOLAT's `generate_cam_jsons` writes them: one frame per camera and OLAT,
    camera-to-world in metres with the y and z columns negated (OpenCV → Blender), ``camera_intrinsics = [cx, cy, fx,
    fy]``, ``light_idx``, ``pl_pos`` in metres. ``nerfstudio``: the same with shared ``fl_x``/``fl_y``/``cx``/``cy``/
    ``w``/``h`` and relative paths without their extension."""
    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers, read_calib, read_spiral
    from gra_mi.capture.source_files import image_size, read_points

    calib = read_calib(subject / "shared" / "cameras.calib")
    leds = read_points(subject / "shared" / "LSX_light_positions_aligned.pc")
    order = read_spiral(subject / "shared" / "LSX3_light_z_spiral.txt", len(leds))
    olat_at, _ = olat_numbers(len(order))
    folder.mkdir(parents=True, exist_ok=True)
    for name, lights in (("train", [k for k in range(len(order)) if k % 5]), ("test", list(range(0, len(order), 5)))):
        frames = []
        for cam, c in enumerate(calib):
            images = images_of(subject / "POSE_00" / "images_processed" / camera_name(cam))
            width = image_size(images[0])[0]
            k = c.k_matrix(width)
            c2w = np.eye(4)
            c2w[:3] = c.extrinsic
            c2w[:3, 3] /= 1000.0
            c2w[:3, 1:3] *= -1
            for position in lights:
                led, path = int(order[position]), images[olat_at[position]]
                frame = {"light_idx": led, "cam_idx": cam, "transform_matrix": c2w.tolist(), "pl_intensity": [1.0, 1.0, 1.0]}
                frame["pl_pos"] = leds[led].tolist()
                if nerfstudio:
                    frame["file_path"] = str(Path("..") / path.relative_to(subject).with_suffix(""))
                    frame["mask_path"] = f"../POSE_00/segmentations/masks/000/{camera_name(cam)}.png"
                else:
                    frame |= {"file_ext": ".avif", "file_path": str(path), "camera_intrinsics": [k[0, 2], k[1, 2], k[0, 0], k[1, 1]]}
                frames.append(frame)
        data = {"frames": frames}
        if nerfstudio:
            data |= {"fl_x": k[0, 0], "fl_y": k[1, 1], "cx": k[0, 2], "cy": k[1, 2], "w": width, "h": image_size(images[0])[1]}
        (folder / f"transforms_{name}.json").write_text(json.dumps(data, indent=1))


@pytest.mark.parametrize("spelling", ["humanolat-tools", "nerfstudio"])
def test_transforms_json_imports_to_the_same_rig(olat_capture, imported, spelling):
    from gra_mi.capture.dataset import Capture
    from gra_mi.stage.lightstage import load_calibration

    root, _, subject = olat_capture
    folder = subject / f"json_{spelling}"
    write_transforms_as_humanolat_tools_do(subject, folder, nerfstudio=spelling == "nerfstudio")
    out = root / f"from_{spelling}"
    args = ["import", "transforms", str(folder), "--out", str(out), "--mesh", str(subject / "POSE_00" / "model" / "model.obj")]
    assert main([*args, "--mesh-units", "mm", "--uv-resolution", "32"]) == 0
    report = json.loads((out / "import_report.json").read_text())
    # with nerfstudio's mask_path as sharp as HumanOLAT's masks; without, the lit pixels of 8-bit OLATs stand in
    assert all(c["mask_iou"] >= (0.97 if spelling == "nerfstudio" else 0.9) for c in report["cameras"]), report["cameras"]
    capture = Capture.load(out)
    assert len(capture.frames) == 24 and sum(f.split == "test" for f in capture.frames) == 5
    mine, theirs = (load_calibration(p / "rig" / "calibration.json") for p in (out, imported))
    for a, b in zip(mine.cameras, theirs.cameras, strict=True):
        assert a.name == b.name
        np.testing.assert_allclose(a.camera_to_world, b.camera_to_world, atol=1e-5)
    np.testing.assert_allclose(mine.led_positions, theirs.led_positions, atol=1e-5)


def test_a_transforms_json_in_a_frame_of_its_own_is_aligned_by_camera_places(olat_capture, imported, tmp_path):
    """A transforms.json whose cameras are in a frame and scale of their own (a reconstruction's; its pl_pos and the mesh
    in the stage's), with --align-cameras placing four of its cameras (two by name, two by an image's file_path as the
    JSON has it): the rig imports as the stage's own."""
    from scipy.spatial.transform import Rotation

    from gra_mi.stage.lightstage import load_calibration

    root, _, subject = olat_capture
    folder = tmp_path / "json"
    write_transforms_as_humanolat_tools_do(subject, folder)
    scale, turn, shift = 2.7, Rotation.from_rotvec([-0.4, 0.9, 1.3]).as_matrix(), np.array([0.3, -4.0, 1.5])
    placed, paths = {}, {}
    for path in folder.glob("transforms_*.json"):
        data = json.loads(path.read_text())
        for frame in data["frames"]:
            c2w = np.array(frame["transform_matrix"])
            placed[f"Cam{frame['cam_idx'] + 1:02d}"] = c2w[:3, 3].copy()
            paths.setdefault(f"Cam{frame['cam_idx'] + 1:02d}", frame["file_path"])
            c2w[:3] = np.column_stack([turn @ c2w[:3, :3], scale * turn @ c2w[:3, 3] + shift])
            frame["transform_matrix"] = c2w.tolist()
        path.write_text(json.dumps(data))
    named = {n: paths[n] if k < 2 else n for k, n in enumerate(sorted(placed)[::2])}  # a camera by name, or by an image's file_path
    (tmp_path / "places.txt").write_text("".join(f"{named[n]} {' '.join(f'{x:.17g}' for x in placed[n])}\n" for n in named))
    out = tmp_path / "aligned"
    args = ["import", "transforms", str(folder), "--out", str(out), "--mesh", str(subject / "POSE_00" / "model" / "model.obj")]
    assert main([*args, "--mesh-units", "mm", "--uv-resolution", "32", "--align-cameras", str(tmp_path / "places.txt")]) == 0
    mine, theirs = (load_calibration(p / "rig" / "calibration.json") for p in (out, imported))
    for a, b in zip(mine.cameras, theirs.cameras, strict=True):
        np.testing.assert_allclose(a.camera_to_world, b.camera_to_world, atol=1e-5)
    said = (out / "import_report.md").read_text()
    assert "scaled 0.37037" in said and "Only" not in said  # (four cameras placed)


def test_a_place_names_its_camera_by_any_name_the_source_gives_it():
    """A places file's NAME: the capture's camera name, the source's own name of it (EasyMocap's `01` for cam01), an
    image path as the source lists it (transforms.json's file_path, whatever folder it is in), or an image path whose
    folder or stem is one of those (COLMAP's image names); anything else is refused, naming the cameras."""
    from gra_mi.capture.alignment import camera_named
    from gra_mi.core.errors import GraMiInputError

    aliases = {"01": "cam01", "shots/take_0003.png": "cam02"}
    said = {name: camera_named(Path("places.txt"), name, ["cam01", "cam02"], aliases)
            for name in ("cam02", "01", "shots/take_0003.png", "images/01/000000.jpg", "cam01.png", "rig\\cam02\\0.png")}  # fmt: skip
    assert said == {"cam02": "cam02", "01": "cam01", "shots/take_0003.png": "cam02", "images/01/000000.jpg": "cam01",
                    "cam01.png": "cam01", "rig\\cam02\\0.png": "cam02"}  # fmt: skip
    with pytest.raises(GraMiInputError, match="'shots/take_0004.png' names no camera of the calibration .its cameras: cam01, cam02"):
        camera_named(Path("places.txt"), "shots/take_0004.png", ["cam01", "cam02"], aliases)


def test_exif_orientation_is_said_where_the_pixels_do_not_fit(olat_capture, tmp_path, capsys):
    """Photos whose EXIF Orientation tag turns them for display (a phone's, a DSLR's): gra-mi reads pixels as stored,
    as COLMAP does. Turned pixels a calibration made on the shown image does not fit stop the import naming the tag;
    a tag over pixels that fit the calibration as stored changes nothing."""
    from PIL import Image

    from gra_mi.capture.source_files import read_image
    from gra_mi.core.color import srgb_encode

    _, _, subject = olat_capture
    folder = subject / "json_exif"  # its file paths lead into the subject's folder
    write_transforms_as_humanolat_tools_do(subject, folder, nerfstudio=True)
    args = ["import", "transforms", str(folder), "--mesh", str(subject / "POSE_00" / "model" / "model.obj"), "--mesh-units", "mm"]
    args += ["--uv-resolution", "32"]
    originals, masks = {}, {}

    def tag_cam01(quarters: int, orientation: int, mask_file: bool = False) -> None:
        for path in folder.glob("transforms_*.json"):
            data = json.loads(path.read_text())
            for k, frame in enumerate(f for f in data["frames"] if f["cam_idx"] == 0):
                masks.setdefault((path.name, k), frame.pop("mask_path", None))
                if mask_file:  # a mask file fits the mesh however the pixels are turned: checked against the pixels
                    frame["mask_path"] = masks[(path.name, k)]
                source = originals.setdefault((path.name, k), (path.parent / frame["file_path"]).resolve())
                pixels = (srgb_encode(np.clip(read_image(source.with_name(source.name + ".avif"))[0], 0, 1)) * 255 + 0.5).astype(np.uint8)
                exif = Image.Exif()
                exif[0x0112] = orientation
                target = tmp_path / "photos" / f"{path.stem}_{k}.png"
                target.parent.mkdir(exist_ok=True)
                Image.fromarray(np.ascontiguousarray(np.rot90(pixels, quarters))).save(target, exif=exif)
                frame["file_path"] = str(target)
            path.write_text(json.dumps(data))

    tag_cam01(1, orientation=6)  # stored turned a quarter, shown upright: as the calibration saw it
    _one_line_error(capsys, [*args, "--out", str(tmp_path / "turned")], "EXIF orientation 6", "rotated 90° clockwise", "as stored")
    tag_cam01(2, orientation=3)  # turned half: the size fits, the mesh does not
    _one_line_error(capsys, [*args, "--out", str(tmp_path / "upside_down")], "Cam01", "IoU", "EXIF orientation 3", "as stored")
    tag_cam01(2, orientation=3, mask_file=True)
    _one_line_error(capsys, [*args, "--out", str(tmp_path / "against_mask")], "Cam01", "outside its mask", "EXIF orientation 3")
    tag_cam01(0, orientation=3)  # a tag over pixels the calibration fits as stored
    assert main([*args, "--out", str(tmp_path / "as_stored")]) == 0
    report = json.loads((tmp_path / "as_stored" / "import_report.json").read_text())
    assert report["cameras"][0]["mask_iou"] > 0.9 and report["cameras"][0]["exif_turned"] == 24, report["cameras"][0]
    assert "EXIF orientation tag, read as stored" in (tmp_path / "as_stored" / "import_report.md").read_text()


def _with_background(subject: Path, folder: Path) -> Path:
    """The layout's images as photographs that keep their background: each camera's images over a backdrop (soft
    stripes and blobs, as bright as the subject), the subject's edge where its mask file says."""
    from scipy.ndimage import gaussian_filter

    from gra_mi.capture.humanolat import camera_name, images_of, write_avif
    from gra_mi.capture.source_files import read_image, read_mask

    copy = folder / subject.name
    shutil.copytree(subject, copy, ignore=shutil.ignore_patterns("json_*"))
    rng = np.random.default_rng(3)
    for cam in range(8):
        images = images_of(copy / "POSE_00" / "images_processed" / camera_name(cam))
        mask = read_mask(copy / "POSE_00" / "segmentations" / "masks" / "000" / f"{camera_name(cam)}.png")
        h, w = mask.shape
        x = np.arange(w)[None, :, None]
        backdrop = 0.35 + 0.15 * np.sin(x / 3.0 + cam) + 0.2 * gaussian_filter(rng.standard_normal((h, w, 3)), 4) * 8
        cover = gaussian_filter(mask.astype(np.float64), 0.7)[..., None]
        for path in images.values():
            rgb = read_image(path)[0]
            level = float(np.median(rgb[mask].max(axis=-1))) if rgb[mask].any() else 0.0
            write_avif(path, rgb * cover + np.clip(backdrop, 0.05, 1.0) * level * (1 - cover))
    return copy


def test_a_masked_image_a_neighbouring_camera_took_is_told_by_the_mask_that_holds_its_light(tmp_path):
    """On a 40-camera stage a neighbour's image puts 5–30 % of its light outside a camera's own mask (below the 25 %
    that stops any image): where another camera's mask of about the same size holds it several times better, the
    image is refused naming both. A loose mask edge, or a much larger mask that would hold any light, is not."""
    from gra_mi.capture.mask_fit import NEIGHBOUR_OUTSIDE, OUTSIDE_MASK, _check_light, _light_outside
    from gra_mi.core.errors import GraMiInputError

    y, x = np.mgrid[:100, :100]

    def disk(cx: float, r: float = 20.0) -> np.ndarray:
        return (x - cx) ** 2 + (y - 50) ** 2 <= r**2

    masks = {"Cam01": disk(50), "Cam02": disk(58), "Cam09": np.ones((100, 100), bool)}
    neighbours = np.repeat(disk(58)[..., None], 3, axis=-1).astype(np.float32)  # Cam02's view, shown as Cam01's
    outside = _light_outside(neighbours, None, masks["Cam01"])
    assert NEIGHBOUR_OUTSIDE < outside < OUTSIDE_MASK, outside  # the old rule alone let it through
    with pytest.raises(GraMiInputError, match="camera Cam01: .* outside camera Cam02's mask: the image looks like camera Cam02's"):
        _check_light("Cam01", tmp_path / "Cam01.avif", neighbours, None, masks, "Cam01.png")
    loose = np.repeat(disk(50, 23.0)[..., None], 3, axis=-1).astype(np.float32)  # a mask 3 pixels tight all round
    assert _light_outside(loose, None, masks["Cam01"]) > NEIGHBOUR_OUTSIDE
    _check_light("Cam01", tmp_path / "Cam01.avif", loose, None, masks, "Cam01.png")  # no mask holds it BETTER_LIGHT× better
    _check_light("Cam01", tmp_path / "Cam01.avif", neighbours, None, {k: masks[k] for k in ("Cam01", "Cam09")}, "Cam01.png")


def test_an_image_that_keeps_its_background_is_held_against_its_mask(olat_capture, tmp_path, capsys):
    """Photographs with their background (no black around the subject) were never checked against their mask files:
    their edges are. An image whose edges follow another camera's mask, or its own mask turned 180°, clearly better
    than its own stops the import naming both; the untouched photographs import. Without mask files, the error says
    where this source's masks go."""
    from gra_mi.capture.humanolat import camera_name, images_of, write_avif
    from gra_mi.capture.mask_fit import BETTER_OUTLINE, edge_strength, outline, outline_fit
    from gra_mi.capture.source_files import read_image, read_mask

    _, _, subject = olat_capture
    photos = _with_background(subject, tmp_path / "layout")
    folders = [photos / "POSE_00" / "images_processed" / camera_name(cam) for cam in range(8)]
    masks = [read_mask(photos / "POSE_00" / "segmentations" / "masks" / "000" / f"{camera_name(cam)}.png") for cam in range(8)]
    edges = [edge_strength(read_image(images_of(f)[0])[0]) for f in folders]
    fits = np.array([[outline_fit(e, np.flatnonzero(outline(m))) for m in masks] for e in edges])
    others = np.where(np.eye(8, dtype=bool), 0, fits).max(axis=1)
    assert (others < BETTER_OUTLINE * np.diag(fits)).all(), fits.round(2)  # cameras side by side see alike: no more
    _imported(tmp_path, photos, "photos")
    truth = json.loads((subject / "synthetic.json").read_text())
    args = ["import", "humanolat", str(photos), "--uv-resolution", "32", "--led-intensity", str(truth["import_led_intensity"])]
    swapped = {n: (images_of(folders[1])[n], images_of(folders[4])[n]) for n in images_of(folders[1])}
    for a, b in swapped.values():  # Cam02's and Cam05's images swapped
        data = a.read_bytes()
        a.write_bytes(b.read_bytes())
        b.write_bytes(data)
    _one_line_error(capsys, [*args, "--out", str(tmp_path / "swapped")], "camera Cam02", "Cam05's mask", "does not go with its mask")
    for a, b in swapped.values():
        data = a.read_bytes()
        a.write_bytes(b.read_bytes())
        b.write_bytes(data)
    for path in images_of(folders[2]).values():  # Cam03's turned 180°: the size fits
        write_avif(path, np.rot90(read_image(path)[0], 2))
    _one_line_error(capsys, [*args, "--out", str(tmp_path / "turned")], "camera Cam03", "turned 180°", "does not go with its mask")
    assert not (tmp_path / "swapped").exists() and not (tmp_path / "turned").exists()
    folder = photos / "json_no_masks"  # the same photographs through a transforms.json without mask_path
    write_transforms_as_humanolat_tools_do(photos, folder)
    args = ["import", "transforms", str(folder), "--mesh", str(photos / "POSE_00" / "model" / "model.obj"), "--mesh-units", "mm"]
    _one_line_error(capsys, [*args, "--out", str(tmp_path / "no_masks")], "covers the whole image", "keep their background", "mask_path")


def _olat_ratio_spread(native, out: Path) -> float:
    """How far each OLAT frame's brightness over its LED's stated intensity strays from the native capture's, over
    the frames (std / mean of the ratio, the worst channel): 0 where every LED is lit as the capture says."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.stage.lightstage import load_calibration

    capture = Capture.load(out)
    stages = load_calibration(out / "rig" / "calibration.json"), load_calibration(native.folder / "rig" / "calibration.json")
    native_frames = {Path(f.pattern).stem: f for f in native.frames if f.kind == "pattern" and "olat" in f.pattern}
    ratios = []
    for frame in (f for f in capture.frames if f.kind == "pattern" and "olat" in f.pattern):
        theirs = native_frames[Path(frame.pattern).stem]
        led = int(Path(frame.pattern).stem.split("_")[1])
        a, b = load_observation(capture, "Cam01", frame.frame), load_observation(native, "cam00", theirs.frame)
        inside = (a[..., 3] > 0.99) & (b[..., 3] > 0.99)
        mine = a[..., :3][inside].mean(axis=0) / capture.lighting(stages[0], frame)[led]
        ratios.append(mine / (b[..., :3][inside].mean(axis=0) / native.lighting(stages[1], theirs)[led]))
    ratios = np.array(ratios)
    return float((ratios.std(axis=0) / ratios.mean(axis=0)).max())


@pytest.fixture(scope="module")
def gained_stage(olat_capture):
    """The HumanOLAT layout of a stage whose LEDs differ in brightness and colour: each OLAT photo scaled by its LED's
    RGB gain (LED k's: row k). Returns (the subject folder, the gains)."""
    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers, read_spiral, write_avif
    from gra_mi.capture.source_files import read_image

    root, _, subject = olat_capture
    gains = np.random.default_rng(3).uniform(0.5, 1.0, (24, 3))
    gained = root / "gained_layout" / subject.name
    shutil.copytree(subject, gained, ignore=shutil.ignore_patterns("json_*"))
    order = read_spiral(gained / "shared" / "LSX3_light_z_spiral.txt", 24)
    for cam in range(8):
        images = images_of(gained / "POSE_00" / "images_processed" / camera_name(cam))
        for position, number in enumerate(olat_numbers(24)[0]):
            write_avif(images[number], read_image(images[number])[0] * gains[order[position]])
    return gained, gains


def test_led_gains_light_each_olat_by_its_led(olat_capture, imported, gained_stage, tmp_path, capsys):
    """A stage whose LEDs differ in brightness and colour: imported with the gains (a --led-gains file, or
    transforms.json's pl_intensity), every OLAT frame's brightness over its LED's intensity is the native capture's;
    imported without, it strays by the gains' spread."""
    _, native, _ = olat_capture
    gained, gains = gained_stage
    (tmp_path / "gains.txt").write_text("# LED gains, r g b\n" + "".join(f"{r} {g} {b}\n" for r, g, b in gains))
    with_gains = _imported(tmp_path, gained, "with_gains", "--led-gains", str(tmp_path / "gains.txt"))
    without = _imported(tmp_path, gained, "without", "--test-olat-every", "5")
    assert "normalised to a mean of 1" in json.loads((with_gains / "capture.json").read_text())["source"]["gains"]
    # the equal-gain stage's own import strays by 8-bit quantisation of dim OLATs alone (1.5 %); the gained one's
    # photos were quantised twice and are dimmer (2.6 %); left without its gains, it strays by their spread (19 %)
    floor = _olat_ratio_spread(native, imported)
    assert _olat_ratio_spread(native, with_gains) < 2 * floor and _olat_ratio_spread(native, without) > 6 * floor, floor
    # the same gains as the dataset's tools would state them, per frame
    folder = gained / "json"
    write_transforms_as_humanolat_tools_do(gained, folder)
    for path in folder.glob("transforms_*.json"):
        data = json.loads(path.read_text())
        for frame in data["frames"]:
            frame["pl_intensity"] = gains[frame["light_idx"]].tolist()
        path.write_text(json.dumps(data))
    out = tmp_path / "from_json"
    args = ["import", "transforms", str(folder), "--out", str(out), "--mesh", str(gained / "POSE_00" / "model" / "model.obj")]
    assert main([*args, "--mesh-units", "mm", "--uv-resolution", "32"]) == 0
    assert _olat_ratio_spread(native, out) < 2 * floor
    # both at once, or either and an estimate, are two answers to one question
    args[args.index(str(out))] = str(tmp_path / "two_answers")
    _one_line_error(capsys, [*args, "--led-gains", str(tmp_path / "gains.txt")], "pl_intensity", "one or the other")
    _one_line_error(capsys, [*args, "--estimate-led-gains"], "pl_intensity", "not both")


def test_led_gains_are_estimated_from_the_olats(olat_capture, gained_stage, tmp_path, monkeypatch, capsys):
    """Without a calibration, --estimate-led-gains measures each LED's gain on the OLATs against the albedo every
    LED's images share. The photos are path-traced (interreflections, a diffuse lobe that is not Lambertian), not the
    one-bounce model's; three LEDs play HumanOLAT's door LEDs, so the rig's order is not the source's numbering."""
    from gra_mi.capture import humanolat
    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers, read_spiral, write_avif
    from gra_mi.capture.source_files import read_image
    from gra_mi.stage.lightstage import load_calibration

    monkeypatch.setattr(humanolat, "DOOR_LEDS", (3, 7, 11))
    gained, gains = gained_stage
    out = _imported(tmp_path, gained, "estimated", "--estimate-led-gains")
    report = json.loads((out / "import_report.json").read_text())["leds"]
    numbers = [k for k in range(24) if k not in (3, 7, 11)]  # the rig's LEDs, in its order
    measured = np.isin(numbers, report["estimate"]["unmeasured_leds"], invert=True)
    assert measured.sum() >= 18, report["estimate"]
    estimated = load_calibration(out / "rig" / "calibration.json").led_gains
    truth = gains[numbers] / gains[numbers][measured].mean(axis=0)
    error, equal = np.abs(estimated / truth - 1)[measured], np.abs(1 / truth - 1)[measured]
    # 16 % off with equal gains; measured to about 1.5 % (the model's own bias on an equal-gain stage: about 1 %)
    assert error.mean() < 0.03 and error.max() < 0.1 and equal.mean() > 0.12, (error.mean(), error.max(), equal.mean())
    assert np.all(estimated[~measured] == 1.0) and "estimated" in json.loads((out / "capture.json").read_text())["source"]["gains"]
    assert "import/led_gains.png" in (out / "import_report.md").read_text() and (out / "import" / "led_gains.png").is_file()
    # the gains file is a --led-gains file for the stage's other captures, in the source's numbering
    text = (out / "import" / "led_gains.txt").read_text()
    assert text.count("# not in the rig") == 3 and len([x for x in text.splitlines() if not x.startswith("#")]) == 24
    again = _imported(tmp_path, gained, "given", "--led-gains", str(out / "import" / "led_gains.txt"))
    np.testing.assert_allclose(load_calibration(again / "rig" / "calibration.json").led_gains, estimated, atol=2e-6)
    # two shards: the last measures them on every shard's images, as one process does
    for shard in ("0/2", "1/2"):
        sharded = _imported(tmp_path, gained, "sharded", "--estimate-led-gains", "--shard", shard)
    np.testing.assert_array_equal(load_calibration(sharded / "rig" / "calibration.json").led_gains, estimated)
    # estimated and given at once are two answers to one question
    args = ["import", "humanolat", str(gained), "--out", str(tmp_path / "both"), "--estimate-led-gains"]
    _one_line_error(capsys, [*args, "--led-gains", str(tmp_path / "x")], "estimate", "not both")
    assert report["estimate"]["suspect_leds"] == []
    # two neighbouring LEDs' OLATs swapped (a mixed-up firing order): each lit where the other's position says
    swapped = tmp_path / "swapped" / gained.name
    shutil.copytree(gained, swapped, ignore=shutil.ignore_patterns("json*"))
    spiral = read_spiral(swapped / "shared" / "LSX3_light_z_spiral.txt", 24)
    a, b = (olat_numbers(24)[0][int(np.flatnonzero(spiral == led)[0])] for led in (5, 10))  # 10: 5's nearest
    for cam in range(8):
        images = images_of(swapped / "POSE_00" / "images_processed" / camera_name(cam))
        pixels = read_image(images[a])[0]
        write_avif(images[a], read_image(images[b])[0])
        write_avif(images[b], pixels)
    mixed = _imported(tmp_path, swapped, "swapped_out", "--estimate-led-gains")
    assert json.loads((mixed / "import_report.json").read_text())["leds"]["estimate"]["suspect_leds"] == [5, 10]
    assert "Check the light order" in (mixed / "import_report.md").read_text()
    # a dead LED measures as one: refused, as a given gain that low is
    dead = tmp_path / "dead" / gained.name
    shutil.copytree(gained, dead, ignore=shutil.ignore_patterns("json*"))
    position = int(np.flatnonzero(read_spiral(dead / "shared" / "LSX3_light_z_spiral.txt", 24) == 5)[0])
    for cam in range(8):
        image = images_of(dead / "POSE_00" / "images_processed" / camera_name(cam))[olat_numbers(24)[0][position]]
        write_avif(image, np.zeros_like(read_image(image)[0]))
    args[2:5] = [str(dead), "--out", str(tmp_path / "dead_out")]
    _one_line_error(capsys, args, "LED 5's OLATs are dark", "dead LED")


@pytest.mark.parametrize("planes, greyscale, alpha", [(1, True, False), (2, True, True), (3, False, False), (4, False, True)])
def test_16_bit_pngs_keep_every_bit(tmp_path, planes, greyscale, alpha):
    """A 16-bit PNG as pypng writes it (grey, grey + alpha, RGB, RGBA): every level decoded with the sRGB curve, not
    Pillow's 8-bit reading of it; the top level saturates; alpha in [0, 1]."""
    import png

    from gra_mi.capture.source_files import read_image
    from gra_mi.core.color import srgb_decode

    levels = np.random.default_rng(planes).integers(0, 65536, (6, 9, planes)).astype(np.uint16)
    levels[0, 0, 0] = 65535
    path = tmp_path / "image.png"
    with open(path, "wb") as fh:
        png.Writer(9, 6, greyscale=greyscale, alpha=alpha, bitdepth=16).write(fh, levels.reshape(6, -1).tolist())
    rgb, saturated, opacity = read_image(path)
    colour = levels[..., : planes - alpha]
    expected = srgb_decode(np.repeat(colour, 3 // colour.shape[-1], axis=-1).astype(np.float32) / 65535).astype(np.float32)
    np.testing.assert_array_equal(rgb, expected)
    assert saturated[0, 0] and saturated.sum() == (colour == 65535).any(axis=-1).sum()
    if alpha:
        np.testing.assert_allclose(opacity, levels[..., -1] / 65535, atol=1e-7)


def test_an_exr_source_image_is_read_as_radiance_or_refused_by_name(tmp_path):
    """A grey (Y) EXR is every channel's; NaN, infinite or negative radiance and an alpha outside [0, 1] are the
    source's faults, named by its file before anything is written (not found later in the written capture)."""
    from gra_mi.capture.source_files import read_image
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.core.io import write_exr

    write_exr(tmp_path / "grey.exr", np.full((4, 5), 0.25, np.float32))
    rgb, saturated, alpha = read_image(tmp_path / "grey.exr")
    assert rgb.shape == (4, 5, 3) and (rgb == 0.25).all() and not saturated.any() and alpha is None
    for name, value, channel, needle in (("nan", np.nan, 0, "NaN"), ("negative", -0.01, 1, "negative"), ("alpha", 1.5, 3, "alpha")):
        image = np.full((4, 5, 4), 0.5, np.float32)
        image[1, 2, channel] = value
        write_exr(tmp_path / f"{name}.exr", image)
        with pytest.raises(GraMiInputError, match=needle) as info:
            read_image(tmp_path / f"{name}.exr")
        assert f"{name}.exr" in str(info.value)


def test_a_16_bit_mask_is_split_at_half_its_range(tmp_path):
    """Pillow's conversion to 8 bits clips 16-bit levels (200 of 65,535 would become 200 of 255: the subject)."""
    import png
    from PIL import Image

    from gra_mi.capture.source_files import read_mask

    with open(tmp_path / "mask16.png", "wb") as fh:
        png.Writer(5, 1, greyscale=True, bitdepth=16).write(fh, [[0, 200, 20000, 40000, 65535]])
    assert read_mask(tmp_path / "mask16.png").tolist() == [[False, False, False, True, True]]
    Image.fromarray(np.array([[0, 100, 200]], np.uint8)).save(tmp_path / "mask8.png")
    assert read_mask(tmp_path / "mask8.png").tolist() == [[False, False, True]]


@pytest.mark.parametrize(
    "text, needles",
    [
        ("1\n" * 23, ["23 gains", "24 LEDs"]),
        ("1\n" * 23 + "nan\n", ["line 24", "finite"]),
        ("1\n" * 23 + "-1\n", ["line 24", "non-negative"]),
        ("1\n" * 23 + "1 1\n", ["line 24", "r g b"]),
        ("1\n" * 23 + "bright\n", ["line 24"]),
        ("1\n" * 23 + "0.001\n", ["LED 23", "below 1%"]),
        ("0\n" * 24, ["every gain is 0"]),
    ],
)
def test_bad_led_gains_are_named(tmp_path, text, needles):
    from gra_mi.capture.source_files import read_led_gains
    from gra_mi.core.errors import GraMiInputError

    (tmp_path / "gains.txt").write_text(text)
    with pytest.raises(GraMiInputError) as info:
        read_led_gains(tmp_path / "gains.txt", list(range(24)))
    for needle in ["gains.txt", *needles]:
        assert needle in str(info.value)


def test_led_gains_are_read_in_the_sources_numbering_and_normalised(tmp_path):
    from gra_mi.capture.source_files import read_led_gains

    (tmp_path / "gains.txt").write_text("# stage calibration\n1.0\n\n0.5 1.0 1.5  # a blue LED\n2\n3\n")
    gains = read_led_gains(tmp_path / "gains.txt", [1, 3])  # a source whose LEDs are numbered 1 and 3
    np.testing.assert_allclose(gains, np.array([[0.5, 1.0, 1.5], [3.0, 3.0, 3.0]]) / 2.0)  # their mean: 2
    (tmp_path / "binary.txt").write_bytes(bytes(range(256)))
    from gra_mi.core.errors import GraMiInputError

    with pytest.raises(GraMiInputError, match="binary.txt"):
        read_led_gains(tmp_path / "binary.txt", [0])
    with pytest.raises(GraMiInputError, match="missing"):
        read_led_gains(tmp_path / "absent.txt", [0])


def test_a_mesh_without_uvs_gets_an_atlas_and_fits(olat_capture, tmp_path):
    """A PLY with positions and faces only (a scan as many tools export it): the import generates a UV atlas
    (xatlas), reprojects as well as the mesh with its own atlas, and the fit runs in the new atlas."""
    import trimesh

    from gra_mi.capture.source_files import read_obj
    from gra_mi.fit.materials import FitConfig, run_fit

    _, _, subject = olat_capture
    folder = subject / "json_ply"  # beside the pose, as the dataset's tools write it
    write_transforms_as_humanolat_tools_do(subject, folder, nerfstudio=True)
    obj = read_obj(subject / "POSE_00" / "model" / "model.obj")
    trimesh.Trimesh(obj.positions, obj.faces, process=False).export(tmp_path / "scan.ply")
    out = tmp_path / "from_ply"
    args = ["import", "transforms", str(folder), "--out", str(out), "--mesh", str(tmp_path / "scan.ply")]
    assert main([*args, "--mesh-units", "mm", "--uv-resolution", "32"]) == 0
    report = json.loads((out / "import_report.json").read_text())
    assert report["uv_atlas"].startswith("generated (xatlas")
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
    result, _ = run_fit(out, tmp_path / "fit", FitConfig(solver="closed-form", roughness_candidates=3))
    observed = result.observed_cameras > 0
    assert observed.mean() > 0.3 and np.isfinite(result.albedo).all()


def test_a_transforms_json_without_intrinsics_or_lights_is_refused(olat_capture, tmp_path, capsys):
    root, _, subject = olat_capture
    folder = tmp_path / "json"
    write_transforms_as_humanolat_tools_do(subject, folder)
    mesh = str(subject / "POSE_00" / "model" / "model.obj")
    original = (folder / "transforms_train.json").read_text()
    data = json.loads(original)
    del data["frames"][3]["camera_intrinsics"]
    (folder / "transforms_train.json").write_text(json.dumps(data))
    args = ["import", "transforms", str(folder), "--out", str(tmp_path / "out"), "--mesh", mesh, "--mesh-units", "mm"]
    _one_line_error(capsys, args, "transforms_train.json", "frames[3]", "intrinsics")
    del data["frames"][3]
    for frame in data["frames"]:
        frame.pop("light_idx")
    (folder / "transforms_train.json").write_text(json.dumps(data))
    _one_line_error(capsys, args, "transforms_train.json", "frames[0]", "light_idx")
    _one_line_error(capsys, args[:-4], "--mesh")
    data["frames"][0] |= {"light_idx": 0, "k1": 0.05}  # one frame of a camera with a lens the others lack
    (folder / "transforms_train.json").write_text(json.dumps(data))
    _one_line_error(capsys, args, "transforms_train.json", "frames[", "two different lens distortions")
    data = json.loads(original)
    mirrored = np.array(data["frames"][2]["transform_matrix"])
    mirrored[:3, 0] *= -1
    for bad, needles in (
        ({"camera_angle_x": 0}, ["frames[2].camera_angle_x", "greater than 0"]),
        ({"fl_x": "abc"}, ["frames[2].fl_x", "valid number"]),
        ({"w": 0}, ["frames[2].w", "greater than 0"]),
        ({"camera_intrinsics": [1.0, 2.0, 3.0]}, ["frames[2].camera_intrinsics", "4 numbers"]),
        ({"camera_intrinsics": [36.0, 48.0, -100.0, 100.0]}, ["frames[2].camera_intrinsics", "fx, fy > 0"]),
        ({"transform_matrix": mirrored.tolist()}, ["frames[2].transform_matrix", "mirrored"]),
        ({"transform_matrix": [[1, 0], [0, 1]]}, ["frames[2].transform_matrix", "4 × 4"]),
        ({"light_idx": -3}, ["frames[2].light_idx"]),
        ({"pl_pos": [0, "x", 1]}, ["frames[2].pl_pos"]),
        ({"camera_model": "EQUIRECTANGULAR"}, ["frames[2]", "camera_model 'EQUIRECTANGULAR'"]),
        ({"camera_model": "PINHOLE", "k1": 0.1}, ["frames[2]", "has no distortion"]),
        ({"camera_model": "OPENCV_FISHEYE", "k1": 0.1, "p1": 0.01}, ["frames[2]", "tangential"]),
        ({"k2": "abc"}, ["frames[2].k2", "valid number"]),
        ({"k1": 0.05}, ["frames[2]", "two different lens distortions"]),
        ({"pl_intensity": [1, -1, 1]}, ["frames[2].pl_intensity", "non-negative"]),
        ({"pl_intensity": [0.5, 0.5]}, ["frames[2].pl_intensity"]),
        ({"pl_intensity": [0.5, 0.5, 0.5]}, ["pl_intensity", "two intensities"]),  # its LED's other frames say 1
    ):
        broken = json.loads(json.dumps(data))
        broken["frames"][2] |= bad
        (folder / "transforms_train.json").write_text(json.dumps(broken))
        _one_line_error(capsys, args, "transforms_train.json", *needles)
        assert not (tmp_path / "out").exists()


def test_nerfstudios_lens_terms_are_read_per_camera_model(olat_capture):
    from gra_mi.capture.transforms import TransformsOptions, read_transforms

    _, _, subject = olat_capture
    folder = subject / "json_lens"  # its paths are relative to the subject's folder
    write_transforms_as_humanolat_tools_do(subject, folder, nerfstudio=True)
    mesh = subject / "POSE_00" / "model" / "model.obj"
    for name in ("train", "test"):
        data = json.loads((folder / f"transforms_{name}.json").read_text())
        data |= {"camera_model": "OPENCV_FISHEYE", "k1": 0.01, "k2": -0.002, "k3": 0.0005, "k4": -0.0001}
        (folder / f"transforms_{name}.json").write_text(json.dumps(data))
    source = read_transforms(folder, TransformsOptions(mesh=mesh, mesh_units="mm"))
    assert {(c.lens.model, c.lens.k, c.lens.p) for c in source.calib} == {("fisheye", (0.01, -0.002, 0.0005, -0.0001), (0.0, 0.0))}
    for name in ("train", "test"):  # OPENCV (nerfstudio's default model): k1…k4 of r², r⁴, r⁶, r⁸ and p1, p2
        data = json.loads((folder / f"transforms_{name}.json").read_text())
        data |= {"camera_model": "OPENCV", "p1": 0.001, "p2": -0.002}
        (folder / f"transforms_{name}.json").write_text(json.dumps(data))
    source = read_transforms(folder, TransformsOptions(mesh=mesh, mesh_units="mm"))
    assert {(c.lens.model, c.lens.p) for c in source.calib} == {("radial-tangential", (0.001, -0.002))}


def test_a_tracked_sequence_under_environment_maps_imports(path_traced_fit, tmp_path):
    """A moving subject (one OBJ per mesh frame) under environment maps, as a transforms.json with `mesh_frame`,
    linear EXR images with alpha masks and the rig's LEDs from --leds: every frame keeps its own pose."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.capture.source_files import write_obj, write_points
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    native = Capture.load(path_traced_fit / "cap")
    stage, seq = load_calibration(native.folder / "rig" / "calibration.json"), load_sequence(native.folder / "subject")
    lit = [f for f in native.frames if f.kind == "envmap"]
    (tmp_path / "meshes").mkdir()
    for k, entry in enumerate(lit):
        write_obj(tmp_path / "meshes", seq.vertices[entry.mesh_frame], seq.uvs, seq.faces, None)
        (tmp_path / "meshes" / "model.obj").rename(tmp_path / "meshes" / f"frame_{k:04d}.obj")
    write_points(tmp_path / "leds.pc", stage.led_positions)
    for split in ("train", "test"):
        frames = []
        for k, entry in enumerate(lit):
            if entry.split != split:
                continue
            for i, cam in enumerate(stage.cameras):
                c2w = cam.camera_to_world.copy()
                c2w[:3, 1:3] *= -1  # OpenCV → OpenGL, as transforms.json holds it
                frames.append(
                    {"file_path": str(native.image_path(cam.name, entry.frame)), "transform_matrix": c2w.tolist(), "cam_idx": i}
                    | {"fl_x": cam.fx, "fl_y": cam.fy, "cx": cam.cx, "cy": cam.cy, "w": cam.width, "h": cam.height}
                    | {"envmap": str(native.folder / entry.envmap), "mesh_frame": k}
                )
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps({"frames": frames}))
    out = tmp_path.parent / f"{tmp_path.name}_imported"  # beside the source: an output inside an input is refused
    args = ["import", "transforms", str(tmp_path), "--out", str(out), "--mesh", str(tmp_path / "meshes")]
    assert main([*args, "--leds", str(tmp_path / "leds.pc"), "--uv-resolution", "32"]) == 0
    capture = Capture.load(out)
    report = json.loads((out / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
    assert [f.pose for f in capture.frames] == list(range(len(lit))) and load_sequence(out / "subject").num_frames == len(lit)
    assert {f.split for f in capture.frames} == {"train", "test"} and all(f.kind == "envmap" for f in capture.frames)
    k = len(lit) - 1  # linear EXR in, linear EXR out: the images are the native ones
    np.testing.assert_allclose(load_observation(capture, "Cam02", k), load_observation(native, "cam01", lit[k].frame), atol=1e-6)
    np.testing.assert_allclose(
        capture.lighting(load_calibration(out / "rig" / "calibration.json"), capture.frames[k]), native.lighting(stage, lit[k]), rtol=1e-5
    )


# --------------------------------------------------------------------------------------------------------------
# EasyMocap: a calibrated rig, a moving subject, per-frame masks, the lighting from the user
# --------------------------------------------------------------------------------------------------------------


def _opencv_matrix(name: str, m: np.ndarray) -> str:
    """One entry as cv2.FileStorage writes it."""
    data = ", ".join(f"{v:.17g}" for v in np.asarray(m, float).ravel())
    return f"{name}: !!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n   data: [ {data} ]\n"


def _with_matrix(text: str, name: str, m: np.ndarray) -> str:
    """``text`` (an OpenCV YAML file) with the entry ``name`` replaced by ``m``."""
    import re

    return re.sub(rf"{name}: !!opencv-matrix\n(?:\s+\w+: .*\n){{3}}\s+data: \[[^\]]*\]\n", _opencv_matrix(name, m), text)


def through_lens(image: np.ndarray, k_cv: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """A pinhole image as a camera with OpenCV's ``dist`` takes it: each pixel sampled (bilinear, cv2.remap) where
    OpenCV's undistortPoints puts its centre in the pinhole image (``k_cv``: OpenCV's K, pixel centres on integers)."""
    import cv2

    h, w = image.shape[:2]
    pixels = np.stack(np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float)), axis=-1).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    at = cv2.undistortPoints(pixels, k_cv, dist, P=k_cv, criteria=criteria).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image.astype(np.float32), at[..., 0], at[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def write_easymocap(native, folder: Path, frames: list, dist: np.ndarray | None = None) -> None:
    """intri.yml / extri.yml as EasyMocap writes them (world-to-camera Rot and T, R as a Rodrigues vector; Rot only for
    odd cameras, so the others go through R), 8-bit sRGB PNG images without alpha, and per-frame mask PNGs.
    ``dist``: OpenCV's distCoeffs (k1, k2, p1, p2, k3[, k4 … k6[, s1 … s4]]) of every camera, its images taken through
    that lens (:func:`through_lens`)."""
    from PIL import Image
    from scipy.spatial.transform import Rotation

    from gra_mi.capture.dataset import load_observation
    from gra_mi.core.color import srgb_encode
    from gra_mi.stage.lightstage import load_calibration

    stage = load_calibration(native.folder / "rig" / "calibration.json")
    names = [f"{i + 1:02d}" for i in range(len(stage.cameras))]
    intri = extri = "%YAML:1.0\n---\nnames:\n" + "".join(f'   - "{n}"\n' for n in names)
    for name, cam in zip(names, stage.cameras, strict=True):
        k = np.array([[cam.fx, 0, cam.cx - 0.5], [0, cam.fy, cam.cy - 0.5], [0, 0, 1]])  # OpenCV's: pixel centres on integers
        intri += _opencv_matrix(f"K_{name}", k)
        intri += _opencv_matrix(f"dist_{name}", np.zeros((1, 5)) if dist is None else np.reshape(dist, (1, -1)))
        rot = cam.rotation.T  # world-to-camera
        extri += _opencv_matrix(f"R_{name}", Rotation.from_matrix(rot).as_rotvec()[:, None])
        if int(name) % 2:
            extri += _opencv_matrix(f"Rot_{name}", rot)
        extri += _opencv_matrix(f"T_{name}", (-rot @ cam.position)[:, None])
        for entry in frames:
            image = load_observation(native, cam.name, entry.frame)
            image = image if dist is None else through_lens(image, k, dist)
            for kind, pixels in (("images", srgb_encode(np.clip(image[..., :3], 0, 1))), ("mask", image[..., 3] > 0.5)):
                (folder / kind / name).mkdir(parents=True, exist_ok=True)
                Image.fromarray(np.round(pixels * 255).astype(np.uint8)).save(folder / kind / name / f"{entry.frame:06d}.png")
    (folder / "intri.yml").write_text(intri)
    (folder / "extri.yml").write_text(extri)


def test_an_easymocap_rig_with_a_moving_subject_imports(path_traced_fit, tmp_path):
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.capture.source_files import write_obj, write_points
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    native = Capture.load(path_traced_fit / "cap")
    stage, seq = load_calibration(native.folder / "rig" / "calibration.json"), load_sequence(native.folder / "subject")
    frames = [native.frames[k] for k in (0, 1, 2, len(native.frames) - 1)]  # uniform, envmap, uniform; a test frame
    write_easymocap(native, tmp_path / "rig", frames)
    (tmp_path / "meshes").mkdir()
    for k in range(seq.num_frames):
        write_obj(tmp_path / "meshes", seq.vertices[k], seq.uvs, seq.faces, None)
        (tmp_path / "meshes" / "model.obj").rename(tmp_path / "meshes" / f"frame_{k:04d}.obj")
    write_points(tmp_path / "leds.pc", stage.led_positions)
    lighting = []
    for f in frames:
        light = {"uniform": 0.5} if f.kind == "uniform" else {"envmap": str(native.folder / f.envmap)}
        lighting.append({"frame": f.frame, "split": f.split} | light)
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": lighting}))
    out = tmp_path / "imported"
    args = ["import", "easymocap", str(tmp_path / "rig"), "--out", str(out), "--mesh", str(tmp_path / "meshes")]
    assert main([*args, "--leds", str(tmp_path / "leds.pc"), "--lighting", str(tmp_path / "lighting.json"), "--uv-resolution", "32"]) == 0
    capture = Capture.load(out)
    report = json.loads((out / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.97 for c in report["cameras"]), report["cameras"]
    assert [f.pose for f in capture.frames] == [f.frame for f in frames]
    imported_stage = load_calibration(out / "rig" / "calibration.json")
    for k, f in enumerate(frames):
        np.testing.assert_allclose(capture.lighting(imported_stage, capture.frames[k]), native.lighting(stage, f), rtol=1e-5)
    a, b = load_observation(capture, "cam02", 3), load_observation(native, "cam01", frames[3].frame)
    inside = (a[..., 3] > 0.5) & (b[..., :3].max(-1) < 0.95)
    assert np.abs(a[..., :3] - b[..., :3])[inside].mean() < 0.01 * b[..., :3][inside].mean() + 2e-4  # 8-bit sRGB
    # the rig is the native one up to the import's rigid transform
    for p, q in zip(imported_stage.cameras, stage.cameras, strict=True):
        assert np.linalg.norm(p.position - imported_stage.center) == pytest.approx(np.linalg.norm(q.position - stage.center), abs=1e-5)
    moved = np.array(json.loads((out / "capture.json").read_text())["source"]["transform"])  # (the import's, in metres)
    _projects_as_opencv(tmp_path / "rig", imported_stage, seq.vertices[0], seq.vertices[0] @ moved[:3, :3].T + moved[:3, 3])


def _projects_as_opencv(rig: Path, imported_stage, vertices: np.ndarray, imported_vertices: np.ndarray) -> None:
    """Each imported camera puts the mesh where OpenCV's own projectPoints, reading the rig's files with its own
    FileStorage, puts it in the source's frame: half a pixel apart, as OpenCV's pixel centres are on integers and
    gra-mi's at +½ (the importer once took K as gra-mi's)."""
    import cv2

    intri, extri = (cv2.FileStorage(str(rig / name), cv2.FILE_STORAGE_READ) for name in ("intri.yml", "extri.yml"))
    for k, camera in enumerate(imported_stage.cameras):
        name = f"{k + 1:02d}"
        k_cv, dist = intri.getNode(f"K_{name}").mat(), intri.getNode(f"dist_{name}").mat()
        rvec, tvec = extri.getNode(f"R_{name}").mat(), extri.getNode(f"T_{name}").mat()
        expected = cv2.projectPoints(vertices.astype(np.float64), rvec, tvec, k_cv, dist)[0].reshape(-1, 2) + 0.5
        np.testing.assert_allclose(camera.project(imported_vertices)[:, :2], expected, atol=1e-3)


def test_broken_easymocap_rigs_stop_with_one_line(path_traced_fit, tmp_path, capsys):
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.source_files import write_obj, write_points
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    native = Capture.load(path_traced_fit / "cap")
    stage, seq = load_calibration(native.folder / "rig" / "calibration.json"), load_sequence(native.folder / "subject")
    rig = tmp_path / "rig"
    write_easymocap(native, rig, native.frames[:1])
    (tmp_path / "meshes").mkdir()
    write_obj(tmp_path / "meshes", seq.vertices[0], seq.uvs, seq.faces, None)
    write_points(tmp_path / "leds.pc", stage.led_positions)
    good = {"frames": [{"frame": 0, "split": "train", "uniform": 0.5}]}
    args = ["import", "easymocap", str(rig), "--out", str(tmp_path / "out"), "--mesh", str(tmp_path / "meshes")]
    args += ["--leds", str(tmp_path / "leds.pc"), "--lighting", str(tmp_path / "lighting.json")]
    intri = (rig / "intri.yml").read_text()
    cases = [
        ({"frames": [{"split": "train", "uniform": 0.5}]}, intri, ["lighting.json", "frames[0].frame"]),
        ({"frames": [{"frame": 0, "sun": 1}]}, intri, ["lighting.json", "frames[0]", "uniform, led"]),
        ({"frames": [{"frame": 0, "led": 10_000}]}, intri, ["lighting.json", "frames[0].led", "out of range"]),
        (
            good,
            _with_matrix(intri, "dist_01", np.array([[0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.9, 0]])),
            ["intri.yml", "dist_01", "tilted"],
        ),
        (good, _with_matrix(intri, "dist_01", np.array([[0.1, 0, 0]])), ["intri.yml", "dist_01", "4, 5, 8"]),
        (good, _with_matrix(intri, "dist_01", np.array([[-3.0, 0, 0, 0, 0]])), ["intri.yml", "dist_01", "folds back"]),
        (good, _with_matrix(intri, "dist_01", np.array([[1e30, 0, 0, 0, 0]])), ["intri.yml", "dist_01", "outside the image"]),
        (good, _with_matrix(intri, "dist_01", np.array([[0, 0, 5.0, 0, 0]])), ["intri.yml", "dist_01", "outside the image"]),
        (good, intri.replace("K_02:", "Kx_02:"), ["intri.yml", "K_02"]),
        ({"frames": [{"frame": 0, "uniform": 0.5}, {"frame": 0, "led": 1}]}, intri, ["lighting.json", "frames[1].frame", "listed twice"]),
        ({"frames": [{"frame": 0, "uniform": float("nan")}]}, intri, ["lighting.json", "frames[0].uniform"]),
        ({"frames": [{"frame": 0, "uniform": -0.5}]}, intri, ["lighting.json", "frames[0].uniform"]),
        ({"frames": [{"frame": -1, "uniform": 0.5}]}, intri, ["lighting.json", "frames[0].frame"]),
        (good, _with_matrix(intri, "K_01", np.zeros((3, 3))), ["intri.yml", "K_01", "last row"]),
        (good, _with_matrix(intri, "K_01", np.eye(2)), ["intri.yml", "K_01", "3 × 3"]),
        (good, _with_matrix(intri, "K_01", np.diag([-500.0, 500.0, 1.0])), ["intri.yml", "K_01", "focal lengths"]),
    ]
    for lighting, text, needles in cases:
        (tmp_path / "lighting.json").write_text(json.dumps(lighting))
        (rig / "intri.yml").write_text(text)
        _one_line_error(capsys, args, *needles)
        assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    (tmp_path / "lighting.json").write_text(json.dumps(good))
    (rig / "intri.yml").write_text(intri)
    _one_line_error(capsys, [*args, "--estimate-led-gains"], "estimate", "one LED alone")
    extri = (rig / "extri.yml").read_text()
    (rig / "extri.yml").write_text(_with_matrix(extri, "R_02", np.zeros((1, 2))))  # a 1 × 2 Rodrigues vector
    _one_line_error(capsys, args, "extri.yml", "R_02", "3 numbers")
    (rig / "extri.yml").write_text(extri)
    _one_line_error(capsys, args[:-2], "--lighting")


def test_import_shards_write_what_one_process_writes(olat_capture, imported):
    # --shard: each shard converts its frames of every camera; the last one writes capture.json and the report.
    from gra_mi.core.provenance import different_outputs

    root, _, subject = olat_capture
    _imported(root, subject, "sharded", "--shard", "0/2")
    # staged until the last shard has checked the whole capture and published it
    assert not (root / "sharded").exists() and (root / ".sharded.partial" / "parts").is_dir()
    _imported(root, subject, "sharded", "--shard", "1/2")
    assert not (root / "sharded" / "parts").exists() and not (root / ".sharded.partial").exists()
    differ = different_outputs(imported, root / "sharded")
    assert not differ, differ


# --------------------------------------------------------------------------------------------------------------
# The doors (issue 51): the source's own checks, staging, provenance over what the import reads
# --------------------------------------------------------------------------------------------------------------


def _calib_edit(edit):
    def damage(s: Path) -> None:
        from gra_mi.capture.humanolat import read_calib, write_calib

        calib = read_calib(s / "shared" / "cameras.calib")
        edit(calib)
        write_calib(s / "shared" / "cameras.calib", calib)

    return damage


def _text_edit(relative: str, edit):
    def damage(s: Path) -> None:
        path = s / relative
        path.write_text(edit(path.read_text()))

    return damage


def _zero_focal(calib):
    calib[0].intrinsic[0, 0] = 0.0


def _one_negative_focal(calib):
    calib[0].intrinsic[1, 1] *= -1


def _negative_focal_pair(calib):
    calib[0].intrinsic[0, 0] *= -1
    calib[0].intrinsic[1, 1] *= -1


def _singular_rotation(calib):
    calib[0].extrinsic[:3, :3] = 0.0


def _mirrored_rotation(calib):
    calib[0].extrinsic[:3, 0] *= -1


def _camera_listed_twice(calib):
    calib[1] = calib[0]


def _first_line_starting(text: str, prefix: str, replace) -> str:
    lines = text.splitlines()
    k = next(i for i, line in enumerate(lines) if line.startswith(prefix))
    lines[k] = replace(lines[k])
    return "\n".join(lines) + "\n"


def _duplicate_led(text: str) -> str:
    lines = text.splitlines()
    lines[1] = lines[0]
    return "\n".join(lines) + "\n"


def _spiral_not_a_permutation(text: str) -> str:
    words = text.split()
    words[1] = words[0]
    return "\n".join(words) + "\n"


def _second_image_with_one_number(s: Path) -> None:
    first = next((s / "POSE_00" / "images_processed" / "Cam03").glob("*.000016.avif"))
    shutil.copyfile(first, first.with_suffix(".png"))


@pytest.mark.parametrize(
    ("damage", "needles"),
    [
        (_calib_edit(_zero_focal), ["cameras.calib", "camera 1", "line 1", "focal lengths must be > 0"]),
        (_calib_edit(_one_negative_focal), ["cameras.calib", "camera 1", "focal lengths must be > 0"]),
        (_calib_edit(_negative_focal_pair), ["cameras.calib", "camera 1", "focal lengths must be > 0"]),
        (_calib_edit(_singular_rotation), ["cameras.calib", "camera 1.extrinsic", "not orthonormal"]),
        (_calib_edit(_mirrored_rotation), ["cameras.calib", "camera 1.extrinsic", "mirrored"]),
        (_calib_edit(_camera_listed_twice), ["cameras.calib", "Cam01 and Cam02", "listed twice"]),
        (_text_edit("shared/LSX_light_positions_aligned.pc", _duplicate_led), ["LSX_light_positions_aligned.pc", "LEDs 0 and 1"]),
        (_text_edit("shared/LSX3_light_z_spiral.txt", _spiral_not_a_permutation), ["LSX3_light_z_spiral.txt", "fires twice"]),
        (
            _text_edit("POSE_00/model/model.obj", lambda t: _first_line_starting(t, "v ", lambda line: " ".join(line.split()[:3]))),
            ["model.obj", "line", "cannot read"],
        ),
        (
            _text_edit("POSE_00/model/model.obj", lambda t: _first_line_starting(t, "v ", lambda line: "v nan 0 0")),
            ["model.obj", "line", "cannot read"],
        ),
        (
            _text_edit("POSE_00/model/model.obj", lambda t: _first_line_starting(t, "vt ", lambda line: "vt 1.5 0.5")),
            ["model.obj", "several unit tiles"],
        ),
        (_second_image_with_one_number, ["Cam03", "image number 16"]),
    ],
    ids=[
        "zero-focal", "one-negative-focal", "negative-focal-pair", "singular-rotation", "mirrored-rotation", "camera-twice",
        "duplicate-led", "spiral-not-permutation", "obj-two-coordinates", "obj-nan-vertex", "uvs-over-tiles", "image-number-twice",
    ],
)  # fmt: skip
def test_hostile_sources_stop_naming_file_and_field_and_write_nothing(olat_capture, tmp_path, capsys, damage, needles):
    subject = _broken(olat_capture, tmp_path, damage)
    out = tmp_path / "out"
    _one_line_error(capsys, ["import", "humanolat", str(subject), "--out", str(out)], *needles)
    assert not out.exists() and not (tmp_path / ".out.partial").exists()


def test_every_camera_held_out_is_refused(olat_capture, tmp_path, capsys):
    _, _, subject = olat_capture
    every = ",".join(f"Cam{i:02d}" for i in range(1, 9))
    out = tmp_path / "out"
    _one_line_error(capsys, ["import", "humanolat", str(subject), "--out", str(out), "--eval-cameras", every], "--eval-cameras", "every")
    assert not out.exists()


def test_uvs_in_one_tile_are_moved_into_the_atlas_not_clamped(olat_capture, imported, tmp_path):
    from gra_mi.subject.sequence import load_sequence

    def shift(text: str) -> str:
        return "\n".join(
            f"vt {float(line.split()[1]) + 1:.9g} {float(line.split()[2]) + 2:.9g}" if line.startswith("vt ") else line
            for line in text.splitlines()
        )

    subject = _broken(olat_capture, tmp_path, _text_edit("POSE_00/model/model.obj", shift))
    moved = _imported(tmp_path, subject, "moved")
    np.testing.assert_allclose(load_sequence(moved / "subject").uvs, load_sequence(imported / "subject").uvs, atol=1e-6)


def test_a_failure_mid_import_leaves_nothing_and_the_fixed_rerun_resumes_without_overwrite(olat_capture, tmp_path, capsys):
    _, _, subject = olat_capture
    copy = _broken(olat_capture, tmp_path, lambda s: None)
    late = sorted((copy / "POSE_00" / "images_processed" / "Cam05").glob("*.avif"))[-1]
    good = late.read_bytes()
    late.write_bytes(good[: len(good) // 3])  # truncated: found only when its camera is imported
    out = tmp_path / "out"
    truth = json.loads((subject / "synthetic.json").read_text())
    args = ["import", "humanolat", str(copy), "--out", str(out), "--uv-resolution", "32", "--test-olat-every", "5"]
    args += ["--led-intensity", str(truth["import_led_intensity"])]
    _one_line_error(capsys, args, late.name)
    assert not out.exists()
    late.write_bytes(good)
    assert main(args) == 0
    assert (out / "capture.json").is_file() and not (tmp_path / ".out.partial").exists()


def _static_easymocap_rig(path_traced_fit, tmp_path: Path, frames: int):
    """The tiny capture's first ``frames`` as an EasyMocap rig (``tmp_path/rig``), its first mesh beside it
    (``meshes/``, one pose) and its LEDs (``leds.pc``): (the native capture, its mesh sequence)."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.source_files import write_obj, write_points
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    native = Capture.load(path_traced_fit / "cap")
    stage, seq = load_calibration(native.folder / "rig" / "calibration.json"), load_sequence(native.folder / "subject")
    write_easymocap(native, tmp_path / "rig", native.frames[:frames])
    (tmp_path / "meshes").mkdir()
    write_obj(tmp_path / "meshes", seq.vertices[0], seq.uvs, seq.faces, None)
    write_points(tmp_path / "leds.pc", stage.led_positions)
    return native, seq


def test_a_file_read_outside_the_source_is_part_of_the_run(path_traced_fit, tmp_path, capsys):
    # EasyMocap's mesh and lighting live beside the rig folder, not in it: editing the mesh (3 cm) after an import
    # makes a rerun into the same folder another run, refused; an edited envmap likewise.
    from gra_mi.capture.source_files import write_obj

    native, seq = _static_easymocap_rig(path_traced_fit, tmp_path, 2)
    frames = [
        {"frame": f.frame, "split": "train", "mesh_frame": 0}
        | ({"uniform": 0.5} if f.kind == "uniform" else {"envmap": str(native.folder / f.envmap)})
        for f in native.frames[:2]
    ]
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": frames}))
    out = tmp_path / "out"
    args = ["import", "easymocap", str(tmp_path / "rig"), "--out", str(out), "--mesh", str(tmp_path / "meshes"), "--uv-resolution", "32"]
    args += ["--leds", str(tmp_path / "leds.pc"), "--lighting", str(tmp_path / "lighting.json")]
    assert main(args) == 0
    assert main(args) == 0  # the same run: already complete
    write_obj(tmp_path / "meshes", seq.vertices[0] + np.array([0.03, 0, 0]), seq.uvs, seq.faces, None)
    _one_line_error(capsys, args, "another run", "files outside the source")


def test_envmaps_are_read_before_anything_is_written(path_traced_fit, tmp_path, capsys):
    from gra_mi.core.io import write_exr

    _static_easymocap_rig(path_traced_fit, tmp_path, 1)
    nan_map = np.ones((8, 16, 3), np.float32)
    nan_map[2, 3] = np.nan
    write_exr(tmp_path / "nan.exr", nan_map)
    (tmp_path / "text.exr").write_text("not an image")
    out = tmp_path / "out"
    args = ["import", "easymocap", str(tmp_path / "rig"), "--out", str(out), "--mesh", str(tmp_path / "meshes")]
    args += ["--leds", str(tmp_path / "leds.pc"), "--lighting", str(tmp_path / "lighting.json")]
    for envmap, needle in (("nan.exr", "nan.exr"), ("text.exr", "text.exr"), ("../../../../../../etc/passwd", "passwd")):
        (tmp_path / "lighting.json").write_text(json.dumps({"frames": [{"frame": 0, "envmap": envmap}]}))
        _one_line_error(capsys, args, needle)
        assert not out.exists()


def _swap_cameras(calib):
    calib[2], calib[5] = calib[5], calib[2]


def _stray_vertex(text: str) -> str:
    return f"{text}\nv 0 0 -100000\n"  # 100 m below the subject (millimetres), referenced by no face


def _empty_mask(s: Path) -> None:
    from PIL import Image

    path = s / "POSE_00" / "segmentations" / "masks" / "000" / "Cam04.png"
    size = Image.open(path).size
    Image.new("L", size, 0).save(path)


def _full_mask(s: Path) -> None:
    from PIL import Image

    path = s / "POSE_00" / "segmentations" / "masks" / "000" / "Cam04.png"
    size = Image.open(path).size
    Image.new("L", size, 255).save(path)


@pytest.mark.parametrize(
    ("damage", "extra", "needles"),
    [
        (_calib_edit(_swap_cameras), [], ["Cam03", "Cam06", "swapped"]),
        (_empty_mask, [], ["Cam04.png", "mask is empty"]),
        (_full_mask, [], ["Cam04.png", "whole image"]),
        (lambda s: None, ["--up", "+y"], ["lying on its side", "--up"]),
        (lambda s: None, ["--scale", "0.01"], ["--scale", "too small"]),
        (lambda s: None, ["--scale", "2000"], ["--scale", "GiB"]),
        (lambda s: None, ["--uv-resolution", "100000"], ["--uv-resolution", "GiB"]),
    ],
    ids=["swapped-cameras", "empty-mask", "full-mask", "wrong-up", "tiny-scale", "huge-scale", "huge-uv-resolution"],
)
def test_the_reprojection_check_names_the_real_culprit(olat_capture, tmp_path, capsys, damage, extra, needles):
    subject = _broken(olat_capture, tmp_path, damage)
    out = tmp_path / "out"
    _one_line_error(capsys, ["import", "humanolat", str(subject), "--out", str(out), *extra], *needles)
    assert not out.exists()


def test_a_mesh_in_the_wrong_units_is_named(olat_capture, tmp_path, capsys):
    _, _, subject = olat_capture
    folder = tmp_path / "json"
    write_transforms_as_humanolat_tools_do(subject, folder)
    mesh = str(subject / "POSE_00" / "model" / "model.obj")
    args = ["import", "transforms", str(folder), "--out", str(tmp_path / "out"), "--mesh", mesh, "--mesh-units", "m"]
    _one_line_error(capsys, args, "IoU", "--mesh-units mm")


def test_a_stray_vertex_does_not_move_the_floor(olat_capture, imported, tmp_path):
    from gra_mi.subject.sequence import load_sequence

    subject = _broken(olat_capture, tmp_path, _text_edit("POSE_00/model/model.obj", _stray_vertex))
    out = _imported(tmp_path, subject, "stray")
    floor = load_sequence(imported / "subject").vertices[0][:, 1].min()
    stray = load_sequence(out / "subject").vertices[0]
    assert abs(np.percentile(stray[:, 1], 1) - np.percentile(load_sequence(imported / "subject").vertices[0][:, 1], 1)) < 1e-4
    assert floor == pytest.approx(0, abs=1e-6)


def test_door_leds_leave_the_rig_with_their_olats_and_the_white_frame(olat_capture, tmp_path, monkeypatch):
    # The test layout has 24 LEDs, fewer than HumanOLAT's door indices: three of its LEDs play the door here.
    from gra_mi.capture import humanolat
    from gra_mi.capture.dataset import Capture
    from gra_mi.stage.lightstage import load_calibration

    monkeypatch.setattr(humanolat, "DOOR_LEDS", (3, 7, 11))
    root, _, subject = olat_capture
    out = _imported(tmp_path, subject, "no_door")
    capture, stage = Capture.load(out), load_calibration(out / "rig" / "calibration.json")
    report = json.loads((out / "import_report.json").read_text())
    assert stage.num_leds == 21 and {3, 7, 11} <= set(report["leds"]["left_out"])
    assert all(f.pattern != "patterns/white.json" for f in capture.frames)
    assert report["linearity"]["olats_over_white"] > 0  # the white frame still checks the sensor's linearity
    for entry in capture.frames:  # each OLAT lights one LED of the rig
        assert np.count_nonzero(capture.lighting(stage, entry).max(axis=1)) == 1
    kept = _imported(tmp_path, subject, "with_door", "--keep-door-leds")
    assert load_calibration(kept / "rig" / "calibration.json").num_leds == 24
    assert any(f.pattern == "patterns/white.json" for f in Capture.load(kept).frames)


def test_images_through_a_lens_are_undistorted_at_import(path_traced_fit, tmp_path):
    """An EasyMocap rig whose cameras have a wide-angle lens (OpenCV's full model: k1, k2, p1, p2, the rational k4, k5,
    thin-prism terms and a tilted sensor; the images taken through it by OpenCV's own model): imported, its images match the pinhole truth as closely as a rig without distortion does,
    the mesh lies on the masks; and with the same images but the lens left out of intri.yml they do not."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.capture.source_files import write_obj, write_points
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.subject.sequence import load_sequence

    native = Capture.load(path_traced_fit / "cap")
    stage, seq = load_calibration(native.folder / "rig" / "calibration.json"), load_sequence(native.folder / "subject")
    (tmp_path / "mesh").mkdir()
    write_obj(tmp_path / "mesh", seq.vertices[0], seq.uvs, seq.faces, None)
    write_points(tmp_path / "leds.pc", stage.led_positions)
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": [{"frame": 0, "split": "train", "uniform": 0.5}]}))
    dist = np.array([-0.12, 0.05, 0.002, -0.003, 0.0, 0.08, 0.01, 0.0, 0.001, 0.0, -0.001, 0.0, 0.02, -0.03])

    def imported(name: str, lens: np.ndarray | None, said: np.ndarray | None) -> tuple[dict, list[float]]:
        write_easymocap(native, tmp_path / name, native.frames[:1], lens)
        if said is not lens:
            (tmp_path / name / "intri.yml").write_text(_with_matrix((tmp_path / name / "intri.yml").read_text(), "dist_01", said[None]))
        out = tmp_path / f"{name}_out"
        args = ["import", "easymocap", str(tmp_path / name), "--out", str(out), "--mesh", str(tmp_path / "mesh" / "model.obj")]
        args += ["--leds", str(tmp_path / "leds.pc"), "--lighting", str(tmp_path / "lighting.json"), "--uv-resolution", "32"]
        if main(args + ["--min-iou", "0.5"]) != 0:
            return {}, []
        capture, errors = Capture.load(out), []
        for k in range(len(stage.cameras)):
            a, b = load_observation(capture, f"cam{k + 1:02d}", 0), load_observation(native, f"cam{k:02d}", native.frames[0].frame)
            inside, seen, truth = b[..., 3] > 0.99, np.clip(a[..., :3], 0, 1), np.clip(b[..., :3], 0, 1)  # 8-bit PNGs clip
            errors.append(float(np.abs(seen - truth)[inside].mean() / truth[inside].mean()))
        return json.loads((out / "import_report.json").read_text()), errors

    plain, plain_errors = imported("pinhole", None, None)
    lens, lens_errors = imported("lens", dist, dist)
    ignored, ignored_errors = imported("ignored", dist, np.zeros(5))  # camera 01 only: its lens left out
    assert all(c["lens"] is None for c in plain["cameras"]) and "radial-tangential" in lens["cameras"][0]["lens"]["model"]
    assert all(c["mask_iou"] >= 0.97 for c in lens["cameras"]), lens["cameras"]
    # what two bilinear resamplings (the lens's and its undoing) cost over the pinhole rig's 8-bit error
    assert max(lens_errors) < max(plain_errors) + 0.015, (lens_errors, plain_errors)
    assert ignored_errors[0] > 3 * lens_errors[0] and ignored["cameras"][0]["mask_iou"] < lens["cameras"][0]["mask_iou"] - 0.02


def test_gaps_are_named_and_a_camera_with_no_image_at_all_is_refused(tmp_path):
    """check_images_present: a gap refused (naming the option that takes it), or recorded with skip; a camera that
    has no image of any frame is refused even then (leave it out with --cameras)."""
    from types import SimpleNamespace

    from PIL import Image

    from gra_mi.capture.importer import check_images_present
    from gra_mi.core.errors import GraMiInputError

    Image.new("RGB", (8, 6)).save(tmp_path / "a.png")
    plans = [SimpleNamespace(index=i, camera=SimpleNamespace(name=f"cam{i}"), source_size=(8, 6)) for i in range(2)]
    frames = [(k, None, "white") for k in range(3)]
    source = SimpleNamespace(
        folder=tmp_path, frames=frames, images=[{0: tmp_path / "a.png", 1: tmp_path / "a.png"}, {0: tmp_path / "a.png"}]
    )
    with pytest.raises(GraMiInputError, match="cam0 has no image of frame 000002.*--missing-images skip"):
        check_images_present(source, plans, skip=False)
    assert check_images_present(source, plans, skip=True) == {1: ["cam1"], 2: ["cam0", "cam1"]}
    source.images[1] = {}
    with pytest.raises(GraMiInputError, match="cam1 has no image of any frame"):
        check_images_present(source, plans, skip=True)
