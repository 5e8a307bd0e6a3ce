"""The doors of issue 51, families 1, 2 and 6 (lightings): a name read from an input never becomes a path that leads
out of ``--out``, an output folder never is, holds or lies inside an input, and two lightings with one name are
refused naming both. Each case asserts exit code 2, the file and field named, and that nothing outside ``--out``
and nothing inside the inputs changed."""

from __future__ import annotations

import hashlib
import json
import struct
from pathlib import Path

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.guard import check_apart, path_component, writing_into
from gra_mi.core.io import atomic_write_text, write_exr

from .conftest import SCENES
from .test_bad_input import assert_refused

HOSTILE = ["../../../X", "/abs/X", "a/b", "a\\b", "..", ".", "", "   ", "a\x00b", "line\nbreak", "x" * 300]


def snapshot(*folders: Path) -> dict[str, str]:
    """Every file under the folders, by content: what must not change."""
    found = {}
    for folder in folders:
        for p in sorted(Path(folder).rglob("*")):
            if p.is_file() and not p.name.startswith(".gra-mi.lock"):
                found[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return found


# --------------------------------------------------------------------------------------------------------------
# The mechanism
# --------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", HOSTILE + [5, None])
def test_a_hostile_name_is_refused_naming_file_and_field(name):
    with pytest.raises(GraMiInputError) as err:
        path_component(name, "calibration.json", "cameras[0].name")
    assert "calibration.json" in str(err.value) and "cameras[0].name" in str(err.value)


@pytest.mark.parametrize("name", ["cam00", "sky.v2", "Kamera-ü", "olat003", "a b"])
def test_plain_names_pass(name):
    assert path_component(name, "x.json", "name") == name


def test_writers_refuse_files_outside_the_output_folder(tmp_path):
    out, outside = tmp_path / "out", tmp_path / "elsewhere"
    out.mkdir()
    (out / "link").symlink_to(tmp_path)  # a symlink inside --out that leads out of it
    with writing_into([out]):
        atomic_write_text(out / "ok.txt", "fine")
        for target in (outside / "x.txt", out / ".." / "x.txt", out / "link" / "x.txt"):
            with pytest.raises(GraMiInputError, match="outside the output folder"):
                atomic_write_text(target, "no")
    assert (out / "ok.txt").is_file() and not (tmp_path / "x.txt").exists() and not outside.exists()
    atomic_write_text(outside / "x.txt", "a library caller outside a command writes where it likes")


@pytest.mark.parametrize("relation", ["is", "holds", "lies inside"])
def test_an_output_folder_overlapping_an_input_is_refused(tmp_path, relation):
    capture = tmp_path / "capture"
    capture.mkdir()
    out = {"is": capture, "holds": tmp_path, "lies inside": capture / "sub"}[relation]
    with pytest.raises(GraMiInputError, match=relation):
        check_apart({"--out": out}, {"capture": capture})
    check_apart({"--out": tmp_path / "elsewhere"}, {"capture": capture})


# --------------------------------------------------------------------------------------------------------------
# Family 1: names from input files (sensor ids, calibration camera names)
# --------------------------------------------------------------------------------------------------------------


def plain_scene(folder: Path, sensor_ids: list[str | None]) -> Path:
    """A Mitsuba scene with a textured floor (its texture beside it) and one sensor per id (None: no id)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_exr(folder / "cam.exr", np.full((4, 4, 3), 0.5, np.float32))  # a texture named like a sensor's output
    sensors = "".join(  # at distinct distances: Mitsuba merges identical sensors, ids and all
        f'<sensor type="perspective"{"" if i is None else f" id={json.dumps(i)}"}><float name="fov" value="40"/>'
        f'<transform name="to_world"><lookat origin="0, 0, {3 + k}" target="0, 0, 0" up="0, 1, 0"/></transform>'
        '<film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/></film></sensor>'
        for k, i in enumerate(sensor_ids)
    )
    xml = (
        '<scene version="3.0.0"><integrator type="direct"/>' + sensors + '<shape type="rectangle"><bsdf type="diffuse">'
        '<texture type="bitmap" name="reflectance"><string name="filename" value="cam.exr"/></texture></bsdf></shape>'
        '<emitter type="constant"/></scene>'
    )
    (folder / "scene.xml").write_text(xml)
    return folder / "scene.xml"


@pytest.mark.parametrize("sensor_id", ["../../../X", "/tmp/gra-mi-hostile/X", "a/b"])
def test_render_refuses_a_sensor_id_that_is_a_path(tmp_path, capsys, llvm_variant, sensor_id):
    scene = plain_scene(tmp_path / "scene", [sensor_id])
    out = tmp_path / "deep" / "er" / "out"
    before = snapshot(tmp_path)
    assert_refused(["render", scene, "--out", out, "--spp", "1"], capsys, str(scene), "sensor 0 id")
    assert snapshot(tmp_path) == before
    assert not Path("/tmp/gra-mi-hostile").exists()


def test_render_refuses_two_sensors_with_one_name(tmp_path, capsys, llvm_variant):
    scene = plain_scene(tmp_path / "scene", [None, "sensor0"])  # the unnamed one is called sensor0 too
    assert_refused(["render", scene, "--out", tmp_path / "out", "--spp", "1"], capsys, "sensors 0 and 1", "sensor0")


def test_render_into_the_scenes_own_folder_is_refused(tmp_path, capsys, llvm_variant):
    # Sensor "cam" would write cam.exr over the scene's own texture.
    scene = plain_scene(tmp_path / "scene", ["cam"])
    before = snapshot(tmp_path)
    for out in (scene.parent, tmp_path):
        assert_refused(["render", scene, "--out", out, "--spp", "1"], capsys, "scene")
    assert snapshot(tmp_path) == before
    # A folder beside the scene's files, holding none of them, is where renders usually go.
    assert main_code(["render", scene, "--out", scene.parent / "renders", "--spp", "1"]) == 0
    texture = scene.parent / "cam.exr"
    assert (scene.parent / "renders" / "cam.exr").is_file()
    assert hashlib.sha256(texture.read_bytes()).hexdigest() == before[str(texture)]


def main_code(argv) -> int:
    from gra_mi.cli import main

    return main([str(a) for a in argv])


@pytest.mark.parametrize("name", ["../../../X", "/abs/X", ".."])
def test_a_calibration_camera_named_like_a_path_is_refused(tmp_path, capsys, llvm_variant, name):
    calibration = json.loads((SCENES / "rigs" / "tiny" / "calibration.json").read_text())
    calibration["cameras"][1]["name"] = name
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps(calibration))
    before = snapshot(tmp_path)
    assert_refused(
        ["rig", "--out", tmp_path / "rig", "--from-calibration", path], capsys, str(path), "cameras[1].name", out=tmp_path / "rig"
    )
    assert snapshot(tmp_path) == before


# --------------------------------------------------------------------------------------------------------------
# Family 2: one name, one thing (lightings of one kind or two)
# --------------------------------------------------------------------------------------------------------------


def _pattern(path: Path, leds: int = 64) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"intensities": np.full((leds, 3), 0.1).tolist()}))
    return path


def _envmap(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_exr(path, np.full((8, 16, 3), 0.3, np.float32))
    return path


@pytest.mark.parametrize("case", ["two envmaps, two folders", "envmap and pattern", "envmap and OLAT", "two patterns"])
def test_relight_refuses_two_lightings_with_one_name(tmp_path, capsys, llvm_variant, case):
    lightings = {
        "two envmaps, two folders": ["--envmap", _envmap(tmp_path / "env" / "sky.exr"), "--envmap", _envmap(tmp_path / "env2" / "sky.exr")],
        "envmap and pattern": ["--envmap", _envmap(tmp_path / "key.exr"), "--pattern", _pattern(tmp_path / "key.json")],
        "envmap and OLAT": ["--envmap", _envmap(tmp_path / "olat003.exr"), "--olat", "3"],
        "two patterns": ["--pattern", _pattern(tmp_path / "a" / "p.json"), "--pattern", _pattern(tmp_path / "b" / "p.json")],
    }[case]
    out = tmp_path / "out"
    line = assert_refused(["relight", SCENES / "tiny_lightstage.xml", *lightings, "--out", out], capsys, "both named", out=out)
    assert "rename one" in line


def test_relight_field_refuses_two_envmaps_with_one_stem_and_an_out_inside_its_capture(inputs, tmp_path, capsys, llvm_variant):
    cap = inputs["cap"]
    before = snapshot(cap)
    for out in (cap, cap / "relit"):
        assert_refused(["relight-field", cap, "--olat", "3", "--out", out], capsys, "capture")
    maps = ["--envmap", _envmap(tmp_path / "a" / "sky.exr"), "--envmap", _envmap(tmp_path / "b" / "sky.exr")]
    assert_refused(["relight-field", cap, *maps, "--out", tmp_path / "out"], capsys, "both named", out=tmp_path / "out")
    assert snapshot(cap) == before


def test_fit_refuses_an_output_inside_its_capture(inputs, capsys, llvm_variant):
    cap = inputs["cap"]
    before = snapshot(cap)
    assert_refused(["fit", cap, "--out", cap / "fit"], capsys, "lies inside", "capture")
    assert snapshot(cap) == before


@pytest.fixture
def inputs(path_traced_fit):
    return {"cap": path_traced_fit / "cap", "fit": path_traced_fit / "fit"}


# --------------------------------------------------------------------------------------------------------------
# Family 7: light paths — a clear error or a correct finite result, never a render that disagrees with its
# conditioning
# --------------------------------------------------------------------------------------------------------------


def _light_path(path: Path, radius: float = 0.03, intensity=2.0, position=(0.6, 1.2, 0.4)) -> Path:
    light = {
        "name": "key",
        "type": "point",
        "radius": radius,
        "intensity": intensity,
        "keyframes": [{"frame": 0, "position": list(position)}],
    }
    path.write_text(json.dumps({"lights": [light]}))
    return path


def test_a_light_whose_sphere_reaches_into_the_subject_is_refused(tmp_path, capsys, llvm_variant):
    path = _light_path(tmp_path / "big.json", radius=5.0)
    out = tmp_path / "out"
    assert_refused(
        ["relight", SCENES / "tiny_lightstage.xml", "--lights", path, "--frames", "0", "--out", out],
        capsys,
        "big.json",
        "reaches into the subject",
        out=out,
    )


@pytest.mark.parametrize("intensity", [1e39, [1, 1, 1e39], -1.0])
def test_a_light_intensity_beyond_float32_is_refused_by_file_and_field(tmp_path, intensity):
    from gra_mi.render.light_path import LightPath

    with pytest.raises(GraMiInputError, match=r"lights\[0\]\.keyframes\[0\]\.intensity"):
        LightPath.load(_light_path(tmp_path / "hot.json", intensity=intensity))


def test_point_light_intensity_option_is_bounded(tmp_path, capsys, llvm_variant):
    out = tmp_path / "out"
    argv = ["relight", SCENES / "tiny_lightstage.xml", "--point-light", "0.6,1.2,0.4", "--point-light-intensity", "1e39", "--out", out]
    assert_refused(argv, capsys, "--point-light-intensity", out=out)


def test_a_light_at_an_led_gives_a_finite_conditioning(llvm_variant):
    from gra_mi.render.point_light import PointLight, conditioning_envmap, conditioning_pattern
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(SCENES / "tiny_lightstage.xml")
    for radius in (0.0, 0.03):
        light = PointLight(ls.stage.led_positions[5], np.full(3, 2.0), radius)
        pattern = conditioning_pattern(ls.stage, ls.scene, light)
        assert np.isfinite(pattern).all() and pattern[5].max() > 0
        assert np.isfinite(conditioning_envmap(ls.stage, pattern)).all()


# --------------------------------------------------------------------------------------------------------------
# Family 8: sizes checked against memory before any output is claimed
# --------------------------------------------------------------------------------------------------------------


def test_sizes_beyond_memory_are_refused_before_anything_is_written(inputs, tmp_path, capsys, llvm_variant):
    cap, fit = inputs["cap"], inputs["fit"]
    out = tmp_path / "out"
    assert_refused(["fit", cap, "--levels", "16,100000", "--out", out], capsys, "--levels", "GiB", out=out)
    assert_refused(
        ["train-relightnet", cap, "--fit", fit, "--synthesized-lightings", "1000000000", "--out", out],
        capsys,
        "--synthesized-lightings",
        "GiB",
        out=out,
    )
    assert_refused(
        ["eval", "--capture", cap, "--fit", fit, "--library-envmaps", "100000000", "--out", out],
        capsys,
        "--library-envmaps",
        "GiB",
        out=out,
    )
    assert_refused(["envmaps", "--height", "1000000", "--out", out], capsys, "--height", "GiB", out=out)


def test_a_film_too_large_for_memory_is_refused(tmp_path, capsys, llvm_variant):
    scene = plain_scene(tmp_path / "scene", ["cam"])
    scene.write_text(
        scene.read_text()
        .replace('name="width" value="8"', 'name="width" value="100000"')
        .replace('name="height" value="8"', 'name="height" value="100000"')
    )
    out = tmp_path / "out"
    assert_refused(["render", scene, "--out", out, "--spp", "1"], capsys, "sensor 0 film", "100000 × 100000", out=out)


# --------------------------------------------------------------------------------------------------------------
# Family 10: shards say so
# --------------------------------------------------------------------------------------------------------------


def test_a_shard_taken_from_a_launcher_says_so(capsys):
    from gra_mi.core import shard as shards

    shards._ANNOUNCED.clear()
    env = {"SLURM_ARRAY_TASK_ID": "2", "SLURM_ARRAY_TASK_COUNT": "3", "SLURM_ARRAY_TASK_MIN": "1"}
    assert str(shards.resolve_shard(None, env)) == "1/3"
    assert "shard 1/3 from the launcher" in capsys.readouterr().err
    shards.resolve_shard(None, env)
    assert capsys.readouterr().err == ""  # once per process


def test_relight_refuses_a_second_shard_count_in_one_folder(tmp_path, capsys, llvm_variant):
    from gra_mi.cli import main

    out = tmp_path / "out"
    base = ["relight", str(SCENES / "tiny_lightstage.xml"), "--olat", "0", "--frames", "0", "--out", str(out)]
    assert main([*base, "--shard", "0/2"]) == 0
    assert_refused([*base, "--shard", "0/3"], capsys, "2 shards", "--shard I/2")
    assert main([*base, "--shard", "1/2"]) == 0  # the same count resumes


# --------------------------------------------------------------------------------------------------------------
# Family 11 (build list 10): the door LEDs leave the rig with their OLATs
# --------------------------------------------------------------------------------------------------------------


def _humanolat_source(leds: int):
    from gra_mi.capture.source import Source

    order = np.random.default_rng(0).permutation(leds)
    positions = np.random.default_rng(1).normal(size=(leds, 3))
    return Source(Path("subject"), "humanolat", Path("cameras.calib"), [], [], [], [], 0.001, positions, [], [], order=order)


def test_the_door_leds_are_left_out_of_the_rig_by_default(tmp_path):
    from gra_mi.capture.humanolat import DOOR_LEDS, HumanolatOptions, humanolat_frames

    source = _humanolat_source(331)
    original = source.leds.copy()
    plan, left_out = humanolat_frames(source, HumanolatOptions(test_olat_every=1000))
    assert len(source.leds) == 331 - len(DOOR_LEDS) and set(DOOR_LEDS) <= set(left_out)
    assert all(drive != "white" for _, _, drive in plan)  # the white frame lit the door too: not imported
    kept = [i for i in range(331) if i not in DOOR_LEDS]
    for _, entry, drive in plan:  # each OLAT's LED, renumbered in the rig, is where the source put it
        assert entry.pattern == f"patterns/olat_{drive:03d}.json"
        np.testing.assert_array_equal(source.leds[drive], original[kept[drive]])
    # a gains file names every LED of the stage, the door's too: each rig LED gets its own
    gains = np.random.default_rng(2).uniform(0.5, 1.5, (331, 3))
    path = tmp_path / "gains.txt"
    path.write_text("".join(f"{r} {g} {b}\n" for r, g, b in gains))
    picked = source.led_gains(path)
    np.testing.assert_allclose(picked, gains[kept] / gains[kept].mean())
    source = _humanolat_source(331)
    plan, left_out = humanolat_frames(source, HumanolatOptions(keep_door_leds=True))
    assert len(source.leds) == 331 and not left_out and plan[0][2] == "white"
    np.testing.assert_allclose(source.led_gains(path), gains / gains.mean())


def test_an_output_file_may_have_siblings_of_its_own_stem_only(tmp_path):
    # `edit-texture --out edited.exr` writes edited.png beside it; nothing else beside it.
    out = tmp_path / "edited.exr"
    with writing_into([out]):
        atomic_write_text(out, "exr")
        atomic_write_text(tmp_path / "edited.png", "preview")
        for target in (tmp_path / "other.png", tmp_path / "edited_x" / "y.png", tmp_path / "editedx.png"):
            with pytest.raises(GraMiInputError, match="outside the output folder"):
                atomic_write_text(target, "no")


@pytest.mark.parametrize("name", ["edited.png", "edited", "folder"])
@pytest.mark.parametrize(
    "command, expected",
    [
        (["edit-texture", "--albedo", "{albedo}", "--image", "{albedo}"], ".exr"),
        (["scene", "--rig", "{root}", "--subject", "{root}"], ".xml"),
        (["export", "--subject", "{root}", "--albedo", "{albedo}", "--roughness", "{albedo}"], ".glb"),
        (["refiner-prompt", "--pipeline", "{root}"], ".safetensors"),
    ],
)
def test_an_output_file_named_as_another_format_or_a_folder_is_refused(tmp_path, capsys, command, expected, name):
    """An EXR written as ``edited.png`` was overwritten by its own PNG preview (the user kept an 8-bit albedo and was
    told to relight with it); one named ``edited`` was written, then its preview refused. Every command whose --out is
    one file refuses another suffix and a folder, by the option, before reading anything."""
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    write_exr(inputs / "albedo.exr", np.full((8, 8, 3), 0.5, np.float32))
    (tmp_path / "folder").mkdir()
    argv = [a.format(albedo=inputs / "albedo.exr", root=inputs) for a in command] + ["--out", str(tmp_path / name)]
    before = snapshot(tmp_path)
    needle = "is a folder" if name == "folder" else "give a file name ending"
    assert_refused(argv, capsys, "--out", needle, expected)
    assert snapshot(tmp_path) == before and sorted(p.name for p in tmp_path.iterdir()) == ["folder", "inputs"]


def test_a_binary_file_under_a_text_files_name_is_refused_by_name(tmp_path):
    """A source's text files (LED positions, the firing order, a mesh, LED gains, OpenCV YAML, COLMAP's cameras.txt and
    images.txt, camera places) that hold an image or an archive, or are not there, or are folders: one line naming the
    file, not a traceback."""
    from gra_mi.capture.alignment import read_places
    from gra_mi.capture.colmap import _cameras_txt, _images_txt
    from gra_mi.capture.easymocap import read_opencv_yaml
    from gra_mi.capture.humanolat import read_spiral
    from gra_mi.capture.source_files import read_led_gains, read_obj, read_points

    binary = tmp_path / "photo.bin"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\x00\x80\xff\xfe" * 16)
    readers = [read_points, read_obj, lambda p: read_spiral(p, 4), lambda p: read_led_gains(p, [0, 1, 2, 3]), read_opencv_yaml]
    readers += [_cameras_txt, _images_txt, read_places]  # (COLMAP's text model, --align-cameras)
    for read in readers:
        with pytest.raises(GraMiInputError, match="photo.bin: not a text file"):
            read(binary)
        with pytest.raises(GraMiInputError, match="nothing.txt: missing: expected"):
            read(tmp_path / "nothing.txt")
        with pytest.raises(GraMiInputError, match=f"{tmp_path.name}: a folder: expected"):
            read(tmp_path)


def _mutations(text: bytes, count: int, seed: int):
    """``count`` damaged copies of a file: bytes replaced, removed, repeated, cut short, numbers made extreme."""
    rng = np.random.default_rng(seed)
    tokens = [b"nan", b"inf", b"-inf", b"1e999", b"-1", b"0", b"99999999999999999999", b"\x00", b"\xff\xfe", b" ", b"\n", b"#", b"x"]
    for _ in range(count):
        data = bytearray(text)
        for _ in range(int(rng.integers(1, 4))):
            at = int(rng.integers(0, len(data) + 1))
            kind = int(rng.integers(0, 5))
            if kind == 0 and data:
                data[min(at, len(data) - 1)] = int(rng.integers(0, 256))
            elif kind == 1:
                del data[at : at + int(rng.integers(1, 12))]
            elif kind == 2:
                data[at:at] = tokens[int(rng.integers(0, len(tokens)))]
            elif kind == 3:
                data[at:at] = data[max(0, at - 20) : at]
            else:
                del data[at:]
        yield bytes(data)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # an overflow on the way is a value silently wrong: a failure too
def test_damaged_source_files_fail_only_by_name(tmp_path):
    """Every text file a capture's source hands gra-mi (LED positions, the firing order, LED gains, HumanOLAT's
    calibration, EasyMocap's YAML, COLMAP's cameras.txt and images.txt, a places file, an OBJ, a lighting file, a
    calibration.json, transforms.json's records) and COLMAP's binary model, damaged 300 ways each (bytes
    replaced, cut, repeated, NaN, 1e999, NUL): each is read, or refused with a GraMiInputError naming it; never another
    exception (a traceback)."""
    from gra_mi.capture.alignment import read_places
    from gra_mi.capture.colmap import _cameras_bin, _cameras_txt, _images_bin, _images_txt
    from gra_mi.capture.easymocap import lighting_frames, read_opencv_yaml
    from gra_mi.capture.humanolat import read_calib, read_spiral
    from gra_mi.capture.source_files import read_led_gains, read_obj, read_points
    from gra_mi.stage.lightstage import default_lightstage, lightstage_to_dict, load_calibration

    matrix = "!!opencv-matrix\n   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 160., 0., 500., 120., 0., 0., 1. ]\n"
    samples = {
        "leds.pc": (read_points, "v 1.0 2.0 3.0\nv -1.5 0.5 2.25\nv 0 0 1\n"),
        "spiral.txt": (lambda p: read_spiral(p, 4), "3\n1\n4\n2\n"),
        "gains.txt": (lambda p: read_led_gains(p, [0, 1, 2]), "1.0\n0.5 0.6 0.7\n# LED 2\n0.9\n"),
        "cameras.calib": (
            read_calib,
            "name Cam01\ndistortionModel opencv\ndistortion 0 0 0 0 0\nfocalLength 50\npixelAspect 1\n"
            "extrinsic\n1 0 0 0\n0 1 0 0\n0 0 1 2000\nintrinsic\n1.2 0 0.5\n0 1.2 0.4\n0 0 1\n",
        ),  # fmt: skip
        "intri.yml": (
            read_opencv_yaml,
            f'%YAML:1.0\n---\nnames:\n   - "01"\nK_01: {matrix}dist_01: !!opencv-matrix\n   rows: 1\n'
            "   cols: 5\n   dt: d\n   data: [ 0., 0., 0., 0., 0. ]\n",
        ),  # fmt: skip
        "cameras.txt": (_cameras_txt, "# header\n1 PINHOLE 320 240 500 500 160 120\n2 OPENCV 320 240 500 500 160 120 0.1 0 0 0\n"),
        "images.txt": (_images_txt, "1 1 0 0 0 0.5 0 2 1 cam01/000000.png\n\n2 0.7 0.7 0 0 0 0 2 2 cam02/000000.png\n1 2 3\n"),
        "places.txt": (read_places, "# NAME X Y Z\ncam01 1 2 3\ncam02/000000.png 4 5 6\n"),
        "model.obj": (read_obj, "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nvt 1 1\nf 1/1 2/2 3/3\nf 2/2 4/4 3/3\n"),
        "lighting.json": (
            lambda p: lighting_frames(p, 4),
            json.dumps(
                {"frames": [{"frame": 0, "split": "train", "uniform": 0.5}, {"frame": 1, "split": "test", "led": 2, "mesh_frame": 0}]}
            ),
        ),  # fmt: skip
        "calibration.json": (
            load_calibration,
            json.dumps(lightstage_to_dict(default_lightstage(num_leds=3, num_cameras=1, width=8, height=6))),
        ),
        "transforms.json": (
            _transforms_frames,
            json.dumps(
                {
                    "fl_x": 500,
                    "fl_y": 500,
                    "cx": 160,
                    "cy": 120,
                    "w": 320,
                    "h": 240,
                    "frames": [{"file_path": "a.png", "transform_matrix": np.eye(4).tolist(), "light_idx": 1, "pl_pos": [0, 2, 0]}],
                }
            ),
        ),  # fmt: skip
        "cameras.bin": (_cameras_bin, struct.pack("<QiiQQ4d", 1, 1, 1, 320, 240, 500.0, 500.0, 160.0, 120.0)),
        "images.bin": (
            _images_bin,
            struct.pack("<QI7dI", 1, 1, 1, 0, 0, 0, 0.5, 0, 2, 1) + b"cam01/000000.png\0" + struct.pack("<Q2dq", 1, 10.0, 20.0, -1),
        ),  # fmt: skip
    }
    _damaged_reads(samples, tmp_path)


def _damaged_reads(samples: dict, folder: Path, copies: int = 300) -> None:
    """Each sample (file name: (reader, its undamaged bytes or text)) read whole, then ``copies`` damaged copies of it:
    each read, or refused with a GraMiInputError; and the damage reaches every reader's checks (30 refused at least)."""
    failures, refused = [], dict.fromkeys(samples, 0)
    for name, (read, text) in samples.items():
        text = text if isinstance(text, bytes) else text.encode()
        read(_written(folder / name, text))  # the undamaged file is read
        for k, damaged in enumerate(_mutations(text, copies, seed=len(name))):
            try:
                read(_written(folder / name, damaged))
            except GraMiInputError:
                refused[name] += 1
            except Exception as exc:  # noqa: BLE001 (what the test looks for)
                failures.append(f"{name} #{k}: {type(exc).__name__}: {exc} ← {damaged[:200]!r}")
    assert not failures, "\n".join(failures[:20])
    assert all(count >= 30 for count in refused.values()), refused


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_damaged_images_and_meshes_fail_only_by_name(tmp_path):
    """A capture's photographs (PNG, JPEG, EXR), masks and a PLY mesh, damaged 300 ways each (an interrupted copy, a
    flipped byte): each is read, or refused with a GraMiInputError naming it; never another exception."""
    import io

    from PIL import Image

    from gra_mi.capture.mesh_frames import read_mesh
    from gra_mi.capture.source_files import image_size, read_image, read_mask
    from gra_mi.core.io import read_hdr_image, write_exr

    pixels = (np.random.default_rng(0).uniform(0, 1, (12, 16, 3)) * 255).astype(np.uint8)
    encoded = {}
    for name, image, kind in (("photo.png", pixels, "PNG"), ("photo.jpg", pixels, "JPEG"), ("mask.png", pixels[..., 0], "PNG")):
        buffer = io.BytesIO()
        Image.fromarray(image).save(buffer, format=kind)
        encoded[name] = buffer.getvalue()
    write_exr(tmp_path / "source.exr", pixels / 100.0)
    ply = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\n"
           "property list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")  # fmt: skip
    both = lambda p: (read_image(p), image_size(p))  # noqa: E731
    samples = {"photo.png": (both, encoded["photo.png"]), "photo.jpg": (both, encoded["photo.jpg"]), "mask.png": (read_mask, encoded["mask.png"]),
               "photo.exr": (lambda p: (both(p), read_hdr_image(p)), (tmp_path / "source.exr").read_bytes()), "mesh.ply": (read_mesh, ply)}  # fmt: skip
    _damaged_reads(samples, tmp_path)


def _transforms_frames(path: Path) -> list:
    """transforms.json read as the import reads it: the file, its shared intrinsics and each frame, typed."""
    from gra_mi.capture.transforms import TransformsCamera, TransformsFrame, _read
    from gra_mi.core.schema import parse

    data = _read(path)
    parse(TransformsCamera, {k: v for k, v in data.items() if k != "frames"}, path)
    return [parse(TransformsFrame, raw, path, f"frames[{i}]") for i, raw in enumerate(data["frames"])]


def _written(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path
