"""`gra-mi import humanolat --envmap-frames --gradient-frames`: the environment-map frames (image numbers 3–12) and the
gradient frames (1–2), whose drive the dataset does not state, imported as held-out lighting with the drive solved
from the pose's OLATs. Checked where it counts:
the solved drive's OLAT sum against each frame on the held-out cameras (which the solve never read), next to the true
drive the synthetic capture was rendered with and a flat drive of the same total; the door LEDs' light taken off
exactly; a frame that is no mix of the OLATs left out, said; a frame's images edited before a resume solved again."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli import main
from gra_mi.core.io import read_exr
from tests.test_import import _imported, olat_capture  # noqa: F401 (the module's fixture, shared)

ENV_NUMBERS = list(range(3, 13))
GRADIENT_NUMBERS = [1, 2]


@pytest.fixture(scope="module")
def env_imported(olat_capture):  # noqa: F811
    root, _, subject = olat_capture
    return _imported(root, subject, "env_imported", "--envmap-frames", "--gradient-frames")


def _olat_frames(capture) -> dict[int, int]:
    """LED → the imported capture's frame of its OLAT."""
    from gra_mi.stage.lightstage import load_calibration, load_pattern

    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    olats = [f for f in capture.frames if f.pattern and "olat_" in f.pattern]
    return {int(np.argmax(load_pattern(stage, capture.folder / f.pattern).max(axis=1))): f.frame for f in olats}


def _env_frames(capture, kind: str = "envmap") -> dict[int, object]:
    """Source image number → the imported frame entry of an environment-map frame (``kind`` gradient: a gradient's)."""
    return {int(Path(f.pattern).stem.split("_")[1]): f for f in capture.frames if f.pattern and f"{kind}_" in f.pattern}


def _relative_error(capture, camera: str, frame: int, drive: np.ndarray, olats: dict[int, int]) -> float:
    """RMS of (the drive-weighted sum of the camera's OLAT images − the frame's image) over the frame's RMS."""
    truth = read_exr(capture.image_path(camera, frame))[..., :3]
    relit = sum(drive[led] * read_exr(capture.image_path(camera, olat))[..., :3] for led, olat in olats.items())
    return float(np.sqrt(np.mean((relit - truth) ** 2)) / np.sqrt(np.mean(truth**2)))


def test_envmap_and_gradient_frames_are_lit_by_the_drive_their_olats_give(olat_capture, env_imported):  # noqa: F811
    from gra_mi.capture.dataset import Capture
    from gra_mi.stage.lightstage import load_calibration, load_pattern

    _, native, _ = olat_capture
    capture = Capture.load(env_imported)
    stage = load_calibration(capture.folder / "rig" / "calibration.json")
    native_stage = load_calibration(native.folder / "rig" / "calibration.json")
    env, gradients = _env_frames(capture), _env_frames(capture, "gradient")
    assert sorted(env) == ENV_NUMBERS and {(f.split, f.sequence) for f in env.values()} == {("test", 2)}
    assert sorted(gradients) == GRADIENT_NUMBERS and {(f.split, f.sequence) for f in gradients.values()} == {("test", 3)}
    assert len({f.frame for f in capture.frames}) == len(capture.frames)
    # the layout's 1–2 are the native capture's gradients, 3–4 its environment-lit frames, 5–12 its white frame
    native_env = [f for f in native.frames if f.kind == "envmap"]
    named = {Path(f.pattern).stem: f for f in native.frames if f.pattern}
    truth = {3: native_env[0], 4: native_env[1], 5: named["white"], 1: named["gradient_up"], 2: named["gradient_down"]}
    olats = _olat_frames(capture)
    for number, entry in truth.items():
        frame = (env | gradients)[number]
        solved = load_pattern(stage, capture.folder / frame.pattern) / stage.max_led_intensity  # in OLATs
        true = native.lighting(native_stage, entry) / native_stage.max_led_intensity
        np.testing.assert_allclose(solved.sum(axis=0), true.sum(axis=0), rtol=0.03)  # the light's total and colour
        flat = np.broadcast_to(solved.mean(axis=0), solved.shape)  # the baseline: as much light, from everywhere
        for camera in capture.eval_cameras:  # cameras the solve never read
            errors = [_relative_error(capture, camera, frame.frame, d, olats) for d in (solved, true, flat)]
            assert errors[0] < errors[1] + 0.01, (number, camera, errors)  # as good as the drive that lit it
            if number != 5:
                assert errors[0] < 0.4 * errors[2], (number, camera, errors)  # an environment is no flat light
    report = json.loads((env_imported / "import_report.json").read_text())["solved_frames"]
    assert [r["image"] for r in report] == ENV_NUMBERS + GRADIENT_NUMBERS
    assert all(r["residual"] < 0.15 and "left_out" not in r for r in report)
    assert {r["what"] for r in report} == {"an environment-map frame", "a gradient frame"}
    assert set(report[0]["cameras"]) == set(capture.train_cameras)
    assert "| 000001 | " in (env_imported / "import_report.md").read_text()
    said = {f.sequence: f.lighting_name for f in capture.frames if f.split == "test"}
    assert said[1] == "OLATs" and said[2].startswith("environment-map frames") and said[3].startswith("gradient frames")


def test_the_door_leds_light_is_taken_off_the_frames(olat_capture, env_imported, tmp_path, monkeypatch):  # noqa: F811
    """The door LEDs leave the rig, but an environment-map frame was lit by them too: their light (each one's OLAT
    image times its solved drive) is subtracted, so the frame shows what the rig's LEDs gave."""
    from gra_mi.capture import humanolat
    from gra_mi.capture.dataset import Capture

    root, _, subject = olat_capture
    monkeypatch.setattr(humanolat, "DOOR_LEDS", (5, 11))
    doorless = Capture.load(_imported(tmp_path, subject, "doorless", "--envmap-frames"))
    whole = Capture.load(env_imported)
    drives = {r["key"]: np.array(r["drive"]) for r in json.loads((whole.folder / "import" / "solved_drives.json").read_text())}
    olats = _olat_frames(whole)
    report = json.loads((doorless.folder / "import_report.json").read_text())["solved_frames"]
    assert all(r["outside_share"] > 0.01 for r in report)
    for number in (3, 4, 5):
        for camera in doorless.eval_cameras:
            image = read_exr(whole.image_path(camera, _env_frames(whole)[number].frame))[..., :3]
            door = sum(drives[number][led] * read_exr(whole.image_path(camera, olats[led]))[..., :3] for led in (5, 11))
            left = read_exr(doorless.image_path(camera, _env_frames(doorless)[number].frame))[..., :3]
            np.testing.assert_allclose(left, np.maximum(image - door, 0), atol=1e-6 * image.max())
            assert door.sum() > 0.01 * image.sum()


def test_a_frame_its_olats_do_not_explain_is_left_out_and_said(olat_capture, tmp_path, caplog):  # noqa: F811
    """An image number 3–12 that is no mix of the pose's OLATs (here: every camera's image of frame 7 is another
    camera's, as mixed-up files or a subject that moved would give) is not held-out truth: it is left out, with a
    warning and a line in the report."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.humanolat import camera_name, images_of, write_avif
    from gra_mi.capture.source_files import read_image

    root, _, subject = olat_capture
    moved = tmp_path / "layout" / subject.name
    shutil.copytree(subject, moved, ignore=shutil.ignore_patterns("json_*"))
    paths = [images_of(moved / "POSE_00" / "images_processed" / camera_name(cam))[7] for cam in range(8)]
    shown = [read_image(path)[0] for path in paths]
    for cam, path in enumerate(paths):  # each camera's image of frame 7 is its neighbour's: the files mixed up
        write_avif(path, shown[(cam + 1) % 8])
    with caplog.at_level(logging.WARNING):
        out = _imported(tmp_path, moved, "moved", "--envmap-frames")
    assert sorted(_env_frames(Capture.load(out))) == [n for n in ENV_NUMBERS if n != 7]
    rows = {r["image"]: r for r in json.loads((out / "import_report.json").read_text())["solved_frames"]}
    assert "unexplained" in rows[7]["left_out"] and rows[7]["residual"] > 0.25 and "left_out" not in rows[8]
    assert "**left out**" in (out / "import_report.md").read_text()
    assert any("frame 000007 left out" in r.message for r in caplog.records)


def test_a_frame_edited_before_the_resume_is_solved_again(olat_capture, env_imported, tmp_path, monkeypatch):  # noqa: F811
    """The solve is kept in the staging folder for a resumed import. An import interrupted right after it, then
    resumed after frame 4's images were edited, is another import (its provenance covers every source file): the
    drive is solved again, not read back stale."""
    from gra_mi.capture import importer
    from gra_mi.capture.humanolat import camera_name, images_of, write_avif
    from gra_mi.capture.source_files import read_image

    root, _, subject = olat_capture
    layout = tmp_path / "layout" / subject.name
    shutil.copytree(subject, layout, ignore=shutil.ignore_patterns("json_*"))
    with monkeypatch.context() as patch:
        patch.setattr(importer, "build_stage", lambda *a: (_ for _ in ()).throw(KeyboardInterrupt()))
        with pytest.raises(AssertionError, match="130 == 0"):  # gra-mi import: interrupted (rerun to resume)
            _imported(tmp_path, layout, "resumed", "--envmap-frames", "--gradient-frames")
    assert (tmp_path / ".resumed.partial" / "import" / "solved_drives.json").is_file()
    for cam in range(8):  # frame 4 at half its brightness: its drive halves
        path = images_of(layout / "POSE_00" / "images_processed" / camera_name(cam))[4]
        write_avif(path, read_image(path)[0] * 0.5)
    out = _imported(tmp_path, layout, "resumed", "--envmap-frames", "--gradient-frames")
    before = {r["key"]: np.array(r["drive"]) for r in json.loads((env_imported / "import" / "solved_drives.json").read_text())}
    after = {r["key"]: np.array(r["drive"]) for r in json.loads((out / "import" / "solved_drives.json").read_text())}
    np.testing.assert_allclose(after[4].sum(axis=0), 0.5 * before[4].sum(axis=0), rtol=0.08)  # re-encoded: 8-bit, AVIF
    np.testing.assert_allclose(after[3], before[3])


def test_missing_frames_and_other_routes_options_are_refused(olat_capture, tmp_path, capsys):  # noqa: F811
    """A pose without images 3–12 (1–2) stops --envmap-frames (--gradient-frames) naming the frame and the way out; an option of another
    route (--envmap-frames to transforms, --olat-step to easymocap) is refused rather than ignored unsaid."""
    from gra_mi.capture.humanolat import camera_name, images_of

    root, _, subject = olat_capture
    bare = tmp_path / "layout" / subject.name
    shutil.copytree(subject, bare, ignore=shutil.ignore_patterns("json_*"))
    for cam in range(8):
        for number in (1, 3):
            images_of(bare / "POSE_00" / "images_processed" / camera_name(cam))[number].unlink()
    for args, needles in [
        (["humanolat", str(bare), "--envmap-frames"], ("000003", "environment-map frame", "without --envmap-frames")),
        (["humanolat", str(bare), "--gradient-frames"], ("000001", "a gradient frame", "without --gradient-frames")),
        (["transforms", str(bare), "--envmap-frames"], ("--envmap-frames", "humanolat option", "gra-mi import transforms")),
        (["easymocap", str(bare), "--olat-step", "2"], ("--olat-step", "humanolat option", "gra-mi import easymocap")),
    ]:
        capsys.readouterr()
        assert main(["import", *args, "--out", str(tmp_path / "out")]) == 2
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert len(err) == 1 and all(n in err[0] for n in needles), err
        assert not (tmp_path / "out").exists()


def test_an_olat_that_grazes_the_subject_fits_its_mask(olat_capture, tmp_path, monkeypatch, capsys):  # noqa: F811
    """With the door LEDs left out, the frame the masks are checked on is the first OLAT. One that only grazes the
    subject lights little more than its anti-aliased edge, half of it outside the mask file: that is no image of another
    camera or frame (it stopped an `olat_quick` import before the check weighed light and grew the mask by its edge);
    a frame whose subject stands aside still stops the import."""
    from scipy.ndimage import binary_dilation, binary_erosion

    from gra_mi.capture import humanolat
    from gra_mi.capture.humanolat import camera_name, images_of, olat_numbers, write_avif
    from gra_mi.capture.source_files import read_image, read_mask

    root, _, subject = olat_capture
    monkeypatch.setattr(humanolat, "DOOR_LEDS", (3, 7, 11))
    rim = tmp_path / "layout" / subject.name
    shutil.copytree(subject, rim, ignore=shutil.ignore_patterns("json_*"))
    first = olat_numbers(24)[0][0]
    for cam in range(8):
        images = images_of(rim / "POSE_00" / "images_processed" / camera_name(cam))
        mask = read_mask(rim / "POSE_00" / "segmentations" / "masks" / "000" / f"{camera_name(cam)}.png")
        edge = binary_dilation(mask, iterations=1) & ~binary_erosion(mask, iterations=1)  # half of it outside the mask
        write_avif(images[first], read_image(images[0])[0] * edge[..., None] * 0.3)
    _imported(tmp_path, rim, "rim")
    moved = images_of(rim / "POSE_00" / "images_processed" / camera_name(1))[first]
    white = read_image(images_of(subject / "POSE_00" / "images_processed" / camera_name(1))[0])[0]
    write_avif(moved, np.roll(white, white.shape[1] // 2, axis=1))  # the subject half a frame aside
    capsys.readouterr()
    with pytest.raises(AssertionError):
        _imported(tmp_path, rim, "moved")
    assert "outside its mask" in capsys.readouterr().err and not (tmp_path / "moved").exists()


def test_an_olat_pose_is_fitted_without_the_brightness_calibration(env_imported, path_traced_fit, tmp_path):
    """The brightness calibration puts the indirect light of an OLAT's dim views into the albedo (on an imported
    331-LED pose it cost 0.5–1.2 dB on held-out cameras: docs/results/envmap-frames.md): `gra-mi fit` leaves it out
    when most training frames are OLATs, says so, and still runs it when asked; an environment-lit capture keeps it."""
    args = ["fit", str(env_imported), "--solver", "closed-form", "--roughness-candidates", "3"]
    assert main([*args, "--out", str(tmp_path / "auto")]) == 0
    report = json.loads((tmp_path / "auto" / "fit.json").read_text())
    assert report["albedo_gain"] is None and report["calibration"] == "automatic"
    assert "no brightness calibration: most training frames are OLATs" in (tmp_path / "auto" / "fit_report.md").read_text()
    assert main([*args, "--out", str(tmp_path / "forced"), "--calibrate-brightness"]) == 0
    assert json.loads((tmp_path / "forced" / "fit.json").read_text())["albedo_gain"] is not None
    assert json.loads((path_traced_fit / "fit" / "fit.json").read_text())["albedo_gain"] is not None  # envmap-lit


def test_two_shards_write_what_one_process_writes(olat_capture, env_imported):  # noqa: F811
    """Each shard solves the drives (or reads the solve another shard kept) and imports its frames, the door light
    subtracted where a shard takes a frame: the published capture is the one-process import's."""
    from gra_mi.core.provenance import different_outputs

    root, _, subject = olat_capture
    for shard in ("0/2", "1/2"):
        _imported(root, subject, "env_sharded", "--envmap-frames", "--gradient-frames", "--shard", shard)
    differ = different_outputs(env_imported, root / "env_sharded")
    assert not differ, differ
