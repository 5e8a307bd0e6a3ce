"""The near-field point light: falloff, soft self-shadowing, envmap conditioning, CLI."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError

from .conftest import SCENES
from .test_cli import run_cli
from .test_stability import _plane_scene, _texels

TINY = SCENES / "tiny_lightstage.xml"


@pytest.fixture
def plugins(variant):
    from gra_mi.render.plugins import register_plugins

    register_plugins()
    return variant


def test_inverse_square_falloff_and_full_visibility_on_a_plane(plugins):
    from gra_mi.render.point_light import PointLight, point_light_visibility, shade_point_light

    scene = _plane_scene(np.zeros((0, 3)), np.zeros((0, 3)))
    geom = _texels([[0.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]], [[0.0, 1.0, 0.0]])
    values = []
    for h in (0.5, 1.0):
        light = PointLight([0.0, h, 0.0], 2.0, radius=0.01)
        frac = point_light_visibility(scene, geom, light)
        assert float(np.array(frac)[0]) == 1.0
        diffuse, _ = shade_point_light(geom, frac, light, np.full(1, 0.5), [0.0, 1.0, 1.0])
        values.append(diffuse[0, 0])
    assert values[0] / values[1] == pytest.approx(4.0, rel=1e-4)


def test_arm_shadows_the_torso(plugins):
    from gra_mi.render.point_light import PointLight, point_light_visibility
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(TINY, frame=0)
    relighter = Relighter(ls, resolution=64)
    geom = relighter.geometry(0)
    light = PointLight([0.7, 1.25, 0.0], 1.0, radius=0.03)  # beside the arm, at shoulder height
    frac = np.array(point_light_visibility(ls.scene, geom, light))
    p, n = np.array(geom.position).T, np.array(geom.normal).T
    to_light = light.position - p
    facing = np.sum(n * to_light, axis=1) > 0
    torso = np.abs(p[:, 0]) < 0.23  # the arm hangs at x ≈ 0.3
    shadowed = facing & torso & (frac < 0.5)
    assert shadowed.sum() > 5, "the arm casts a shadow on torso texels that face the light"
    assert np.any((frac > 0) & (frac < 1)), "the light's size gives soft shadow edges"


def test_conditioning_follows_the_papers_recipe(plugins):
    from gra_mi.render.point_light import PointLight, conditioning_envmap, conditioning_pattern
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(TINY, frame=0)
    stage = load_calibration(SCENES / "rigs" / "tiny" / "calibration.json")
    light = PointLight([0.0, 1.0, 1.0], 2.0, conditioning_radius=0.5)  # in front of the subject
    pattern = conditioning_pattern(stage, ls.scene, light)
    lit = pattern.sum(axis=1) > 0
    assert lit.any()
    d = stage.led_directions()[lit]
    assert np.all(d @ np.array([0.0, 0.0, 1.0]) > 0.7), "only LEDs in the light's direction"
    dist2 = np.sum((stage.led_positions[lit] - light.position) ** 2, axis=1)
    np.testing.assert_allclose(pattern[lit, 0], 2.0 / dist2)
    # A light inside the torso: past the light, the ray still crosses the subject's surface.
    inside = conditioning_pattern(stage, ls.scene, PointLight([0.0, 1.0, 0.05], 2.0, conditioning_radius=0.02))
    assert inside.sum() == 0
    env = conditioning_envmap(stage, pattern, 16)
    assert env.shape == (16, 32, 3) and env.max() > 0
    with pytest.raises(GraMiInputError):
        PointLight([0.0, np.nan, 0.0], 1.0)


def test_relight_cli_point_light(tmp_path):
    out = run_cli(
        "relight", str(TINY), "--frames", "0", "--point-light", "0.6,1.2,0.3", "--uv-resolution", "64", "--out", str(tmp_path / "r")
    )
    assert out.returncode == 0, out.stderr
    assert "visibility traced 0 time(s)" in out.stdout, "LEDs are off: nothing traced for them"
    for name in ("conditioning.exr", "conditioning.png", "conditioning_leds.npy", "cam00/frame_0000.exr"):
        assert (tmp_path / "r" / "point_light" / name).exists(), name
    bad = run_cli("relight", str(TINY), "--point-light", "1,2", "--out", str(tmp_path / "x"))
    assert bad.returncode == 2 and "X,Y,Z" in bad.stderr


@pytest.mark.slow
def test_near_field_pipeline(tmp_path):
    import os
    import subprocess
    import sys

    env = {**os.environ, "GRA_MI_QUIET": "1"}
    out = subprocess.run(
        [sys.executable, str(SCENES.parent / "pipelines" / "near_field.py"), str(TINY), "--positions", "2", "--uv-resolution", "64", "--out", str(tmp_path / "nf")],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "nf" / "contact_sheet.png").exists() and (tmp_path / "nf" / "light_01_conditioning.exr").exists()
