"""Lightstage rig, calibration file validation, and LED patterns."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError
from gra_mi.stage.lightstage import (
    default_lightstage,
    lightstage_to_dict,
    load_calibration,
    load_pattern,
    olat_pattern,
    save_calibration,
    uniform_pattern,
)


def test_default_rig_shape(default_stage):
    stage = default_stage
    assert stage.num_leds == 331 and len(stage.cameras) == 40
    np.testing.assert_allclose(stage.led_distances(), 2.0, rtol=1e-6)
    # Evenly spread: every LED's nearest neighbour is at a similar angle.
    d = stage.led_directions()
    cos = d @ d.T
    np.fill_diagonal(cos, -1)
    nearest = np.degrees(np.arccos(cos.max(axis=1)))
    assert nearest.max() / nearest.min() < 1.6
    heights = {round(c.position[1], 3) for c in stage.cameras}
    assert len(heights) >= 4, "cameras at several heights"
    for cam in stage.cameras:
        to_centre = stage.center - cam.position
        assert cam.rotation[:, 2] @ to_centre / np.linalg.norm(to_centre) > 0.99  # looks at the stage
        assert cam.rotation[:, 1][1] < 0  # image y points down the world


def test_rig_is_configurable():
    stage = default_lightstage(num_leds=50, radius=1.5, num_cameras=7, camera_distance=1.0, width=64, height=48)
    assert stage.num_leds == 50 and len(stage.cameras) == 7
    np.testing.assert_allclose(stage.led_distances(), 1.5, rtol=1e-6)
    with pytest.raises(GraMiInputError, match="inside the LED sphere"):
        default_lightstage(radius=1.0, camera_distance=1.2)


def test_calibration_round_trip(tmp_path):
    stage = default_lightstage(num_leds=20, num_cameras=3)
    stage.led_gains = np.random.default_rng(0).uniform(0.8, 1.2, (20, 3))
    save_calibration(stage, tmp_path / "c.json")
    back = load_calibration(tmp_path / "c.json")
    np.testing.assert_allclose(back.led_positions, stage.led_positions, atol=1e-6)
    np.testing.assert_allclose(back.led_gains, stage.led_gains, atol=1e-6)
    np.testing.assert_allclose(back.cameras[2].camera_to_world, stage.cameras[2].camera_to_world, atol=1e-8)
    assert back.cameras[1].name == stage.cameras[1].name


def test_committed_default_rig_matches_generator(default_stage):
    fresh = default_lightstage()
    np.testing.assert_allclose(default_stage.led_positions, fresh.led_positions, atol=1e-6)


def _broken(tmp_path, mutate):
    data = lightstage_to_dict(default_lightstage(num_leds=10, num_cameras=2))
    mutate(data)
    path = tmp_path / "calib.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize(
    "mutate, field",
    [
        (lambda d: d["leds"][3].update(position=[0, float("nan"), 1]), "leds[3].position"),
        (lambda d: d["leds"][1].update(position=[1, 2]), "leds[1].position"),
        (lambda d: d["leds"][0].update(normal=[1, 1, 0]), "leds[0].normal"),
        (lambda d: d["cameras"][1]["intrinsics"].update(fx=-3), "cameras[1].intrinsics.fx"),
        (lambda d: d["cameras"][0]["intrinsics"].update(fy=999), "cameras[0].intrinsics"),
        (
            lambda d: d["cameras"][0].update(camera_to_world=[[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]),
            "cameras[0].camera_to_world",
        ),
        (lambda d: d["cameras"][1].update(image_size=[640]), "cameras[1].image_size"),
        (lambda d: d["stage"].pop("radius"), "stage.radius"),
        (lambda d: d.update(format="something-else"), "format"),
    ],
)
def test_calibration_validation_names_the_field(tmp_path, mutate, field):
    path = _broken(tmp_path, mutate)
    with pytest.raises(GraMiInputError) as info:
        load_calibration(path)
    assert info.value.field == field
    assert str(path) in str(info.value)


def test_malformed_and_missing_calibration(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json")
    with pytest.raises(GraMiInputError, match="malformed JSON"):
        load_calibration(bad)
    with pytest.raises(GraMiInputError, match="not found"):
        load_calibration(tmp_path / "missing.json")


def test_patterns(tmp_path):
    stage = default_lightstage(num_leds=12, num_cameras=1)
    olat = olat_pattern(stage, 5)
    assert olat[5].tolist() == [stage.max_led_intensity] * 3 and olat.sum() == 3 * stage.max_led_intensity
    assert uniform_pattern(stage, 0.5).min() == stage.max_led_intensity * 0.5
    with pytest.raises(GraMiInputError, match="out of range"):
        olat_pattern(stage, 12)
    good = tmp_path / "p.json"
    good.write_text(json.dumps({"intensities": [0.5] * 12}))
    assert load_pattern(stage, good).shape == (12, 3)
    bad = tmp_path / "q.json"
    bad.write_text(json.dumps({"intensities": [[1, 1, 1]] * 11}))
    with pytest.raises(GraMiInputError, match=r"\(12,\)"):
        load_pattern(stage, bad)
    neg = tmp_path / "n.npy"
    np.save(neg, -np.ones(12))
    with pytest.raises(GraMiInputError, match="non-negative"):
        load_pattern(stage, neg)
