"""`gra-mi export`: USD and glTF that the field's own validators accept, that read back to the same mesh, and that
Blender (Cycles) renders as Mitsuba renders gra-mi's model (docs/export.md)."""

from __future__ import annotations

import json
import math
import re
import struct

import numpy as np
import pytest

from gra_mi.apps.export import export_avatar, gltf_validator, validate_glb, validate_usd
from gra_mi.apps.gltf import export_glb
from gra_mi.apps.usd import LED_RADIUS_M, UsdLighting, export_usd
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.eval.blender import compare_with_blender, find_blender, reexport_in_blender, render_in_mitsuba, subject_window
from gra_mi.stage.envmap import shift_longitude
from gra_mi.stage.envmap_library import reference_map
from gra_mi.stage.lightstage import default_lightstage, olat_pattern
from gra_mi.subject.sequence import load_sequence, tiny_subject

pxr = pytest.importorskip("pxr")


def structured_maps(n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Maps whose every convention shows: albedo red along u, green along v, a blue checker; roughness along v."""
    u, v = np.meshgrid((np.arange(n) + 0.5) / n, (np.arange(n) + 0.5) / n)
    albedo = np.stack([0.15 + 0.6 * u, 0.15 + 0.6 * v, 0.3 + 0.2 * ((u * 8).astype(int) % 2)], axis=-1)
    return albedo.astype(np.float32), (0.3 + 0.5 * v)[..., None].astype(np.float32)


@pytest.fixture(scope="module")
def avatar():
    return tiny_subject(6), *structured_maps()


def test_usd_passes_usd_cores_validators_in_every_form(tmp_path, avatar):
    seq, albedo, roughness = avatar
    stage = default_lightstage()
    lighting = UsdLighting(reference_map("studio", 16), stage, olat_pattern(stage, 5))
    for name in ("avatar.usdz", "avatar.usda", "avatar.usdc"):
        report = validate_usd(export_usd(tmp_path / name, seq, albedo, roughness, None, stage.cameras, lighting))
        assert report.errors == [] and report.warnings == [], report.summary()
    assert (tmp_path / "avatar_textures" / "albedo.png").is_file() and (tmp_path / "avatar_textures" / "envmap.exr").is_file()


def test_the_validators_do_reject_a_broken_stage(tmp_path, avatar):
    """The check is not vacuous: a material bound without MaterialBindingAPI (a common hand-written mistake) fails."""
    from pxr import Usd, UsdShade

    path = export_usd(tmp_path / "a.usda", *avatar)
    stage = Usd.Stage.Open(str(path))
    body = stage.GetPrimAtPath("/Avatar/Body")
    body.RemoveAPI(UsdShade.MaterialBindingAPI)
    stage.Save()
    assert validate_usd(path).errors


def test_usd_holds_what_a_pipeline_expects(tmp_path, avatar):
    from pxr import Usd, UsdGeom, UsdLux, UsdShade

    seq, albedo, roughness = avatar
    stage_rig = default_lightstage()
    pattern = olat_pattern(stage_rig, 7) * 0.5
    path = export_usd(
        tmp_path / "a.usda", seq, albedo, roughness, [0, 1, 2, 3], stage_rig.cameras[:2], UsdLighting(None, stage_rig, pattern)
    )
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == seq.fps and (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0, 3)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Body"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [0, 1, 2, 3]
    np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get(2)), seq.vertices[2])
    st = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").Get())
    np.testing.assert_allclose(st, np.stack([seq.uvs[:, 0], 1 - seq.uvs[:, 1]], 1), atol=1e-7)
    surface = UsdShade.Shader(stage.GetPrimAtPath("/Avatar/Looks/Fitted/PreviewSurface"))
    assert surface.GetInput("ior").Get() == 1.5 and surface.GetInput("metallic").Get() == 0.0
    texture = UsdShade.Shader(stage.GetPrimAtPath("/Avatar/Looks/Fitted/albedoTexture"))
    assert texture.GetInput("sourceColorSpace").Get() == "sRGB"
    import png

    width, height, rows, _ = png.Reader(filename=str(tmp_path / "a_textures" / "roughness.png")).read()
    np.testing.assert_allclose(np.array(list(rows)) / 65535.0, roughness[..., 0], atol=1e-4)  # raw, 16 bit, row 0 = v 0
    lights = [p for p in stage.Traverse() if p.IsA(UsdLux.SphereLight)]
    assert len(lights) == 1, "only the LED that is on"
    light = UsdLux.SphereLight(lights[0])
    assert light.GetIntensityAttr().Get() == pytest.approx(pattern[7].max() / (math.pi * LED_RADIUS_M**2), rel=1e-6)


def test_usd_camera_projects_as_the_calibration(tmp_path, avatar):
    """usd-core's own camera model (Gf.Camera's frustum) puts the body where the OpenCV calibration does, with the
    principal point off the centre."""
    from dataclasses import replace

    from pxr import Gf, Usd, UsdGeom

    seq = avatar[0]
    camera = replace(default_lightstage().cameras[1], cx=300.0, cy=180.0)
    path = export_usd(tmp_path / "a.usda", *avatar, cameras=[camera])
    stage = Usd.Stage.Open(str(path))
    prim = stage.GetPrimAtPath("/Capture/Cameras/cam000")
    frustum = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode.Default()).frustum
    view_projection = frustum.ComputeViewMatrix() * frustum.ComputeProjectionMatrix()
    points = seq.vertices[0][::7]
    ndc = np.array([view_projection.Transform(Gf.Vec3d(*p.tolist())) for p in points])
    pixels = np.stack([(ndc[:, 0] + 1) / 2 * camera.width, (1 - ndc[:, 1]) / 2 * camera.height], 1)
    np.testing.assert_allclose(pixels, camera.project(points)[:, :2], atol=1e-3)


@pytest.mark.skipif(gltf_validator() is None, reason="node or the npm package gltf-validator is missing (scripts/setup.sh)")
def test_glb_passes_the_khronos_validator_and_a_broken_one_does_not(tmp_path, avatar):
    report = validate_glb(export_glb(tmp_path / "a.glb", *avatar))
    assert report.errors == [] and report.warnings == [], report.errors + report.warnings
    data = bytearray((tmp_path / "a.glb").read_bytes())
    json_length = struct.unpack("<I", data[12:16])[0]
    text = data[20 : 20 + json_length].replace(b'"count":', b'"count":9', 1)  # an accessor that overruns its buffer
    broken = tmp_path / "broken.glb"
    broken.write_bytes(bytes(data[:20]) + text + bytes(data[20 + json_length :]))
    assert validate_glb(broken).errors


def _gltf_pixels(gltf: dict, node: dict, width: int, height: int, points: np.ndarray) -> np.ndarray:
    """Where a glTF camera node sees ``points``, by the spec's own perspective matrix (infinite far plane) and the
    node's column-major matrix: pixels of a ``width`` × ``height`` image, row 0 at the top."""
    camera = gltf["cameras"][node["camera"]]["perspective"]
    t = math.tan(camera["yfov"] / 2.0)
    projection = np.array([[1 / (camera["aspectRatio"] * t), 0, 0, 0], [0, 1 / t, 0, 0], [0, 0, -1, -2 * camera["znear"]], [0, 0, -1, 0]])
    view = np.linalg.inv(np.array(node["matrix"]).reshape(4, 4).T)
    clip = np.concatenate([points, np.ones((len(points), 1))], 1) @ (projection @ view).T
    ndc = clip[:, :3] / clip[:, 3:]
    return np.stack([(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height], 1)


@pytest.mark.skipif(gltf_validator() is None, reason="node or the npm package gltf-validator is missing (scripts/setup.sh)")
def test_a_glbs_cameras_see_as_the_rigs_and_its_lit_leds_are_point_lights(tmp_path, avatar):
    """Cameras and LEDs in a .glb: the Khronos validator accepts them (KHR_lights_punctual), each camera projects the
    mesh where the rig's camera does (the spec's projection, written here), a camera whose principal point glTF cannot
    hold is said, and only the LEDs that are on are lights, each at its position with 683 lm/W × its W/sr."""
    from dataclasses import replace

    seq = avatar[0]
    rig = default_lightstage()
    centred = [replace(cam, cx=cam.width / 2, cy=cam.height / 2) for cam in rig.cameras]
    drive = olat_pattern(rig, 5) + olat_pattern(rig, 40, 0.5)
    report = export_avatar(tmp_path / "a.glb", *avatar, rig=replace(rig, cameras=centred), led_intensities=drive)
    assert report.errors == [] and report.warnings == [], report.errors + report.warnings
    data = (tmp_path / "a.glb").read_bytes()
    gltf = json.loads(data[20 : 20 + struct.unpack("<I", data[12:16])[0]])
    cameras = [n for n in gltf["nodes"] if "camera" in n]
    points = seq.vertices[0][::5].astype(np.float64)
    assert len(cameras) == len(centred) and set(gltf["scenes"][0]["nodes"]) == set(range(len(gltf["nodes"])))
    for node, cam in zip(cameras, centred, strict=True):
        np.testing.assert_allclose(_gltf_pixels(gltf, node, cam.width, cam.height, points), cam.project(points)[:, :2], atol=1e-6)
    lights = gltf["extensions"]["KHR_lights_punctual"]["lights"]
    lit = [n for n in gltf["nodes"] if "extensions" in n]
    assert [light["name"] for light in lights] == ["led0005", "led0040"] and gltf["extensionsUsed"] == ["KHR_lights_punctual"]
    for node, led in zip(lit, (5, 40), strict=True):
        light = lights[node["extensions"]["KHR_lights_punctual"]["light"]]
        np.testing.assert_allclose(node["translation"], rig.led_positions[led])
        assert light["type"] == "point" and light["intensity"] == pytest.approx(683 * drive[led].max()) and light["color"] == [1, 1, 1]
    shifted = replace(rig, cameras=[replace(centred[0], cx=centred[0].cx + 12.5), *centred[1:]])
    off = export_avatar(tmp_path / "b.glb", *avatar, rig=shifted)
    assert off.errors == [] and len(off.warnings) == 1 and "(+12.5, +0.0) px off" in off.warnings[0], off.warnings


@pytest.mark.parametrize("name", ["a.usdz", "a.usda", "a.usdc", "a.glb"])
def test_an_export_reads_back_to_the_same_mesh(tmp_path, avatar, name):
    seq = avatar[0]
    (export_glb if name.endswith(".glb") else export_usd)(tmp_path / name, *avatar)
    back = load_sequence(tmp_path / name)
    np.testing.assert_allclose(back.vertices, seq.vertices, atol=1e-6)
    np.testing.assert_allclose(back.uvs, seq.uvs, atol=1e-6)
    assert np.array_equal(back.faces, seq.faces) and back.fps == pytest.approx(seq.fps, rel=1e-5)


@pytest.mark.parametrize("name", ["a.usda", "a.glb"])
def test_a_frame_selection_exports_those_frames_from_time_0_and_names_them(tmp_path, avatar, name):
    """--frames takes relight's selections: the frames come out in the order given, from time 0, each time naming
    the sequence's frame it shows (USD: gra_mi:sourceFrame; glTF: the node's extras)."""
    seq = avatar[0]
    chosen = [3, 1, 2] if seq.num_frames > 3 else [seq.num_frames - 1, 0]
    export_avatar(tmp_path / name, *avatar, frames=chosen)
    back = load_sequence(tmp_path / name)
    np.testing.assert_allclose(back.vertices, seq.vertices[chosen], atol=1e-6)
    if name.endswith(".glb"):
        document = json.loads(_glb_json(tmp_path / name))
        assert document["nodes"][0]["extras"]["gra_mi"]["source_frames"] == chosen
    else:
        from pxr import Usd

        stage = Usd.Stage.Open(str(tmp_path / name))
        attribute = stage.GetPrimAtPath("/Avatar/Body").GetAttribute("gra_mi:sourceFrame")
        assert [attribute.Get(float(t)) for t in range(len(chosen))] == chosen
    for bad in ([], [seq.num_frames], [-1]):
        with pytest.raises(GraMiParameterError, match="frame"):
            export_avatar(tmp_path / f"bad{name}", *avatar, frames=bad)
    assert not (tmp_path / f"bad{name}").exists()


def _glb_json(path) -> str:
    data = path.read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    return data[20 : 20 + length].decode()


def test_a_dcc_tools_usd_reads_back_z_up_centimetres_and_uv_corners(tmp_path, avatar):
    """What Blender or Maya write after an edit: Z up, centimetres, quads, st per face corner (indexed), the mesh
    under a transformed Xform."""
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(tmp_path / "dcc.usda"))
    UsdGeom.SetStageUpAxis(stage, "Z")
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    root = UsdGeom.Xform.Define(stage, "/root")
    stage.SetDefaultPrim(root.GetPrim())
    root.AddTranslateOp().Set(Gf.Vec3d(100.0, 0.0, 0.0))  # 1 m along x
    mesh = UsdGeom.Mesh.Define(stage, "/root/quad")
    square = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float) * 100  # a 1 m square in the z = 0 plane
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(square.astype(np.float32)))
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    st.Set(Vt.Vec2fArray([(0, 0), (1, 0), (1, 1), (0, 1)]))
    st.SetIndices(Vt.IntArray([0, 1, 2, 3]))
    stage.Save()
    seq = load_sequence(tmp_path / "dcc.usda")
    assert seq.faces.shape == (2, 3) and seq.num_vertices == 4
    np.testing.assert_allclose(seq.vertices[0][:, 0].max(), 2.0, atol=1e-6)  # metres, translated
    np.testing.assert_allclose(seq.vertices[0][:, 1], 0.0, atol=1e-6)  # Z up's z = 0 plane is gra-mi's y = 0 floor
    np.testing.assert_allclose(np.sort(seq.uvs[:, 1]), [0, 0, 1, 1], atol=1e-6)  # v = 1 − t


@pytest.mark.parametrize(
    ("name", "content", "said"),
    [
        ("empty.usda", b"", "not a readable USD"),
        ("nomesh.usda", b'#usda 1.0\ndef Xform "root"\n{\n}\n', "expected one Mesh"),
        ("text.usdc", b"not a crate file", "not a readable USD"),
        ("bad.glb", b"glTF\x02\x00\x00\x00\x40\x00\x00\x00" + b"\0" * 16, "expected a whole glTF"),
        ("png.glb", b"\x89PNG\r\n\x1a\n" + b"\0" * 32, "no 'glTF' magic"),
    ],
)
def test_bad_interchange_files_say_what_is_wrong(tmp_path, name, content, said):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(GraMiInputError, match=said):
        load_sequence(tmp_path / name)


def test_a_truncated_export_is_refused(tmp_path, avatar):
    for name in ("a.usdz", "a.glb"):
        path = (export_glb if name.endswith(".glb") else export_usd)(tmp_path / name, *avatar)
        path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        with pytest.raises(GraMiInputError):
            load_sequence(path)


def test_export_refuses_an_environment_in_a_glb_and_unknown_formats(tmp_path, avatar):
    with pytest.raises(GraMiInputError, match="no environment light"):
        export_avatar(tmp_path / "a.glb", *avatar, envmap=reference_map("studio", 16))
    with pytest.raises(GraMiInputError, match="unknown format"):
        export_avatar(tmp_path / "a.fbx", *avatar)


def test_a_glb_too_long_for_the_format_is_refused_before_anything_is_written(tmp_path, avatar):
    from dataclasses import replace

    from gra_mi.core.errors import GraMiParameterError

    seq, albedo, roughness = avatar
    frames = 1 + (1 << 32) // (seq.num_vertices * 24)  # one frame past 4 GiB of morph targets, never allocated
    long = replace(seq, vertices=np.broadcast_to(seq.vertices[:1], (frames, *seq.vertices.shape[1:])))
    with pytest.raises(GraMiParameterError, match=r"at most \d+ frames \(--frames 0:\d+\)") as refused:
        export_avatar(tmp_path / "long.glb", long, albedo, roughness)
    assert not (tmp_path / "long.glb").exists()
    from gra_mi.apps.gltf import check_glb_size

    offered = int(re.search(r"--frames 0:(\d+)", str(refused.value)).group(1))
    check_glb_size(long, offered)  # what the message offers fits, and a frame more would not
    with pytest.raises(GraMiParameterError):
        check_glb_size(long, offered + 1)


# --------------------------------------------------------------------------------------------------------------
# Blender re-renders the export as Mitsuba renders gra-mi's model
# --------------------------------------------------------------------------------------------------------------

needs_blender = pytest.mark.skipif(find_blender() is None, reason="no Blender (bpy): scripts/setup.sh installs it into .venv-blender")


@pytest.fixture(scope="module")
def blender_scene(tmp_path_factory):
    seq, albedo, roughness = tiny_subject(8), *structured_maps()
    folder = tmp_path_factory.mktemp("blender")
    from gra_mi.core.io import write_exr

    write_exr(folder / "studio.exr", reference_map("studio", 64))
    camera = subject_window(default_lightstage().cameras[0], seq.vertices.reshape(-1, 3), 128)
    assets = [export_usd(folder / "avatar.usdz", seq, albedo, roughness), export_glb(folder / "avatar.glb", seq, albedo, roughness)]
    return seq, albedo, roughness, folder, camera, assets


@needs_blender
@pytest.mark.parametrize("name", ["a.glb", "a.usda"])
def test_blender_imports_the_cameras_and_lights_as_the_rig_holds_them(tmp_path, avatar, name):
    """Blender's own importers: every camera where the rig's stands, looking where it looks with its vertical field of
    view, and every lit LED a point light at its position emitting 4π × its W/sr (in watts) in its colour. Blender
    4.5's USD importer reads a SphereLight's intensity as π × intensity watts whatever its radius: with its
    ``light_intensity_scale`` at the sphere's area (4π r²) it gets the power the USD holds."""
    from dataclasses import replace

    from gra_mi.eval.blender import inventory_in_blender

    rig = default_lightstage()
    rig = replace(rig, cameras=rig.cameras[:3])
    drive = olat_pattern(rig, 7) * np.array([1.0, 0.5, 0.25])
    export_avatar(tmp_path / name, *avatar, rig=rig, led_intensities=drive)
    scale = 1.0 if name.endswith(".glb") else 4 * math.pi * LED_RADIUS_M**2
    seen = inventory_in_blender(tmp_path / name, tmp_path / "inventory.json", scale)
    cameras = sorted(seen["cameras"], key=lambda c: c["name"])  # USD's prims are cam000 …, glTF's nodes the rig's names
    assert len(cameras) == len(rig.cameras), [c["name"] for c in cameras]
    for seen_camera, cam in zip(cameras, rig.cameras, strict=True):
        c2w = np.array(seen_camera["camera_to_world"])
        np.testing.assert_allclose(c2w[:3, 3], cam.position, atol=1e-5)
        np.testing.assert_allclose(c2w[:3, 2], cam.rotation[:, 2], atol=1e-5)  # OpenCV's +Z: where it looks
        np.testing.assert_allclose(c2w[:3, 1], cam.rotation[:, 1], atol=1e-5)  # +Y: the image's down
        assert seen_camera["angle_y"] == pytest.approx(2 * math.atan(cam.height / (2 * cam.fy)), rel=1e-5)
    (light,) = seen["lights"]
    assert light["type"] == "POINT" and light["energy"] == pytest.approx(4 * math.pi * drive[7].max(), rel=1e-4)
    np.testing.assert_allclose(light["position"], rig.led_positions[7], atol=1e-5)
    np.testing.assert_allclose(light["color"], [1.0, 0.5, 0.25], atol=1e-6)


@needs_blender
def test_blender_renders_the_export_as_mitsuba_renders_gra_mis_model(blender_scene, llvm_variant):
    seq, albedo, roughness, folder, camera, assets = blender_scene
    assert np.abs(seq.vertices[2] - seq.vertices[0]).max() > 0.2, "the pose moves between the two frames"
    rows, _ = compare_with_blender(
        assets, seq, [0, 2], albedo, roughness, folder / "studio.exr", camera, folder, 128, ("fitted", "lambert")
    )
    for row in rows:
        assert row["pose_error_m"] < 1e-5, row
        assert row["iou"] >= 0.99 and abs(row["brightness"]) <= 0.03 and row["psnr"] >= 30.0, row
    fitted = np.mean([r["psnr"] for r in rows if r["material"] == "fitted"])
    lambert = np.mean([r["psnr"] for r in rows if r["material"] == "lambert"])
    assert lambert > fitted + 2.0, "with one model on both sides, the handover itself agrees better (docs/export.md)"


@needs_blender
def test_the_blender_comparison_sees_a_turned_envmap_and_a_flipped_texture(blender_scene, llvm_variant):
    """Negative controls: the agreement above is not loose enough to hide the conventions it checks."""
    from gra_mi.core.io import read_exr, write_exr
    from gra_mi.eval.blender import agreement, render_in_blender

    seq, albedo, roughness, folder, camera, assets = blender_scene
    blender, _ = render_in_blender(assets[0], 0, seq.fps, folder / "studio.exr", camera, folder, 128, lambert=True)
    write_exr(folder / "turned.exr", shift_longitude(read_exr(folder / "studio.exr"), 0.25))
    turned = render_in_mitsuba(seq, 0, albedo, roughness, folder / "turned.exr", camera, folder / "turned", 256, lambert=True)
    flipped = render_in_mitsuba(seq, 0, albedo[::-1], roughness, folder / "studio.exr", camera, folder / "flipped", 256, lambert=True)
    right = render_in_mitsuba(seq, 0, albedo, roughness, folder / "studio.exr", camera, folder / "right", 256, lambert=True)
    assert agreement(blender, right)["psnr"] >= 33.0
    assert agreement(blender, turned)["psnr"] < 28.0 and agreement(blender, flipped)["psnr"] < 28.0


def test_export_command_round_trip_and_hostile_outputs(tmp_path, avatar, capsys):
    from gra_mi.cli.main import main
    from gra_mi.core.io import write_exr
    from gra_mi.stage.lightstage import save_calibration
    from gra_mi.subject.sequence import save_sequence

    seq, albedo, roughness = avatar
    save_sequence(seq, tmp_path / "subject")
    save_calibration(default_lightstage(), tmp_path / "rig" / "calibration.json")
    (tmp_path / "three_leds.json").write_text("[[1, 1, 1], [0, 0, 0], [1, 0, 0]]")
    write_exr(tmp_path / "nan.exr", np.full((8, 16, 3), np.nan, np.float32))
    write_exr(tmp_path / "albedo.exr", albedo)
    write_exr(tmp_path / "rough.exr", roughness)
    maps = ["--albedo", str(tmp_path / "albedo.exr"), "--roughness", str(tmp_path / "rough.exr")]
    assert main(["export", "--out", str(tmp_path / "a.usdz"), "--subject", str(tmp_path / "subject"), *maps]) == 0
    assert main(["export", "--out", str(tmp_path / "b.glb"), "--subject", str(tmp_path / "a.usdz"), *maps]) == 0  # USD in, glTF out
    np.testing.assert_allclose(load_sequence(tmp_path / "b.glb").vertices, seq.vertices, atol=1e-6)
    capsys.readouterr()
    refused = [
        (["--out", str(tmp_path / "subject" / "x.usdz"), "--subject", str(tmp_path / "subject")], "lies inside"),
        (["--out", str(tmp_path / "c.glb"), "--subject", str(tmp_path / "subject"), "--rig", str(tmp_path / "subject")], "calibration"),
        (["--out", str(tmp_path / "c.fbx"), "--subject", str(tmp_path / "subject")], "give a file name ending .usda"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "albedo.exr")], "not a subject"),
        (["--out", str(tmp_path / "a.usdz"), "--subject", str(tmp_path / "a.usdz")], "the subject input"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "subject"), "--rig", str(tmp_path / "rig"),
          "--pattern", str(tmp_path / "three_leds.json")], "three_leds.json"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "subject"), "--envmap", str(tmp_path / "nan.exr")], "nan.exr"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "subject"), "--frames", "2"], "':2' exports the first 2"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "subject"), "--frames", "0:99"], "frame 6 is not"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "subject"), "--frames", "5:2"], "selects nothing"),
        (["--out", str(tmp_path / "c.usdz"), "--subject", str(tmp_path / "subject"), "--frames", "1,x"], "--frames"),
    ]  # fmt: skip
    for args, said in refused:
        assert main(["export", *args, *maps]) == 2
        assert said in capsys.readouterr().err
    assert not (tmp_path / "c.usdz").exists() and not (tmp_path / "subject" / "x.usdz").exists()


@needs_blender
@pytest.mark.parametrize(
    ("ours", "blenders", "offset"),
    [
        ("avatar.glb", "edited.glb", 0),  # morph targets, sparse accessors, LINEAR keys
        ("avatar.usdz", "edited.usdc", 0),  # time-sampled points, UVs per face corner
        ("avatar.glb", "edited.usda", 1),  # shape keys as UsdSkel blend shapes; Blender's frames start at 1
    ],
)
def test_an_avatar_that_blender_wrote_back_reads_as_the_same_performance(blender_scene, tmp_path, ours, blenders, offset):
    """The importer on files written the way the DCC tool writes them, not only by gra-mi's own exporter."""
    from scipy.spatial import cKDTree

    seq, assets = blender_scene[0], blender_scene[5]
    asset = assets[0] if ours.endswith(".usdz") else assets[1]
    back = load_sequence(reexport_in_blender(asset, tmp_path / blenders))
    assert back.num_frames >= seq.num_frames - offset and back.fps == pytest.approx(seq.fps)
    for j in range(seq.num_frames - offset):
        truth = seq.vertices[j + offset]
        assert cKDTree(truth).query(back.vertices[j])[0].max() < 1e-5, f"frame {j}"
        assert cKDTree(back.vertices[j]).query(truth)[0].max() < 1e-5, f"frame {j}: a vertex went missing"
    with_uv = cKDTree(np.concatenate([seq.vertices[offset], seq.uvs], axis=1))
    assert with_uv.query(np.concatenate([back.vertices[0], back.uvs], axis=1))[0].max() < 1e-5, "every (position, UV) pair is gra-mi's"
