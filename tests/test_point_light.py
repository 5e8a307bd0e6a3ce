"""The near-field point light: falloff, soft self-shadowing, envmap conditioning, CLI."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError

from .conftest import SCENES
from .test_cli import run_cli
from .test_stability import _plane_scene, _texels

TINY = SCENES / "tiny_lightstage.xml"


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
    for name in ("conditioning/frame_0000.exr", "conditioning/frame_0000.png", "conditioning/frame_0000_leds.npy", "cam00/frame_0000.exr"):
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
        [sys.executable, str(SCENES.parent / "pipelines" / "near_field.py"), str(TINY), "--frames", "0:3", "--uv-resolution", "64", "--out", str(tmp_path / "nf")],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "nf" / "contact_sheet.png").exists() and (tmp_path / "nf" / "lights" / "conditioning" / "frame_0002.exr").exists()
    from gra_mi.render.light_path import LightPath

    path = LightPath.load(tmp_path / "nf" / "lights.json")  # the file it wrote is one `gra-mi relight --lights` reads
    assert [round(light.position[0], 3) for light in path.at(0)] == [0.0] and path.at(1)[0].position[0] > 0.5


def test_spot_falloff_is_mitsubas_spot(plugins):
    """A spot's I·falloff/d² at texels equals what Mitsuba's own `spot` emitter gives for the same points."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.point_light import PointLight, shade_point_light

    rng = np.random.default_rng(1)
    points = rng.uniform([-0.6, 0.4, -0.3], [0.6, 1.6, 0.3], (4000, 3))
    origin, target = np.array([0.1, 1.3, 1.2]), np.array([0.0, 1.0, 0.0])
    light = PointLight(origin, [2.0, 1.5, 1.0], radius=0.0, direction=target - origin, cutoff_angle=20.0, beam_width=12.0)
    spot = mi.load_dict({
        "type": "spot", "cutoff_angle": 20.0, "beam_width": 12.0, "intensity": {"type": "rgb", "value": [2.0, 1.5, 1.0]},
        "to_world": mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=target.tolist(), up=[0, 1, 0]),
    })  # fmt: skip
    it = dr.zeros(mi.SurfaceInteraction3f, len(points))
    it.p = mi.Point3f(*points.T.astype(np.float32))
    _, mitsuba_weight = spot.sample_direction(it, mi.Point2f(0.5, 0.5), True)
    mitsuba_weight = np.array(mitsuba_weight).T
    # Ours: texels facing the light, fully visible, roughness 1 and a diffuse-only read-out of the weight.
    normals = origin - points
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    geom = _texels(points, normals, normals)
    diffuse, _ = shade_point_light(geom, mi.Float(np.ones(len(points), np.float32)), light, np.ones(len(points)), origin)
    ours = diffuse * np.pi  # Lambert at normal incidence: (1/π) · weight
    edge = (mitsuba_weight[:, 0] > 0) & (mitsuba_weight[:, 0] < 2.0 / np.sum((points - origin) ** 2, axis=1) * 0.999)
    assert edge.sum() > 20 and (mitsuba_weight[:, 0] == 0).sum() > 100, "points in the ramp and outside the cone"
    np.testing.assert_allclose(ours, mitsuba_weight, rtol=2e-3, atol=1e-6)
    np.testing.assert_allclose(
        light.falloff(points - origin), mitsuba_weight[:, 0] * np.sum((points - origin) ** 2, axis=1) / 2.0, rtol=2e-3, atol=1e-6
    )


def test_several_near_lights_add_and_a_path_interpolates(plugins, tmp_path):
    import json

    from gra_mi.render.light_path import LightPath
    from gra_mi.render.point_light import PointLight
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(TINY, frame=0)
    relighter = Relighter(ls, resolution=32)
    off = np.zeros((ls.stage.num_leds, 3))
    a = PointLight([0.6, 1.2, 0.4], 1.5)
    b = PointLight([0.0, 1.8, 0.9], 4.0, direction=[0.0, -0.7, -0.9], cutoff_angle=25.0)
    both = relighter.shade(0, 0, off, [a, b])[0].radiance
    apart = relighter.shade(0, 0, off, a)[0].radiance + relighter.shade(0, 0, off, b)[0].radiance
    np.testing.assert_allclose(both, apart, rtol=1e-5, atol=1e-7)
    (tmp_path / "p.json").write_text(json.dumps({"lights": [
        {"name": "key", "intensity": [1, 2, 3], "keyframes": [{"frame": 2, "position": [0, 1, 1]}, {"frame": 6, "position": [1, 1, 0], "intensity": 5}]},
        {"name": "rim", "type": "spot", "cutoff_angle": 30, "target": [0, 1, 0],
         "keyframes": [{"frame": 0, "position": [0, 2, 0]}, {"frame": 9, "position": [0, 2, 0], "direction": [0, -1, 0]}]},
    ]}))  # fmt: skip
    path = LightPath.load(tmp_path / "p.json")
    key, rim = path.at(3)
    np.testing.assert_allclose(key.position, [0.25, 1, 0.75])
    np.testing.assert_allclose(key.intensity, [2.0, 2.75, 3.5])
    np.testing.assert_allclose(rim.direction, [0, -1, 0]) and rim.beam_width == 22.5
    path.check_frames([2, 6])
    with pytest.raises(GraMiInputError, match="light 'key' has keyframes for frames 2..6, frame"):
        path.check_frames([1, 2])


@pytest.mark.parametrize(
    "light, field, problem",
    [
        ({"keyframes": [{"frame": 0, "position": [0, "nan", 1]}]}, "lights[0].keyframes[0].position", "three numbers"),
        ({"keyframes": [{"frame": 0, "position": [0, float("nan"), 1]}]}, "lights[0].keyframes[0].position", "finite"),
        ({"keyframes": [{"frame": 3, "position": [0, 1, 1]}, {"frame": 3, "position": [0, 1, 1]}]}, "lights[0].keyframes", "must increase"),
        ({"keyframes": [{"frame": -1, "position": [0, 1, 1]}]}, "lights[0].keyframes[0].frame", "frame index"),
        ({"intensity": -2, "keyframes": [{"frame": 0, "position": [0, 1, 1]}]}, "lights[0].keyframes[0].intensity", ">= 0"),
        ({"type": "area", "keyframes": [{"frame": 0, "position": [0, 1, 1]}]}, "lights[0].type", "point, spot"),
        ({"type": "spot", "keyframes": [{"frame": 0, "position": [0, 1, 1]}]}, "lights[0].keyframes[0]", "'direction' or 'target'"),
        (
            {"type": "spot", "cutoff_angle": 190, "keyframes": [{"frame": 0, "position": [0, 1, 1], "direction": [0, 0, -1]}]},
            "keyframes[0]",
            "< 180",
        ),
        ({"type": "spot", "keyframes": [{"frame": 0, "position": [0, 1, 1], "target": [0, 1, 1]}]}, "target", "zero vector"),
        ({"keyframes": []}, "lights[0].keyframes", "at least one keyframe"),
        ({"keyframes": [3]}, "lights[0].keyframes[0]", "expected an object"),
    ],
)
def test_bad_light_path_files_name_the_field(tmp_path, light, field, problem):
    import json

    from gra_mi.render.light_path import LightPath

    (tmp_path / "bad.json").write_text(json.dumps({"lights": [light]}))
    with pytest.raises(GraMiInputError) as info:
        LightPath.load(tmp_path / "bad.json")
    assert "bad.json" in str(info.value) and field in str(info.value) and problem in str(info.value), str(info.value)


def test_relight_cli_moving_lights_video_and_conditioning(tmp_path):
    import json

    from gra_mi.core.io import read_exr

    lights = {"lights": [
        {"name": "key", "intensity": 1.5, "keyframes": [{"frame": 0, "position": [0.7, 1.2, 0.5]}, {"frame": 3, "position": [-0.7, 1.2, 0.5]}]},
        {"name": "top", "type": "spot", "intensity": 4, "cutoff_angle": 30, "keyframes": [{"frame": 0, "position": [0, 2.2, 0.6], "target": [0, 1.1, 0]}]},
    ]}  # fmt: skip
    (tmp_path / "sweep.json").write_text(json.dumps(lights))
    out = run_cli(
        "relight",
        str(TINY),
        "--lights",
        str(tmp_path / "sweep.json"),
        "--frames",
        "0:4",
        "--uv-resolution",
        "32",
        "--out",
        str(tmp_path / "r"),
    )
    assert out.returncode == 0, out.stderr
    folder = tmp_path / "r" / "sweep"
    assert (folder / "cam00.mp4").is_file()
    first, last = (read_exr(folder / "cam00" / f"frame_{f:04d}.exr") for f in (0, 3))
    covered = (first[..., 3] > 0.99) & (last[..., 3] > 0.99)
    columns = np.nonzero(covered.any(axis=0))[0]
    left, right = columns[: len(columns) // 2], columns[len(columns) // 2 :]
    side = lambda image, cols: image[:, cols, :3].sum()  # noqa: E731
    # The key light moves from +x to -x: camera 0 looks down -z, so +x is the image's right.
    assert side(first, right) > side(first, left) and side(last, left) > side(last, right)
    envs = [read_exr(folder / "conditioning" / f"frame_{f:04d}.exr") for f in (0, 3)]
    assert envs[0].max() > 0 and not np.allclose(envs[0], envs[1]), "the conditioning follows the light"
    missing = run_cli("relight", str(TINY), "--lights", str(tmp_path / "sweep.json"), "--frames", "0:6", "--out", str(tmp_path / "x"))
    assert missing.returncode == 2 and "sweep.json" in missing.stderr and "[4, 5]" in missing.stderr
    (tmp_path / "broken.json").write_text('{"lights": [')
    for name, said in (("absent.json", "not found"), ("broken.json", "malformed JSON")):
        bad = run_cli("relight", str(TINY), "--lights", str(tmp_path / name), "--out", str(tmp_path / "y"))
        assert bad.returncode == 2 and name in bad.stderr and said in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
