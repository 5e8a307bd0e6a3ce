"""The set: shapes of a lightstage scene besides the subject (a floor, a wall, props). They shadow the subject and hide it
from the cameras, as Mitsuba renders the same file; they carry none of the subject's texture. And shadow rays are
segments that stop at their light: what lies beyond a light (a floor just below a low LED, a wall behind a lamp or a
camera) casts no shadow."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import numpy as np

from gra_mi.core.io import read_exr
from gra_mi.render.scene_file import subject_pixels

from .conftest import SCENES
from .test_bad_input import assert_refused, run
from .test_from_scene import MATERIAL, _moving_scene, write_user_scene

FLOOR = '<shape type="rectangle" id="floor"><transform name="to_world"><scale value="3"/><rotate x="1" angle="-90"/><translate y="0.02"/></transform></shape>'
PILLAR = '<shape type="cube" id="pillar"><transform name="to_world"><scale x="0.04" y="1" z="0.04"/><translate x="0.2" y="1" z="1.2"/></transform></shape>'
BLOCKER = (
    '<shape type="sphere" id="../lamp shade"><point name="center" x="-0.6" y="2.2" z="0.3"/><float name="radius" value="0.35"/></shape>'
)
BODY = f'<shape type="obj" id="subject"><string name="filename" value="body.obj"/>{MATERIAL}</shape>'


def _tiny_stage(folder: Path, shapes: str = "") -> Path:
    """The tiny lightstage scene (its rig and subject copied beside it) with ``shapes`` added."""
    for part in ("rigs", "subjects"):
        shutil.copytree(SCENES / part / "tiny", folder / part / "tiny")
    text = (SCENES / "tiny_lightstage.xml").read_text().replace("</scene>", f"    {shapes}\n</scene>")
    (folder / "scene.xml").write_text(text)
    return folder / "scene.xml"


def _wall(center, facing, half: float = 0.4) -> str:
    """A square wall of side 2 × ``half`` at ``center``, its normal along ``facing``."""
    c, f = (", ".join(f"{v:.6f}" for v in np.asarray(x, float)) for x in (center, np.asarray(center) + facing))
    return (f'<shape type="rectangle"><transform name="to_world"><scale value="{half}"/>'
            f'<lookat origin="{c}" target="{f}" up="{"0, 0, 1" if abs(facing[1]) > 0.9 else "0, 1, 0"}"/></transform></shape>')  # fmt: skip


def test_a_set_shadows_and_hides_the_subject_as_mitsuba_renders_the_users_scene(plugins, tmp_path, capsys):
    """A user's scene with a floor just below its lowest LEDs, a pillar in front of a camera and a lamp shade (an analytic
    sphere, its id a path): from-scene keeps them, and gra-mi's relight matches Mitsuba's ``direct`` and gra_onebounce on
    the user's file, pixel by pixel where the subject is seen (every pixel where the set is in front is empty)."""
    import mitsuba as mi
    from scipy.ndimage import binary_erosion

    path = write_user_scene(tmp_path / "user", shapes=BODY + FLOOR + PILLAR + BLOCKER)
    code, lines = run(["from-scene", path, "--out", tmp_path / "stage"], capsys)
    assert code == 0, lines
    notes = (tmp_path / "stage" / "notes.md").read_text()
    for said in ("kept as the set: shape 'floor'", "shape 'pillar'", "shape '../lamp shade'", "reflects light onto it"):
        assert said in notes
    assert len(list((tmp_path / "stage" / "set").iterdir())) == 1  # the cube as a PLY; the rectangle and sphere exact
    stage = tmp_path / "stage"
    argv = ["relight", stage / "scene.xml", "--pattern", stage / "lighting.json", "--albedo", stage / "albedo.exr"]
    assert run([*argv, "--roughness", stage / "roughness.exr", "--cameras", "front,side", "--out", tmp_path / "r"], capsys)[0] == 0
    scene = mi.load_file(str(path), parallel=False)
    for index, name in ((0, "front"), (1, "side")):
        ours = read_exr(tmp_path / "r" / "lighting" / name / "frame_0000.exr")
        subject = subject_pixels(scene, index)  # (whether the centre ray meets the subject first, through Mitsuba's sensor)
        anything = np.array(mi.render(scene, sensor=index, integrator=mi.load_dict({"type": "direct"}), spp=16))[..., 3] > 0.999
        hidden = anything & ~subject
        # the set in front: no subject there (a border pixel's sub-pixel rays may reach past the set's edge)
        assert hidden.sum() > 100 and (ours[..., 3][binary_erosion(hidden)] == 0).all() and (ours[..., 3][hidden] < 1).all(), name
        assert (ours[..., 3][subject] > 0).mean() > 0.99, name
        inside = binary_erosion(subject) & (ours[..., 3] > 0.999)  # whole pixels (a border pixel mixes in the set)
        assert inside.sum() > 200
        for integrator, spp, median in (("direct", 1024, 0.08), ("gra_onebounce", 64, 0.03)):
            truth = np.array(mi.render(scene, sensor=index, integrator=mi.load_dict({"type": integrator}), spp=spp))[..., :3]
            ratio = ours[..., :3][inside].sum() / truth[inside].sum()
            rel = np.abs(ours[..., :3] - truth)[inside] / np.maximum(truth[inside], 2e-2)
            assert abs(ratio - 1) < 0.03 and np.median(rel) < median, (name, integrator, ratio, np.median(rel))
    # the set shadows the subject: without it, the same lighting is brighter where the front camera sees the subject
    clean = write_user_scene(tmp_path / "clean")
    assert run(["from-scene", clean, "--out", tmp_path / "clean_stage"], capsys)[0] == 0
    argv = ["relight", tmp_path / "clean_stage" / "scene.xml", "--pattern", stage / "lighting.json", "--albedo", stage / "albedo.exr"]
    assert run([*argv, "--roughness", stage / "roughness.exr", "--cameras", "front", "--out", tmp_path / "c"], capsys)[0] == 0
    lit, unshadowed = (read_exr(tmp_path / d / "lighting" / "front" / "frame_0000.exr") for d in ("r", "c"))
    both = (lit[..., 3] > 0.999) & (unshadowed[..., 3] > 0.999)
    assert lit[..., :3][both].sum() < 0.9 * unshadowed[..., :3][both].sum()


def test_shadow_rays_stop_at_their_light(plugins, tmp_path):
    """Walls beyond every LED (outside the rig's sphere: a room), behind a near-field light and behind a camera change
    nothing a ray from the subject to them carries; far field too, where a ray ends at its LED's distance. ``mi.Ray3f(o, d, maxt)`` sets a ray's time, not its end: rays ran on past their
    light, and a floor just below a low LED put it out."""
    import mitsuba as mi

    from gra_mi.fit.materials import _camera_visible
    from gra_mi.render.point_light import PointLight, point_light_visibility
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.lightstage import load_calibration
    from gra_mi.stage.scene import LightstageScene

    stage = load_calibration(SCENES / "rigs" / "tiny" / "calibration.json")
    center, camera = stage.center, stage.cameras[0]
    light = PointLight(center + np.array([0.0, 0.1, 0.7]), np.ones(3), radius=0.02)
    outward = [(center + 1.3 * (p - center), (p - center) / np.linalg.norm(p - center)) for p in stage.led_positions]
    beyond = {  # what each ray carries, and walls beyond where those rays end (each wall in its own scene)
        "LEDs": (lambda ls, r, g: np.array(r.visibility(0)), "".join(_wall(c, -f, 0.3) for c, f in outward)),
        "LEDs far field": (lambda ls, r, g: np.array(r.visibility(0, far_field=True)), "".join(_wall(c, -f, 0.3) for c, f in outward)),
        "a near light": (
            lambda ls, r, g: np.array(point_light_visibility(ls.scene, g, light)),
            _wall(light.position + [0, 0, 0.15], -np.eye(3)[2], 1.0),
        ),
        "a camera": (
            lambda ls, r, g: _camera_visible(ls.scene, camera, g),
            _wall(1.2 * camera.position - 0.2 * center, center - camera.position, 1.0),
        ),
    }
    for what, (carried, walls) in beyond.items():
        seen = []
        for name, shapes in (("bare", ""), ("walled", walls)):
            ls = LightstageScene.load(_tiny_stage(tmp_path / what / name, shapes))
            assert len(ls.scene.shapes()) > 1 or not shapes
            relighter = Relighter(ls, 64)
            geom = relighter.geometry(0)
            ls.set_frame(0)
            seen.append(carried(ls, relighter, geom))
        assert seen[0].any(), what
        np.testing.assert_array_equal(seen[0], seen[1], err_msg=what)
    # what lies inside the rig still shadows, far field too: a floor under the feet puts out the LEDs far below it
    below = np.flatnonzero((stage.led_positions - center)[:, 1] < -0.5 * np.linalg.norm(stage.led_positions - center, axis=1))
    lit = []
    for name, shapes in (("open", ""), ("floored", FLOOR.replace('translate y="0.02"', 'translate y="0.44"'))):
        relighter = Relighter(LightstageScene.load(_tiny_stage(tmp_path / name, shapes)), 64)
        bits, m = np.array(relighter.visibility(0, far_field=True)), relighter.atlas.num_texels
        lit.append(sum(int(((bits[(k // 32) * m : (k // 32 + 1) * m] >> (k % 32)) & 1).sum()) for k in below))
    assert below.size and lit[0] > 0 and lit[1] == 0, lit
    assert mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f(0, 0, 1), 0.5).maxt[0] > 1e30  # (why: the third argument is the time)


def test_a_visibility_cache_traced_without_the_set_is_not_served_with_it(plugins, tmp_path, capsys):
    """``--vis-cache`` keys the bits by the set too: adding a wall over the subject to the scene retraces them."""
    bare = _tiny_stage(tmp_path / "s")
    roof = _wall([0.0, 1.9, 0.0], np.array([0.0, -1.0, 0.0]), 1.5)  # over the subject: the upper LEDs go dark
    walled = tmp_path / "s" / "walled.xml"
    walled.write_text(bare.read_text().replace("</scene>", f"    {roof}\n</scene>"))
    every = tmp_path / "every.json"
    every.write_text(json.dumps({"intensities": [[1.0, 1.0, 1.0]] * 64}))
    renders = {}
    for name, scene, cache in (("bare", bare, "vc"), ("walled", walled, "vc"), ("fresh", walled, "vc2")):
        argv = ["relight", scene, "--pattern", every, "--frames", "0", "--vis-cache", tmp_path / cache, "--out", tmp_path / name]
        code, lines = run(argv, capsys)
        assert code == 0, lines
        renders[name] = read_exr(next((tmp_path / name).rglob("frame_0000.exr")))
    assert renders["walled"][..., :3].sum() < 0.9 * renders["bare"][..., :3].sum()
    np.testing.assert_array_equal(renders["walled"], renders["fresh"])


def test_a_set_that_moves_with_the_frames_is_refused_naming_the_frame(plugins, tmp_path, capsys):
    path = _moving_scene(tmp_path / "user")
    moving = PILLAR.replace('translate x="0.2"', 'translate x="0.$frame"')
    path.write_text(path.read_text().replace("</scene>", f"{FLOOR}{moving}</scene>"))
    assert_refused(["from-scene", path, "--frames", "0:3", "--out", tmp_path / "a"], capsys, "frame=0001", "the set stays still")
    still = _moving_scene(tmp_path / "still")
    still.write_text(still.read_text().replace("</scene>", f"{FLOOR}{PILLAR}</scene>"))
    assert run(["from-scene", still, "--frames", "0:3", "--out", tmp_path / "b"], capsys)[0] == 0


def test_a_set_shape_the_stage_cannot_hold_is_left_out_and_said(plugins, tmp_path, capsys):
    (tmp_path / "user").mkdir()
    (tmp_path / "user" / "hair.txt").write_text("0 1.5 0.2 0.01\n0.1 1.6 0.2 0.01\n0.2 1.6 0.3 0.01\n0.3 1.5 0.3 0.01\n")
    curve = '<shape type="bsplinecurve" id="hair"><string name="filename" value="hair.txt"/></shape>'
    path = write_user_scene(tmp_path / "user", shapes=BODY + curve)
    assert run(["from-scene", path, "--out", tmp_path / "stage"], capsys)[0] == 0
    notes = (tmp_path / "stage" / "notes.md").read_text()
    assert "left out: shape 'hair'" in notes and "its shadows are not in gra-mi's renders" in notes
    assert not (tmp_path / "stage" / "set").exists() and "set_000" not in (tmp_path / "stage" / "scene.xml").read_text()


def test_photographs_of_a_stage_in_a_set_import_with_the_set_and_fit(plugins, tmp_path, capsys, caplog):
    """Photographs of a user's stage with a floor and a lamp (their pixels in the photographs' alpha too; the subject's
    masks beside them): `import mitsuba` carries the set into the capture's scene in the capture's frame, and the fit
    explains its shadows. The same capture without its set fits an albedo far too dark (the LEDs the floor hides would
    light the subject)."""
    from gra_mi.core.io import read_exr_channels
    from gra_mi.stage.lightstage import load_calibration

    from .test_from_scene import RGBA_SENSORS, _leds, _photograph

    caplog.set_level(logging.INFO)
    folder = tmp_path / "capture"
    lamp = '<shape type="sphere" id="lamp"><point name="center" x="0.5" y="1.9" z="0.5"/><float name="radius" value="0.2"/></shape>'
    floor = FLOOR.replace('translate y="0.02"', 'translate y="0.44"')  # just under the feet
    write_user_scene(folder, sensors=RGBA_SENSORS, lights=_leds(off_every=0), shapes=BODY + floor + lamp).rename(folder / "scene.xml")
    from gra_mi.capture.scene_stage import stage_from_scene

    stage = stage_from_scene(folder / "scene.xml")
    lighting = [{"frame": 0, "uniform": 1.0}] + [{"frame": k, "led": k} for k in range(1, 20)] + [{"frame": 20, "split": "test", "led": 20}]
    _photograph(folder / "scene.xml", folder, lighting, stage.intensities)
    assert (folder / "mask" / "front" / "000000.png").is_file()
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": lighting}))
    argv = ["import", "mitsuba", folder, "--lighting", tmp_path / "lighting.json", "--eval-cameras", "tele", "--uv-resolution", "64"]
    code, lines = run([*argv, "--out", tmp_path / "cap"], capsys)
    assert code == 0, lines
    assert "kept as the set: shape 'lamp'" in caplog.text
    report = json.loads((tmp_path / "cap" / "import_report.json").read_text())
    assert (
        sorted(report["set"]) == ["shape 'floor'", "shape 'lamp'"] and "shape 'lamp'" in (tmp_path / "cap" / "import_report.md").read_text()
    )
    text = (tmp_path / "cap" / "scene.xml").read_text()
    assert 'type="sphere" id="set_' in text and 'type="rectangle" id="set_' in text
    # the lamp where the capture's frame puts the scene's (0.5, 1.9, 0.5): the import's move of the LEDs applied to it
    imported = load_calibration(tmp_path / "cap" / "rig" / "calibration.json")
    move = imported.led_positions[0] - stage.stage.led_positions[0]
    np.testing.assert_allclose(
        imported.led_positions - stage.stage.led_positions, np.broadcast_to(move, imported.led_positions.shape), atol=1e-5
    )
    import mitsuba as mi

    shapes = {s.class_name(): s for s in mi.load_file(str(tmp_path / "cap" / "scene.xml"), parallel=False).shapes()}
    np.testing.assert_allclose(np.array(shapes["Sphere"].bbox().center()), np.array([0.5, 1.9, 0.5]) + move, atol=1e-5)
    bare = tmp_path / "cap_without_set"
    shutil.copytree(tmp_path / "cap", bare)
    (bare / "scene.xml").write_text("\n".join(line for line in text.splitlines() if 'id="set_' not in line) + "\n")
    truth = read_exr(folder / "albedo_in.exr")[..., :3]
    ratios = {}
    for name, cap in (("with", tmp_path / "cap"), ("without", bare)):
        assert run(["fit", cap, "--out", tmp_path / f"fit_{name}"], capsys)[0] == 0
        fitted = read_exr(tmp_path / f"fit_{name}" / "albedo.exr")[..., :3]
        seen = read_exr_channels(tmp_path / f"fit_{name}" / "confidence.exr")["views"] > 0
        assert seen.sum() > 500
        ratios[name] = fitted[seen].mean(axis=0) / truth[seen].mean(axis=0)
    np.testing.assert_allclose(ratios["with"], 1.0, atol=0.06)
    assert (ratios["without"] < 0.5).all(), ratios
