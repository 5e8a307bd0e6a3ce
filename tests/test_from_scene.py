"""``gra-mi from-scene``: a lightstage made of a Mitsuba scene a user wrote, checked against Mitsuba's own reading of
that scene (its sensors' projections, its bitmaps, its ``direct`` integrator's render) and fed what a user gets wrong.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from gra_mi.cli import main
from gra_mi.core.io import read_exr, write_exr

from .conftest import SCENES
from .test_bad_input import assert_refused, run

SENSORS = """
  <sensor type="perspective" id="front">
    <float name="fov" value="35"/><string name="fov_axis" value="y"/>
    <float name="principal_point_offset_x" value="0.04"/><float name="principal_point_offset_y" value="-0.03"/>
    <transform name="to_world"><lookat origin="0.3, 1.1, 2.4" target="0, 1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="96"/><integer name="height" value="72"/>
      <string name="pixel_format" value="rgba"/><rfilter type="box"/></film>
  </sensor>
  <sensor type="perspective" id="side">
    <float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="-2.2, 1.3, 0.6" target="0, 1, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="120"/><integer name="height" value="80"/>
      <integer name="crop_offset_x" value="20"/><integer name="crop_offset_y" value="6"/>
      <integer name="crop_width" value="70"/><integer name="crop_height" value="60"/>
      <string name="pixel_format" value="rgba"/><rfilter type="box"/></film>
  </sensor>
  <sensor type="perspective" id="tele">
    <string name="focal_length" value="85mm"/>
    <transform name="to_world"><rotate y="1" angle="180"/><translate x="0.2" y="1.1" z="3.5"/></transform>
    <film type="hdrfilm"><integer name="width" value="48"/><integer name="height" value="64"/></film>
  </sensor>"""
RGBA_SENSORS = SENSORS.replace('value="64"/></film>', 'value="64"/><string name="pixel_format" value="rgba"/></film>')  # alpha: masks
MATERIAL = """<bsdf type="gra_microfacet"><texture type="bitmap" name="albedo"><string name="filename" value="albedo_in.exr"/></texture>
      <texture type="bitmap" name="roughness"><string name="filename" value="rough_in.exr"/><boolean name="raw" value="true"/></texture></bsdf>"""


def _leds(count: int = 24, off_every: int = 5) -> str:
    """Point LEDs on a 2 m sphere around the subject, every ``off_every``-th one off, the others of random colours."""
    rng = np.random.default_rng(0)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    lines = []
    for k, d in enumerate(directions):
        p, i = np.array([0, 1, 0]) + 2.0 * d, rng.uniform(0.2, 1.0, 3) * (not off_every or k % off_every != 0)
        lines.append(f'<emitter type="point" id="L{k}"><point name="position" x="{p[0]}" y="{p[1]}" z="{p[2]}"/>'
                     f'<rgb name="intensity" value="{i[0]}, {i[1]}, {i[2]}"/></emitter>')  # fmt: skip
    return "\n  ".join(lines)


def write_user_scene(folder: Path, sensors: str = SENSORS, lights: str | None = None, shapes: str | None = None) -> Path:
    """A scene as a user writes it: the tiny body as an OBJ (its texture coordinates in OBJ's convention, which
    Mitsuba flips on loading), two sensors spelt differently, point LEDs, a gra_microfacet material with bitmaps."""
    from gra_mi.subject.sequence import load_sequence

    folder.mkdir(parents=True, exist_ok=True)
    seq = load_sequence(SCENES / "subjects" / "tiny")
    lines = [f"v {a:.7f} {b:.7f} {c:.7f}" for a, b, c in seq.vertices[1]] + [f"vt {a:.7f} {1 - b:.7f}" for a, b in seq.uvs]
    lines += [f"f {a + 1}/{a + 1} {b + 1}/{b + 1} {c + 1}/{c + 1}" for a, b, c in seq.faces]
    (folder / "body.obj").write_text("\n".join(lines) + "\n")
    u = (np.arange(64) + 0.5) / 64
    albedo = np.stack(np.broadcast_arrays(0.2 + 0.6 * u[None, :], 0.3 + 0.5 * u[:, None], 0.4), axis=-1)
    write_exr(folder / "albedo_in.exr", albedo.astype(np.float32))
    write_exr(folder / "rough_in.exr", (0.3 + 0.4 * u[None, :] * u[:, None])[..., None].astype(np.float32))
    body = f'<shape type="obj" id="subject"><string name="filename" value="body.obj"/>{MATERIAL}</shape>'
    xml = f'<scene version="3.0.0">{sensors}\n  {_leds() if lights is None else lights}\n  {body if shapes is None else shapes}\n</scene>\n'
    (folder / "user.xml").write_text(xml)
    return folder / "user.xml"


def test_cameras_project_as_mitsubas_sensors_do(plugins, tmp_path):
    """Every world point lands on the pixel Mitsuba's own sensor puts it on: a y-axis field of view, principal point
    offsets, a crop window, a 35 mm focal length, a transform of rotations and translations."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.capture.scene_stage import stage_from_scene

    path = write_user_scene(tmp_path)
    stage = stage_from_scene(path)
    points = np.random.default_rng(1).uniform([-0.5, 0.3, -0.5], [0.5, 1.7, 0.5], (400, 3))
    for sensor, camera in zip(mi.load_file(str(path), parallel=False).sensors(), stage.stage.cameras, strict=True):
        it = dr.zeros(mi.Interaction3f, len(points))
        it.p = mi.Point3f(points.T.astype(np.float32))
        ds, weight = sensor.sample_direction(it, mi.Point2f(0.5, 0.5))
        seen = np.array(weight)[0] > 0
        assert seen.sum() > 50
        ours = camera.project(points)[:, :2]
        assert np.abs(np.array(ds.uv).T[seen] - ours[seen]).max() < 2e-3, camera.name
    assert [(c.name, c.width, c.height) for c in stage.stage.cameras] == [("front", 96, 72), ("side", 70, 60), ("tele", 48, 64)]


def test_material_maps_are_the_bitmaps_and_the_drive_the_scenes_leds(plugins, tmp_path):
    from gra_mi.capture.scene_stage import stage_from_scene

    stage = stage_from_scene(write_user_scene(tmp_path))
    # texel centres: the bitmap's own texels (inside the UV layout, the UV interpolated on the surface: float rounding)
    np.testing.assert_allclose(stage.maps["albedo"], read_exr(tmp_path / "albedo_in.exr")[..., :3], atol=1e-5)
    np.testing.assert_allclose(stage.maps["roughness"], read_exr(tmp_path / "rough_in.exr")[..., :1], atol=1e-5)
    assert stage.stage.num_leds == 24 and stage.intensities.max() == pytest.approx(stage.stage.max_led_intensity)
    assert (stage.intensities[::5] == 0).all() and (stage.intensities.max(axis=1)[1:5] > 0).all()
    assert not stage.notes


def assert_relit_like_mitsuba(path: Path, cameras: tuple[str, ...], tmp_path: Path, capsys) -> None:
    """``path`` made a stage and relit by gra-mi under the scene's own LEDs (lighting.json) against Mitsuba's ``direct``
    rendering the user's file as it is (its sampling, visibility and texture look-ups, none of gra-mi's code but the
    BSDF) and gra_onebounce on it (image space: the same light, no UV resampling): totals within 2 %."""
    import mitsuba as mi

    code, lines = run(["from-scene", path, "--out", tmp_path / "stage"], capsys)
    assert code == 0, lines
    stage = tmp_path / "stage"
    assert {p.name for p in stage.iterdir()} >= {"scene.xml", "rig", "subject", "lighting.json", "albedo.exr", "roughness.exr", "notes.md"}
    argv = ["relight", stage / "scene.xml", "--pattern", stage / "lighting.json", "--albedo", stage / "albedo.exr"]
    code, lines = run([*argv, "--roughness", stage / "roughness.exr", "--cameras", ",".join(cameras), "--out", tmp_path / "r"], capsys)
    assert code == 0, lines
    scene = mi.load_file(str(path), parallel=False)
    for name in cameras:
        index = [sensor.id() for sensor in scene.sensors()].index(name)
        ours = read_exr(tmp_path / "r" / "lighting" / name / "frame_0000.exr")
        for integrator, spp, median in (("direct", 1024, 0.08), ("gra_onebounce", 64, 0.03)):
            truth = np.array(mi.render(scene, sensor=index, integrator=mi.load_dict({"type": integrator}), spp=spp))
            covered = (ours[..., 3] > 0.5) & (truth[..., 3] > 0.999)
            assert covered.sum() > 500
            ratio = ours[..., :3][covered].sum() / truth[..., :3][covered].sum()
            rel = np.abs(ours[..., :3] - truth[..., :3])[covered] / np.maximum(truth[..., :3][covered], 2e-2)
            assert abs(ratio - 1) < 0.02 and np.median(rel) < median, (name, integrator, ratio, np.median(rel))


def test_relit_stage_matches_mitsubas_render_of_the_users_scene(plugins, tmp_path, capsys):
    """A scene with a principal point offset and a cropped film, its maps from EXR bitmaps."""
    assert_relit_like_mitsuba(write_user_scene(tmp_path / "user"), ("front", "side"), tmp_path, capsys)


def test_the_shipped_example_stage_relights_as_mitsuba_renders_it(plugins, tmp_path, capsys):
    """scenes/user_stage, the guide's example (a PNG albedo, warm and cool LEDs, a y field of view), as the guide runs it."""
    assert_relit_like_mitsuba(SCENES / "user_stage" / "scene.xml", ("front", "left"), tmp_path, capsys)


def test_what_the_stage_leaves_out_is_said(plugins, tmp_path, capsys):
    floor = '<shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/></transform></shape>'
    body = '<shape type="obj" id="subject"><string name="filename" value="body.obj"/><bsdf type="twosided"><bsdf type="diffuse"/></bsdf></shape>'
    path = write_user_scene(tmp_path / "user", shapes=body + floor)
    assert main(["from-scene", str(path), "--out", str(tmp_path / "stage")]) == 0
    printed = capsys.readouterr().out
    notes = (tmp_path / "stage" / "notes.md").read_text()
    for said in ("kept as the set: shape 'floor'", "SmoothDiffuse has no roughness"):
        assert said in notes and said in printed
    albedo = read_exr(tmp_path / "stage" / "albedo.exr")
    assert albedo.shape == (256, 256, 3) and np.allclose(albedo, 0.5)  # diffuse's default reflectance, through twosided
    assert not (tmp_path / "stage" / "roughness.exr").exists()


def test_rerun_is_the_same_and_an_edited_scene_starts_over(plugins, tmp_path, capsys):
    path = write_user_scene(tmp_path / "user")
    out = tmp_path / "stage"
    assert run(["from-scene", path, "--out", out], capsys)[0] == 0
    first = json.loads((out / "lighting.json").read_text())
    assert run(["from-scene", path, "--out", out], capsys)[0] == 0
    write_user_scene(tmp_path / "user", lights='<emitter type="point"><point name="position" x="0" y="3" z="0"/></emitter>')
    assert run(["from-scene", path, "--out", out], capsys)[0] == 0
    assert len(json.loads((out / "lighting.json").read_text())["intensities"]) == 1 != len(first["intensities"])


SPHERE = '<shape type="sphere" id="subject"/>'
BAD = {
    "thinlens": ({"sensors": '<sensor type="thinlens" id="dof"><float name="aperture_radius" value="0.01"/></sensor>'}, ("'dof'", "ThinLensCamera", "perspective")),
    "area LED": ({"lights": '<shape type="sphere" id="panel"><emitter type="area"/></shape>'}, ("'area' emitter", "point emitters")),
    "envmap": ({"lights": '<emitter type="constant" id="sky"/>'}, ("'sky'", "'constant'")),
    "no light": ({"lights": ""}, ("no emitter",)),
    "not a mesh": ({"shapes": SPHERE}, ("Sphere, not a mesh",)),
    "two unnamed shapes": ({"shapes": '<shape type="obj"><string name="filename" value="body.obj"/></shape>' * 2}, ("no shape has id 'subject'",)),
    "mirrored camera": ({"sensors": SENSORS.replace('<lookat origin="0.3', '<scale x="-1"/><lookat origin="0.3')}, ("'front'", "mirrors")),
    "negative LED": ({"lights": '<emitter type="point"><point name="position" x="0" y="-1" z="0"/><rgb name="intensity" value="-1"/></emitter>'}, ("must be finite, >= 0",)),
    "blinding LED": ({"lights": '<emitter type="point"><point name="position" x="0" y="-1" z="0"/><rgb name="intensity" value="1e21"/></emitter>'}, ("<= 1e+20 W/sr",)),
}  # fmt: skip


@pytest.mark.parametrize("case", list(BAD))
def test_what_a_lightstage_cannot_hold_is_refused_by_name(plugins, tmp_path, capsys, case):
    parts, needles = BAD[case]
    path = write_user_scene(tmp_path / "user", **parts)
    assert_refused(["from-scene", path, "--out", tmp_path / "stage"], capsys, str(path), *needles, out=tmp_path / "stage")


def test_a_mesh_without_uvs_gets_an_atlas_and_an_output_over_the_input_is_refused(plugins, tmp_path, capsys):
    path = write_user_scene(tmp_path / "user")
    obj = tmp_path / "user" / "body.obj"
    lines = [" ".join(w.split("/")[0] for w in line.split()) for line in obj.read_text().splitlines() if not line.startswith("vt")]
    obj.write_text("\n".join(lines) + "\n")
    assert run(["from-scene", path, "--out", tmp_path / "stage"], capsys)[0] == 0
    notes = (tmp_path / "stage" / "notes.md").read_text()
    assert "its UV layout is generated (xatlas" in notes and "textures are not baked" in notes
    assert not (tmp_path / "stage" / "albedo.exr").exists()
    code, lines = run(["relight", tmp_path / "stage" / "scene.xml", "--olat", "1", "--out", tmp_path / "r"], capsys)
    assert code == 0, lines
    assert read_exr(tmp_path / "r" / "olat001" / "front" / "frame_0000.exr")[..., :3].max() > 0
    assert_refused(["from-scene", path, "--out", tmp_path / "user"], capsys, "the scene input")
    assert_refused(["from-scene", path, "--out", tmp_path / "x", "-D", "nothing=1"], capsys, "nothing", out=tmp_path / "x")


def _moving_scene(folder: Path, frames: int = 3, sensors: str = SENSORS, lights: str | None = None) -> Path:
    """The user scene with the body as one OBJ per frame (``body_$frame.obj``, the tiny subject's frames)."""
    from gra_mi.subject.sequence import load_sequence

    path = write_user_scene(folder, sensors=sensors, lights=lights)
    seq = load_sequence(SCENES / "subjects" / "tiny")
    body = (folder / "body.obj").read_text().splitlines()
    for t in range(frames):
        vertices = [f"v {a:.7f} {b:.7f} {c:.7f}" for a, b, c in seq.vertices[t]]
        (folder / f"body_{t:04d}.obj").write_text("\n".join(vertices + [line for line in body if not line.startswith("v ")]) + "\n")
    text = path.read_text().replace('value="body.obj"', 'value="body_$frame.obj"')
    path.write_text(text.replace('<scene version="3.0.0">', '<scene version="3.0.0"><default name="frame" value="0000"/>'))
    return path


def test_a_moving_subject_comes_in_a_frame_at_a_time(plugins, tmp_path, capsys):
    from gra_mi.subject.sequence import load_sequence

    path = _moving_scene(tmp_path / "user")
    assert run(["from-scene", path, "--frames", "0:3", "--fps", "30", "--out", tmp_path / "stage"], capsys)[0] == 0
    ours, truth = load_sequence(tmp_path / "stage" / "subject"), load_sequence(SCENES / "subjects" / "tiny")
    assert ours.num_frames == 3 and ours.fps == 30 and list(ours.frame_labels) == ["0000", "0001", "0002"]
    for t in range(3):  # Mitsuba merges the OBJ's vertices that share a position and a UV: compare as point sets
        apart = np.linalg.norm(ours.vertices[t][:, None] - truth.vertices[t][None], axis=-1)
        assert apart.min(axis=1).max() < 1e-6 and apart.min(axis=0).max() < 1e-6
    code, lines = run(["relight", tmp_path / "stage" / "scene.xml", "--olat", "1", "--frames", "0:3", "--out", tmp_path / "r"], capsys)
    assert code == 0, lines
    first, last = (read_exr(tmp_path / "r" / "olat001" / "front" / f"frame_{t:04d}.exr") for t in (0, 2))
    assert not np.allclose(first, last)  # the body moved


def test_what_moves_besides_the_subject_is_refused_naming_the_frame(plugins, tmp_path, capsys):
    path = _moving_scene(
        tmp_path / "user", sensors=SENSORS.replace('up="0, 1, 0"/></transform>', 'up="0, 1, 0"/><translate x="$frame"/></transform>', 1)
    )
    assert_refused(
        ["from-scene", path, "--frames", "0:3", "--out", tmp_path / "a"], capsys, "frame=0001", "sensor 'front'", "rig stays fixed"
    )
    path = _moving_scene(tmp_path / "user2")
    obj = tmp_path / "user2" / "body_0002.obj"
    obj.write_text("\n".join(line for line in obj.read_text().splitlines()[:-1]) + "\n")  # a triangle fewer
    assert_refused(["from-scene", path, "--frames", "0:3", "--out", tmp_path / "b"], capsys, "frame=0002", "faces differ")
    assert run(["from-scene", path, "--frames", "0:2", "--out", tmp_path / "b"], capsys)[0] == 0  # a whole stage, then
    (tmp_path / "user2" / "body_0001.obj").unlink()
    assert_refused(["from-scene", path, "--frames", "0:2", "--out", tmp_path / "b"], capsys, "frame=0001", "body_0001.obj", "not found")
    assert not (tmp_path / "b" / "scene.xml").exists()  # the same run again, stopped at a frame: no stage
    for argv, needle in (
        (["--frames", "3:1"], "A < B"),
        (["--frames", "0000,0000"], "twice"),
        (["--frame-parameter", "step"], "takes effect with --frames"),
        (["--fps", "12"], "takes effect with --frames"),
        (["--frames", "0:2", "-D", "frame=0001"], "--frames sets per frame"),
        (["--frames", "0:2", "--frame-parameter", "nothing"], "nothing"),
    ):
        assert_refused(["from-scene", path, *argv, "--out", tmp_path / "c"], capsys, needle, out=tmp_path / "c")


def test_gra_mis_own_scene_round_trips_with_its_vertex_colours(plugins, tmp_path, capsys):
    """A scene gra-mi wrote (LEDs off, the subject's colours a vertex attribute) made a stage again relights as the
    original does: the colours baked on the surface (not at a UV alone, where a vertex attribute reads 0)."""
    scene = SCENES / "tiny_lightstage.xml"
    assert run(["from-scene", scene, "--out", tmp_path / "stage"], capsys)[0] == 0
    assert "every LED is off" in (tmp_path / "stage" / "notes.md").read_text()
    images = {}
    for name, argv in (("original", [scene]), ("stage", [tmp_path / "stage" / "scene.xml", "--albedo", tmp_path / "stage" / "albedo.exr"])):
        code, lines = run(
            ["relight", *argv, "--olat", "5", "--cameras", "cam01", "--uv-resolution", "256", "--out", tmp_path / f"r_{name}"], capsys
        )
        assert code == 0, lines
        images[name] = read_exr(tmp_path / f"r_{name}" / "olat005" / "cam01" / "frame_0000.exr")
    # the rig's LEDs give 4 W/sr at full drive; a scene whose LEDs are all off says no intensity: the stage's give 1
    original, stage = images["original"], images["stage"] * [4, 4, 4, 1]
    assert original[..., :3].max() > 0 and np.abs(stage - original).max() < 1e-3 * original[..., :3].max()


def _photograph(scene_path: Path, folder: Path, lighting: list[dict], intensities: np.ndarray, moving: bool = False) -> None:
    """Photographs of the user's stage as a capture takes them: each lighting entry rendered by Mitsuba's ``direct``
    from every sensor, its LEDs (the scene's point emitters, in order) at the entry's drive × their intensities; a
    ``moving`` subject at the mesh frame of the entry's number (the scene's ``frame``)."""
    import mitsuba as mi

    from gra_mi.capture.mitsuba_capture import write_photographs

    for entry in lighting:
        scene = mi.load_file(str(scene_path), parallel=False, **({"frame": f"{entry['frame']:04d}"} if moving else {}))
        drive = np.full(len(intensities), entry["uniform"]) if "uniform" in entry else np.eye(len(intensities))[entry["led"]]
        write_photographs(scene, folder, entry["frame"], drive[:, None] * intensities, mi.load_dict({"type": "direct"}), 64)


def test_photographs_on_a_stage_written_as_a_mitsuba_scene_import(plugins, tmp_path, capsys):
    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.scene_stage import stage_from_scene
    from gra_mi.stage.lightstage import load_calibration

    folder = tmp_path / "capture"
    path = write_user_scene(folder, sensors=RGBA_SENSORS, lights=_leds(off_every=0))
    path.rename(folder / "scene.xml")
    stage = stage_from_scene(folder / "scene.xml")
    lighting = (
        [{"frame": 0, "uniform": 1.0}] + [{"frame": k, "led": k} for k in (1, 2, 3, 4, 6)] + [{"frame": 7, "split": "test", "led": 7}]
    )
    _photograph(folder / "scene.xml", folder, lighting, stage.intensities)
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": lighting}))
    argv = ["import", "mitsuba", folder, "--lighting", tmp_path / "lighting.json", "--eval-cameras", "tele", "--uv-resolution", "64"]
    code, lines = run([*argv, "--out", tmp_path / "cap"], capsys)
    assert code == 0, lines
    report = json.loads((tmp_path / "cap" / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.95 for c in report["cameras"]), report["cameras"]
    capture = Capture.load(tmp_path / "cap")
    assert capture.train_cameras == ["front", "side"] and capture.eval_cameras == ["tele"] and len(capture.frames) == 7
    imported = load_calibration(tmp_path / "cap" / "rig" / "calibration.json")
    # the LEDs' intensities differ in the scene: they come in as its stated gains; the rig is the scene's up to a rigid move
    np.testing.assert_allclose(imported.gains, stage.intensities / stage.intensities.mean(), rtol=1e-5)
    for p, q in zip(imported.cameras, stage.stage.cameras, strict=True):
        assert (p.width, p.height) == (q.width, q.height) and p.fx == pytest.approx(q.fx, rel=1e-6)
        assert np.linalg.norm(p.position - imported.led_positions[0]) == pytest.approx(
            np.linalg.norm(q.position - stage.stage.led_positions[0]), abs=1e-5
        )
    # The scene's LED intensities are the stage's, so the photographs' units are the fit's: the fitted albedo comes out
    # at the truth's scale, the right way up in U and V (a check of conventions on renders of gra-mi's own BRDF, not
    # of recovery: tests/test_fit.py measures that against path-traced truth).
    from gra_mi.core.io import read_exr_channels

    assert run(["fit", tmp_path / "cap", "--out", tmp_path / "fit"], capsys)[0] == 0
    fitted, truth = read_exr(tmp_path / "fit" / "albedo.exr")[..., :3], read_exr(folder / "albedo_in.exr")[..., :3]
    seen = read_exr_channels(tmp_path / "fit" / "confidence.exr")["views"] > 0
    assert seen.sum() > 500
    np.testing.assert_allclose(fitted[seen].mean(axis=0) / truth[seen].mean(axis=0), 1.0, atol=0.08)
    for channel in (0, 1):  # R follows U, G follows V
        assert np.corrcoef(fitted[..., channel][seen], truth[..., channel][seen])[0, 1] > 0.4


def test_broken_captures_on_a_mitsuba_stage_stop_with_one_line(plugins, tmp_path, capsys):
    folder = tmp_path / "capture"
    write_user_scene(folder, lights=_leds(off_every=0)).rename(folder / "scene.xml")
    lighting = tmp_path / "lighting.json"
    lighting.write_text(json.dumps({"frames": [{"frame": 0, "uniform": 1.0}, {"frame": 1, "led": 3}]}))
    base = ["import", "mitsuba", folder, "--lighting", lighting, "--out", tmp_path / "cap"]
    assert_refused(base, capsys, "images/front", "no images", out=tmp_path / "cap")
    for name, (w, h) in (("front", (96, 72)), ("side", (70, 60)), ("tele", (60, 60))):  # tele's film is 48 × 64
        for frame in (0, 1):
            write_exr(folder / "images" / name / f"{frame:06d}.exr", np.zeros((h, w, 4), np.float32))
    assert_refused(base, capsys, "sensor 'tele'", "another aspect ratio", out=tmp_path / "cap")
    for frame in (0, 1):  # twice the film's size: the same camera, scaled
        write_exr(folder / "images" / "tele" / f"{frame:06d}.exr", np.zeros((128, 96, 4), np.float32))
    lighting.write_text(json.dumps({"frames": [{"frame": 0, "uniform": 1.0}, {"frame": 1, "led": 24}]}))
    assert_refused(base, capsys, "LED 24 out of range: the stage has 24 LEDs", out=tmp_path / "cap")
    lighting.write_text(json.dumps({"frames": [{"frame": 0, "uniform": 1.0}, {"frame": 1, "led": 3, "mesh_frame": 1}]}))
    assert_refused(base, capsys, "2 mesh frames", "no parameter 'frame'", out=tmp_path / "cap")
    assert_refused([*base, "--mesh", folder / "body.obj"], capsys, "--mesh", "transforms option", out=tmp_path / "cap")
    assert_refused(base[:3] + base[5:], capsys, "--lighting", out=tmp_path / "cap")
    lighting.write_text(json.dumps({"frames": [{"frame": 0, "uniform": 1.0}, {"frame": 1, "led": 3}]}))
    text = (folder / "scene.xml").read_text()
    (folder / "scene.xml").write_text(re.sub(r'<rgb name="intensity" value="[^"]*"/>', '<rgb name="intensity" value="0"/>', text, count=1))
    assert_refused(base, capsys, "LED 0's gain", out=tmp_path / "cap")


def test_photographs_of_a_moving_subject_on_a_mitsuba_stage_import(plugins, tmp_path, capsys):
    from gra_mi.capture.scene_stage import stage_from_scene
    from gra_mi.subject.sequence import load_sequence

    folder = tmp_path / "capture"
    _moving_scene(folder, sensors=RGBA_SENSORS, lights=_leds(off_every=0)).rename(folder / "scene.xml")
    stage = stage_from_scene(folder / "scene.xml")
    lighting = [{"frame": 0, "uniform": 1.0}, {"frame": 1, "led": 3}, {"frame": 2, "uniform": 0.5, "split": "test"}]
    _photograph(folder / "scene.xml", folder, lighting, stage.intensities, moving=True)
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": lighting}))
    argv = ["import", "mitsuba", folder, "--lighting", tmp_path / "lighting.json", "--eval-cameras", "tele", "--out", tmp_path / "cap"]
    code, lines = run(argv, capsys)
    assert code == 0, lines
    report = json.loads((tmp_path / "cap" / "import_report.json").read_text())
    assert all(c["mask_iou"] >= 0.95 for c in report["cameras"]), report["cameras"]
    imported, truth = load_sequence(tmp_path / "cap" / "subject"), load_sequence(SCENES / "subjects" / "tiny")
    assert imported.num_frames == 3
    for t in (1, 2):  # the import's rigid move aside, each frame moved as the truth's did
        moved, true_move = imported.vertices[t] - imported.vertices[0], truth.vertices[t] - truth.vertices[0]
        assert np.linalg.norm(moved, axis=1).max() == pytest.approx(np.linalg.norm(true_move, axis=1).max(), rel=1e-3)
    # Without alpha, a render's masks are its pixels that are not black: the reconstruction filter's soft edge makes
    # them too big, which the import names instead of blaming the calibration
    for path in (folder / "images" / "tele").iterdir():
        write_exr(path, read_exr(path)[..., :3])
    assert_refused([*argv[:-1], tmp_path / "cap2"], capsys, "camera tele", "the mesh lies inside the mask", "the calibration fits")


def test_a_moving_stage_whose_rig_moves_with_the_frame_is_refused(plugins, tmp_path, capsys):
    folder = tmp_path / "capture"
    sensors = RGBA_SENSORS.replace('up="0, 1, 0"/></transform>', 'up="0, 1, 0"/><translate x="$frame"/></transform>', 1)
    _moving_scene(folder, sensors=sensors, lights=_leds(off_every=0)).rename(folder / "scene.xml")
    for name, (w, h) in (("front", (96, 72)), ("side", (70, 60)), ("tele", (48, 64))):
        for frame in (0, 1):
            write_exr(folder / "images" / name / f"{frame:06d}.exr", np.ones((h, w, 4), np.float32))
    lighting = tmp_path / "lighting.json"
    lighting.write_text(json.dumps({"frames": [{"frame": 0, "uniform": 1.0}, {"frame": 1, "led": 3}]}))
    argv = ["import", "mitsuba", folder, "--lighting", lighting, "--out", tmp_path / "cap"]
    assert_refused(argv, capsys, "frame=0001", "sensor 'front'", "rig stays fixed", out=tmp_path / "cap")


def test_point_lights_set_are_what_mitsuba_emits(plugins):
    """set_point_lights, which the photographs of a stage go through, read back through the emitters' own
    sample_direction (point_lights); the count is checked."""
    import mitsuba as mi

    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.render.scene_lights import point_lights, set_point_lights

    scene = mi.load_file(str(SCENES / "user_stage" / "scene.xml"), parallel=False)
    emitted = np.zeros((40, 3))
    emitted[7] = [3.0, 2.0, 1.0]
    set_point_lights(scene, emitted)
    np.testing.assert_allclose(point_lights(list(scene.emitters()))[1], emitted, atol=1e-6)
    with pytest.raises(GraMiParameterError, match="one per point emitter"):
        set_point_lights(scene, emitted[:39])


def test_an_imported_stage_shades_with_the_scenes_normals(plugins, tmp_path, capsys):
    """A coarse mesh without normals (the shipped stage's body: 282 vertices): Mitsuba computes its vertex normals
    (angle-weighted), gra-mi's own are area-weighted, up to 10° apart here. The import keeps Mitsuba's, so a rim light
    (the LEDs behind, grazing what the front camera sees) relit from the import matches the photograph; with gra-mi's
    normals it came out 17 % dark."""
    import shutil

    import mitsuba as mi

    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.mitsuba_capture import write_photographs
    from gra_mi.capture.scene_stage import stage_from_scene
    from gra_mi.render.relighter import Relighter

    folder = tmp_path / "stage"
    shutil.copytree(SCENES / "user_stage", folder)
    text = (folder / "scene.xml").read_text()  # films at 2x: a rim light's pixels are not all at the silhouette
    (folder / "scene.xml").write_text(text.replace('value="160"/>', 'value="320"/>').replace('value="120"/>', 'value="240"/>'))
    stage = stage_from_scene(folder / "scene.xml")
    behind = np.where((stage.stage.led_positions - stage.stage.center)[:, 2] < -0.3, 1.0, 0.0)
    (tmp_path / "rim.json").write_text(json.dumps({"intensities": (behind * stage.intensities.mean()).tolist()}))
    lighting = [{"frame": 0, "uniform": 1.0}, {"frame": 1, "split": "test", "pattern": "rim.json"}]
    (tmp_path / "lighting.json").write_text(json.dumps({"frames": lighting}))
    scene = mi.load_file(str(folder / "scene.xml"), parallel=False)
    for number, emitted in enumerate((stage.intensities, behind[:, None] * stage.intensities)):
        write_photographs(scene, folder, number, emitted, mi.load_dict({"type": "direct"}), 256)
    argv = ["import", "mitsuba", folder, "--lighting", tmp_path / "lighting.json", "--eval-cameras", "left", "--uv-resolution", "128"]
    assert run([*argv, "--out", tmp_path / "cap"], capsys)[0] == 0
    capture = Capture.load(tmp_path / "cap")
    ls = capture.load_scene()
    mitsubas = np.array(mi.traverse(scene.shapes()[0])["vertex_normals"]).reshape(-1, 3)
    np.testing.assert_allclose(ls.sequence.normals[0], mitsubas, atol=1e-5)  # the capture's frame is the scene's, up to a shift
    entry = capture.frames[1]
    relit = Relighter(ls, albedo=stage.maps["albedo"], roughness=stage.maps["roughness"]).render(
        0, "front", capture.lighting(ls.stage, entry)
    )
    photograph = read_exr(capture.image_path("front", entry.frame))
    covered = (photograph[..., 3] > 0.999) & (relit.image[..., 3] > 0.5)
    assert relit.image[..., :3][covered].sum() / photograph[..., :3][covered].sum() == pytest.approx(1.0, abs=0.03)
