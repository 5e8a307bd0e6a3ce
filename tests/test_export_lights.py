"""`gra-mi export --lights`: a light path's moving point and spot lights in USD and glTF, sampled at every exported
frame where gra-mi's own path puts them, accepted by the formats' validators, and imported so by Blender."""

from __future__ import annotations

import json
import math
import struct

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

PATH = {
    "lights": [
        {"name": "key light", "type": "point", "radius": 0.03, "intensity": 1.5,
         "keyframes": [{"frame": 0, "position": [0.6, 1.2, 0.4]}, {"frame": 3, "position": [-0.6, 1.5, 0.4], "intensity": [3, 2, 1]}]},
        {"name": "../rim", "type": "spot", "radius": 0, "intensity": [4, 3.6, 3], "cutoff_angle": 25, "beam_width": 18,
         "keyframes": [{"frame": 0, "position": [0, 1.8, -0.8], "target": [0, 1.2, 0]},
                       {"frame": 3, "position": [0.8, 1.8, 0.0], "target": [0, 1.0, 0], "cutoff_angle": 40}]},
    ]
}  # fmt: skip
FRAMES = [1, 2, 3]  # exported as times 0, 1, 2


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The avatar's frames 1..3 with the path's lights, in each format; the path's own lights at those frames."""
    from gra_mi.apps.export import export_avatar
    from gra_mi.apps.export_lights import light_tracks
    from gra_mi.render.light_path import LightPath
    from gra_mi.subject.sequence import tiny_subject

    folder = tmp_path_factory.mktemp("export_lights")
    (folder / "path.json").write_text(json.dumps(PATH))
    path = LightPath.load(folder / "path.json")
    tracks = light_tracks(path, FRAMES)
    maps = (np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8, 1), 0.5, np.float32))
    reports = {name: export_avatar(folder / name, tiny_subject(4), *maps, FRAMES, tracks=tracks) for name in ("a.usda", "a.usdz", "a.glb")}
    truth = {light.name: [light.at(f) for f in FRAMES] for light in path.lights}
    return folder, reports, truth


def _rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v turned by the unit quaternion q = (x, y, z, w): v + 2w (q⃗ × v) + 2 q⃗ × (q⃗ × v)."""
    u, w = np.asarray(q[:3], np.float64), float(q[3])
    return v + 2 * w * np.cross(u, v) + 2 * np.cross(u, np.cross(u, v))


def test_usd_holds_each_light_where_the_path_puts_it_at_each_frame(exported):
    """At time code t (the sequence's frame FRAMES[t]): the light's transform at the path's position, a spot's −Z along
    its direction; intensity × π r² the path's peak W/sr, the colour its RGB over that peak; a spot's cone angle its
    cutoff and softness the share of the cone outside the full beam; a light without radius marked treatAsPoint."""
    from pxr import Usd, UsdGeom, UsdLux

    folder, reports, truth = exported
    assert all(r.errors == [] and r.warnings == [] for name, r in reports.items() if name != "a.glb"), reports
    stage = Usd.Stage.Open(str(folder / "a.usda"))
    lights = {p.GetDisplayName(): UsdLux.SphereLight(p) for p in stage.Traverse() if p.IsA(UsdLux.SphereLight)}
    assert sorted(lights) == sorted(truth)
    for name, states in truth.items():
        light = lights[name]
        radius = light.GetRadiusAttr().Get()
        assert light.GetTreatAsPointAttr().Get() == (states[0].radius == 0)
        assert radius == pytest.approx(states[0].radius or 0.01)
        for t, state in enumerate(states):
            m = np.array(UsdGeom.Xformable(light).ComputeLocalToWorldTransform(t)).T  # (column vectors)
            np.testing.assert_allclose(m[:3, 3], state.position, atol=1e-6)
            peak = state.intensity.max()
            assert light.GetIntensityAttr().Get(t) * math.pi * radius**2 == pytest.approx(peak, rel=1e-5)
            np.testing.assert_allclose(tuple(light.GetColorAttr().Get(t)), state.intensity / peak, rtol=1e-6)
            if state.is_spot:
                shine = m[:3, :3] @ [0.0, 0.0, -1.0]
                np.testing.assert_allclose(shine, state.direction, atol=1e-6)
                shaping = UsdLux.ShapingAPI(light.GetPrim())
                assert shaping.GetShapingConeAngleAttr().Get(t) == pytest.approx(state.cutoff_angle, rel=1e-6)
                assert shaping.GetShapingConeSoftnessAttr().Get(t) == pytest.approx(1 - state.beam_width / state.cutoff_angle, rel=1e-5)


def _glb_json(path) -> tuple[dict, bytes]:
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20 : 20 + length])
    return gltf, data[20 + length + 8 :]


def _accessor(gltf: dict, binary: bytes, index: int) -> np.ndarray:
    accessor = gltf["accessors"][index]
    view = gltf["bufferViews"][accessor["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[accessor["type"]]
    values = np.frombuffer(binary, np.float32, accessor["count"] * width, view["byteOffset"])
    return values.reshape(accessor["count"], width)


def test_glb_lights_move_with_the_avatar_and_say_what_glTF_cannot_hold(exported):
    """A point and a spot light (KHR_lights_punctual; candela = 683 × W/sr; a spot's outer cone its cutoff, its inner the
    full beam), each on a node whose translation (and a spot's rotation: −Z along its direction) the avatar's animation
    steps through at the exported frames' times; the warnings name what glTF leaves out (the key light's radius and
    changing intensity, the spot's changing cone)."""
    from gra_mi.subject.sequence import tiny_subject

    folder, reports, truth = exported
    assert reports["a.glb"].errors == []
    warnings = "\n".join(reports["a.glb"].warnings)
    assert "light 'key light': the .glb leaves out its 0.03 m radius" in warnings and "changing intensity and colour" in warnings
    assert "light '../rim': the .glb leaves out its changing cone" in warnings
    gltf, binary = _glb_json(folder / "a.glb")
    lights = {light["name"]: light for light in gltf["extensions"]["KHR_lights_punctual"]["lights"]}
    nodes = {n["name"]: i for i, n in enumerate(gltf["nodes"]) if "KHR_lights_punctual" in n.get("extensions", {})}
    (animation,) = gltf["animations"]  # (the avatar's and the lights': one timeline)
    for name, states in truth.items():
        first = states[0]
        assert lights[name]["intensity"] == pytest.approx(683 * first.intensity.max(), rel=1e-6)
        channels = {
            c["target"]["path"]: animation["samplers"][c["sampler"]] for c in animation["channels"] if c["target"]["node"] == nodes[name]
        }
        times = _accessor(gltf, binary, channels["translation"]["input"])[:, 0]
        np.testing.assert_allclose(times, np.arange(len(FRAMES)) / tiny_subject(1).fps, rtol=1e-6)
        moved = _accessor(gltf, binary, channels["translation"]["output"])
        np.testing.assert_allclose(moved, [s.position for s in states], atol=1e-6)
        if first.is_spot:
            spot = lights[name]["spot"]
            assert spot["outerConeAngle"] == pytest.approx(math.radians(first.cutoff_angle))
            assert spot["innerConeAngle"] == pytest.approx(math.radians(first.beam_width))
            turned = _accessor(gltf, binary, channels["rotation"]["output"])
            for q, state in zip(turned, states, strict=True):
                np.testing.assert_allclose(_rotate(q, np.array([0.0, 0.0, -1.0])), state.direction, atol=1e-5)


def test_a_path_light_named_as_an_led_keeps_apart_from_it(tmp_path):
    """The LEDs a pattern lights (/Capture/Lights/ledNNNN) and a light path's lights (/Capture/PathLights) do not share
    prims: a path light named led0001 beside a lit LED 1 leaves both."""
    from pxr import Usd, UsdLux

    from gra_mi.apps.export import export_avatar
    from gra_mi.apps.export_lights import light_tracks
    from gra_mi.render.light_path import LightPath
    from gra_mi.stage.lightstage import default_lightstage, olat_pattern
    from gra_mi.subject.sequence import tiny_subject

    named = {"lights": [{"name": "led0001", "keyframes": [{"frame": 0, "position": [0, 2, 1]}]}]}
    (tmp_path / "path.json").write_text(json.dumps(named))
    rig = default_lightstage()
    maps = (np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8, 1), 0.5, np.float32))
    tracks = light_tracks(LightPath.load(tmp_path / "path.json"), [0])
    report = export_avatar(tmp_path / "a.usda", tiny_subject(1), *maps, rig=rig, led_intensities=olat_pattern(rig, 1), tracks=tracks)
    assert report.errors == []
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    lights = sorted(str(p.GetPath()) for p in stage.Traverse() if p.IsA(UsdLux.SphereLight))
    assert lights == ["/Capture/Lights/led0001", "/Capture/PathLights/led0001"]
    led = UsdLux.SphereLight(stage.GetPrimAtPath("/Capture/Lights/led0001"))
    assert not led.GetPrim().GetAttribute("xformOp:transform").IsValid()  # (the LED's own translate, not the path light's)


def test_export_lights_refuses_what_a_format_or_the_path_cannot_hold(tmp_path, capsys):
    """A spot wider than a hemisphere goes to USD, not to a .glb (refused before writing, naming the light); frames
    outside a light's keyframes are refused, not extrapolated; a path file that is not one names its field."""
    from gra_mi.cli.main import main
    from gra_mi.core.io import write_exr
    from gra_mi.subject.sequence import save_sequence, tiny_subject

    save_sequence(tiny_subject(5), tmp_path / "subject")
    write_exr(tmp_path / "maps.exr", np.full((8, 8, 3), 0.5, np.float32))
    wide = {
        "lights": [
            {"name": "flood", "type": "spot", "cutoff_angle": 120, "keyframes": [{"frame": 0, "position": [0, 2, 1], "target": [0, 1, 0]}]}
        ]
    }
    (tmp_path / "wide.json").write_text(json.dumps(wide))
    (tmp_path / "short.json").write_text(json.dumps(PATH))  # keyframes 0..3 of a 5-frame subject
    (tmp_path / "bad.json").write_text('{"lights": [{"keyframes": [{"frame": 0, "position": [0, "x", 0]}]}]}')
    base = [
        "export",
        "--subject",
        str(tmp_path / "subject"),
        "--albedo",
        str(tmp_path / "maps.exr"),
        "--roughness",
        str(tmp_path / "maps.exr"),
    ]
    for out, path, said in (("a.glb", "wide.json", "light 'flood' is a spot of cutoff 120°"), ("a.usdz", "short.json", "frame(s) [4]"),
                            ("a.usdz", "bad.json", "lights[0].keyframes[0].position")):  # fmt: skip
        assert main([*base, "--out", str(tmp_path / out), "--lights", str(tmp_path / path)]) == 2
        assert said in capsys.readouterr().err
    assert not (tmp_path / "a.glb").exists() and not (tmp_path / "a.usdz").exists()
    assert main([*base, "--out", str(tmp_path / "a.usdz"), "--lights", str(tmp_path / "wide.json")]) == 0
    assert main([*base, "--out", str(tmp_path / "b.usdz"), "--lights", str(tmp_path / "short.json"), "--frames", "1:4"]) == 0


@pytest.mark.skipif(__import__("gra_mi.eval.blender", fromlist=["x"]).find_blender() is None, reason="no Blender (bpy)")
@pytest.mark.parametrize("name", ["a.glb", "a.usda"])
def test_blender_imports_the_moving_lights_where_the_path_puts_them(exported, tmp_path, name):
    """Blender's own importers, at each exported frame: every light where the path puts it at that frame, a spot
    shining along its direction. Its cone (Blender's: twice the cutoff) is the first frame's in both: a .glb holds no
    other, and Blender 4.5's USD importer reads the first of the cone's time samples (the file holds each frame's:
    the USD test above)."""
    from gra_mi.eval.blender import inventory_in_blender
    from gra_mi.subject.sequence import tiny_subject

    folder, _, truth = exported

    for t in range(len(FRAMES)):
        seen = inventory_in_blender(folder / name, tmp_path / f"inventory{t}.json", at=(t, tiny_subject(1).fps))
        lights = {light["name"]: light for light in seen["lights"]}  # (glTF keeps a light's name; USD's prim path its letters)
        assert len(lights) == len(truth), lights
        for light_name, states in truth.items():
            light = lights.get(light_name) or lights[light_name.replace("../", "___").replace(" ", "_")]
            np.testing.assert_allclose(light["position"], states[t].position, atol=1e-4)
            if states[t].is_spot:
                np.testing.assert_allclose(light["direction"], states[t].direction, atol=1e-4)
                assert light["spot_size"] == pytest.approx(2 * math.radians(states[0].cutoff_angle), rel=1e-4)
