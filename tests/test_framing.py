"""Cameras framed on the subject (stage/framing.py): the crop-window geometry, Mitsuba's own render of a framed
camera, and a framed, lighting-rich capture."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from gra_mi.core.errors import GraMiParameterError
from gra_mi.stage.framing import frame_subject, subject_box
from gra_mi.stage.lightstage import default_lightstage


def _body_points(seed: int = 0) -> np.ndarray:
    """A standing, person-sized cloud of points: 0.5 m wide, 0.3 m deep, 1.7 m tall, off the stage centre."""
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.25, 0.0, -0.15], [0.25, 1.7, 0.15], (4000, 3)) + np.array([0.1, 0.0, -0.05])


def test_framed_cameras_hold_the_subject_centred_with_the_margin():
    stage = default_lightstage(num_leds=16, num_cameras=8, width=256, height=135)
    points, width, height, margin = _body_points(), 90, 160, 0.05
    for camera in frame_subject(stage.cameras, points, width, height, margin):
        u0, v0, u1, v1 = subject_box(camera, points)
        assert (camera.width, camera.height) == (width, height)
        slack_u, slack_v = min(u0, width - u1), min(v0, height - v1)
        assert min(slack_u / width, slack_v / height) == pytest.approx(margin, abs=1e-6)  # the binding axis touches it
        assert slack_u / width >= margin - 1e-6 and slack_v / height >= margin - 1e-6
        assert 0.5 * (u0 + u1) == pytest.approx(width / 2, abs=1e-6) and 0.5 * (v0 + v1) == pytest.approx(height / 2, abs=1e-6)


def test_a_framed_camera_is_a_crop_window_of_the_original():
    """Position and orientation kept; every pixel's ray is the original camera's ray through the matching point."""
    camera = default_lightstage(num_leds=16, num_cameras=8, width=256, height=135).cameras[3]
    framed = frame_subject([camera], _body_points(), 90, 160)[0]
    np.testing.assert_array_equal(framed.camera_to_world, camera.camera_to_world)
    assert framed.fx == pytest.approx(framed.fy)
    origin, rays = framed.pixel_rays()
    scale = framed.fx / camera.fx
    u = (np.arange(framed.width) + 0.5 - framed.cx) / scale + camera.cx
    v = (np.arange(framed.height) + 0.5 - framed.cy) / scale + camera.cy
    d = np.stack(np.broadcast_arrays(((u - camera.cx) / camera.fx)[None, :], ((v - camera.cy) / camera.fy)[:, None], 1.0), -1)
    d = d @ camera.rotation.T
    np.testing.assert_allclose(rays, d / np.linalg.norm(d, axis=-1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(origin, camera.position)


def test_mitsuba_renders_the_subject_where_the_framing_put_it(llvm_variant):
    """The framed camera's sensor (its principal point offset included) through Mitsuba: the rendered silhouette's
    box is the predicted one to within a pixel."""
    import mitsuba as mi

    from gra_mi.stage.scene import camera_sensor_dict

    center, radius = np.array([0.2, 1.1, -0.1]), 0.45
    rng = np.random.default_rng(1)
    directions = rng.normal(size=(200_000, 3))
    points = center + radius * directions / np.linalg.norm(directions, axis=1, keepdims=True)
    cameras = frame_subject(default_lightstage(num_leds=16, num_cameras=4, width=256, height=135).cameras, points, 64, 96, 0.1)
    for camera in cameras[:2]:
        scene = mi.load_dict(
            {
                "type": "scene",
                "integrator": {"type": "direct"},
                "sensor": camera_sensor_dict(camera, spp=16),
                "ball": {"type": "sphere", "center": center.tolist(), "radius": radius},
            }
        )
        alpha = np.array(mi.render(scene))[..., 3] > 0.5
        rows, cols = np.where(alpha.any(1))[0], np.where(alpha.any(0))[0]
        u0, v0, u1, v1 = subject_box(camera, points)
        assert abs(cols.min() - u0) <= 1.0 and abs(cols.max() + 1 - u1) <= 1.0, camera.name
        assert abs(rows.min() - v0) <= 1.0 and abs(rows.max() + 1 - v1) <= 1.0, camera.name


def test_framing_refuses_what_no_crop_window_holds():
    camera = default_lightstage(num_leds=16, num_cameras=8, width=256, height=135).cameras[0]
    behind = np.array([camera.position - 0.5 * camera.rotation[:, 2], camera.position + camera.rotation[:, 2]])
    with pytest.raises(GraMiParameterError, match=f"camera {camera.name}: the subject reaches behind the camera"):
        frame_subject([camera], behind, 90, 160)
    with pytest.raises(GraMiParameterError, match="margin"):
        frame_subject([camera], _body_points(), 90, 160, margin=0.5)
    with pytest.raises(GraMiParameterError, match="image size"):
        frame_subject([camera], _body_points(), 0, 160)


def test_a_framed_lighting_rich_capture(tmp_path, monkeypatch):
    """A framed preset's cameras fill their images with the subject; relit frames follow the preset's ratio, each
    under its own map, rendered with their own sample counts (recorded, and in the noise record)."""
    from gra_mi.capture import synthetic
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture
    from gra_mi.core.io import read_exr
    from gra_mi.subject.sequence import load_sequence

    preset = replace(synthetic.PRESETS["tiny"], width=48, height=64, frames_per_clip=7, relit_per_uniform=2, test_frames_per_clip=2)
    preset = replace(preset, relit_spp=4, relit_indirect_spp=4, framed=True, framing_margin=0.05)
    monkeypatch.setitem(synthetic.PRESETS, "tiny", preset)
    capture = generate_capture(tmp_path / "cap", CaptureConfig(preset="tiny"))
    train = [f for f in capture.frames if f.split == "train"]
    assert [f.kind for f in train] == ["uniform", "envmap", "envmap"] * 2 + ["uniform"]
    assert len({f.envmap for f in train if f.envmap}) == 4
    record = json.loads((tmp_path / "cap" / "capture.json").read_text())["ground_truth"]
    assert (record["relit_spp"], record["relit_indirect_spp"], record["spp"]) == (4, 4, preset.spp)
    assert {probe["spp"][0] for label, probe in record["noise"].items() if label != "uniform"} <= {4}
    cameras = synthetic.LightstageScene.load(tmp_path / "cap" / "scene.xml").stage.cameras
    vertices = load_sequence(tmp_path / "cap" / "subject").vertices.reshape(-1, 3)
    for camera in cameras:
        alpha = np.any([read_exr(capture.image_path(camera.name, f.frame))[..., 3] > 0.5 for f in capture.frames], axis=0)
        rows, cols = np.where(alpha.any(1))[0], np.where(alpha.any(0))[0]
        assert rows.min() >= 1 and cols.min() >= 1 and rows.max() <= 62 and cols.max() <= 46, camera.name  # inside the margin
        filled = max((rows.max() + 1 - rows.min()) / 64, (cols.max() + 1 - cols.min()) / 48)
        assert filled >= 0.85, camera.name  # the union of its frames fills 90 % of the binding axis
        u0, v0, u1, v1 = subject_box(camera, vertices)  # the rig written to disk is the framed one
        assert min(u0, v0) >= 0.05 * 48 - 1e-6 and u1 <= 0.95 * 48 + 1e-6 and v1 <= 0.95 * 64 + 1e-6, camera.name


def test_the_demos_held_out_subject_stands_at_least_256_pixels_tall_in_every_frame(tmp_path):
    """The `small` preset's framing, projected (not rendered): in each held-out camera, every held-out frame of the
    march spans ≥ 256 pixel rows, the frames with the nearer foot raised included."""
    from gra_mi.capture import synthetic
    from gra_mi.subject.sequence import load_sequence

    preset = synthetic.PRESETS["small"]
    synthetic._write_subject(preset, tmp_path)
    stage = synthetic._capture_rig(preset, tmp_path)
    test_frames = load_sequence(tmp_path / "subject").vertices[len(preset.train_clips) * preset.frames_per_clip :]
    assert len(test_frames) == preset.test_frames() * len(preset.test_clips)
    for camera in stage.cameras[-preset.eval_cameras :]:
        rows = [subject_box(camera, frame)[3] - subject_box(camera, frame)[1] for frame in test_frames]
        assert min(rows) >= 256, (camera.name, np.round(rows))
        assert max(rows) <= preset.height, camera.name
