"""`gra-mi export --set`: a scene's set (a floor, props) beside the avatar, as Mitsuba holds each shape (its surface,
its facing) and a preview of its BSDF, accepted by the formats' own validators, and imported so by Blender."""

from __future__ import annotations

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

PLACE = '<transform name="to_world"><scale value="{s}"/><translate x="{x}" y="{y}" z="{z}"/></transform>'
SHAPES = {  # the user's id → its element (from-scene names them set_NNN in its order)
    "floor": '<shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="2"/></transform>'
    '<bsdf type="roughconductor"><float name="alpha" value="0.25"/></bsdf></shape>',
    "ball": f'<shape type="sphere" id="ball">{PLACE.format(s=0.1, x=0.5, y=0.3, z=0.2)}<bsdf type="roughplastic">'
    '<rgb name="diffuse_reflectance" value="0.8, 0.2, 0.1"/></bsdf></shape>',
    "pole": f'<shape type="cylinder" id="pole">{PLACE.format(s=0.05, x=-0.5, y=0.5, z=0)}<bsdf type="twosided"><bsdf type="diffuse">'
    '<rgb name="reflectance" value="0.3"/></bsdf></bsdf></shape>',
    "lamp": f'<shape type="disk" id="lamp">{PLACE.format(s=0.2, x=-0.5, y=1.0, z=0.3)}<bsdf type="principled">'
    '<float name="roughness" value="0.6"/></bsdf></shape>',
    "crate": f'<shape type="cube" id="crate">{PLACE.format(s=0.1, x=0.6, y=0.15, z=-0.4)}<bsdf type="roughconductor">'
    '<texture type="bitmap" name="alpha"><string name="filename" value="alpha.exr"/><boolean name="raw" value="true"/></texture>'
    "</bsdf></shape>",
}  # fmt: skip
EXPECTED = {  # (metallic, roughness) of each preview
    "floor": (1.0, 0.5),
    "ball": (0.0, np.sqrt(0.1)),  # roughplastic's default α
    "pole": (0.0, 1.0),
    "lamp": (0.0, 0.6),  # principled's roughness is perceptual already
    "crate": (1.0, np.sqrt(0.2)),  # the mean of the texture's α (0.04 and 0.36)
}


@pytest.fixture(scope="module")
def stage_with_set(tmp_path_factory):
    """A lightstage with the set of SHAPES, from `from-scene`; its set as the export reads it, the shapes by user id."""
    from gra_mi.apps.set_export import read_set
    from gra_mi.cli.main import main
    from gra_mi.core.io import write_exr
    from gra_mi.core.runtime import choose_variant

    from .test_from_scene import write_user_scene
    from .test_scene_set import BODY

    folder = tmp_path_factory.mktemp("set_export")
    (folder / "user").mkdir()
    alpha = np.where(np.indices((2, 2)).sum(axis=0) % 2 == 0, 0.04, 0.36)[..., None].astype(np.float32)
    write_exr(folder / "user" / "alpha.exr", alpha)
    path = write_user_scene(folder / "user", shapes=BODY + "".join(SHAPES.values()))
    assert main(["from-scene", str(path), "--out", str(folder / "stage")]) == 0
    choose_variant("llvm_ad_rgb")
    notes = (folder / "stage" / "notes.md").read_text()
    ids = dict(line.split("shape '")[1].split("' (")[0:2] for line in notes.splitlines() if line.startswith("- kept as the set: shape"))
    by_user = {user: at.split(" ")[0] for user, at in ids.items()}  # the user's id → set_NNN
    parts, said = read_set(folder / "stage" / "scene.xml")
    return folder, {user: next(p for p in parts if p.name == name) for user, name in by_user.items()}, said


def _stage_scene(folder):
    from gra_mi.stage.scene import LightstageScene

    return LightstageScene.load(folder / "stage" / "scene.xml").scene


def test_each_set_part_lies_on_mitsubas_shape_and_faces_its_way(stage_with_set):
    """Every triangle's centre lies on the Mitsuba shape it stands for, its winding facing as Mitsuba's normal there (a
    ray back along the triangle's normal meets the shape at once, front side first); the triangles' area is the shape's
    (Mitsuba's surface_area, within the tessellation's 1 %), and the vertex normals face as the triangles do."""
    import mitsuba as mi

    folder, parts, _ = stage_with_set
    scene = _stage_scene(folder)
    shapes = {s.id(): s for s in scene.shapes()}
    assert sorted(parts) == sorted(SHAPES)
    for user, part in parts.items():
        shape = shapes[part.name]
        corners = part.vertices.astype(np.float64)[part.faces]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        area = 0.5 * np.linalg.norm(cross, axis=1)
        assert area.sum() == pytest.approx(float(shape.surface_area()[0]), rel=0.01), user
        facing = cross / np.linalg.norm(cross, axis=1, keepdims=True)
        centre = corners.mean(axis=1)
        start = centre + 1e-3 * facing
        ray = mi.Ray3f(mi.Point3f(*start.T.astype(np.float32)), mi.Vector3f(*(-facing).T.astype(np.float32)))
        si = scene.ray_intersect(ray)
        assert np.all(np.array(si.shape == mi.ShapePtr(shape))), user
        t, n = np.array(si.t), np.array(si.n).T
        assert np.all(t < 2e-3), (user, float(t.max()))  # the centre is on the surface (within a tessellation's sag)
        assert np.all(np.sum(n * facing, axis=1) > 0.98), user  # and the triangle faces as Mitsuba's normal
        vertex_normals = part.normals[part.faces].mean(axis=1)
        assert np.all(np.sum(vertex_normals * facing, axis=1) > 0), user
    flat = parts["crate"].normals[parts["crate"].faces]  # (a cube's faces stay flat, as Mitsuba shades them)
    np.testing.assert_allclose(flat, np.repeat(flat[:, :1], 3, axis=1), atol=1e-6)
    assert np.allclose(np.abs(flat[:, 0]).max(axis=1), 1.0, atol=1e-6)


def test_each_preview_summarises_its_bsdf(stage_with_set):
    """Metal, roughness and colour per BSDF: a rough metal is metallic with √α; a plastic's base colour is its diffuse
    lobe's albedo under the coat (the hue of its reflectance, darker); a diffuse its reflectance, rough 1, no specular
    (ior 1); a principled its own parameters; a textured α its mean. Each shape is said in the notes."""
    folder, parts, said = stage_with_set
    for user, (metallic, roughness) in EXPECTED.items():
        assert parts[user].preview.metallic == metallic and parts[user].preview.roughness == pytest.approx(roughness, rel=1e-4), user
    np.testing.assert_allclose(parts["pole"].preview.base_color, 0.3, rtol=1e-4)
    assert parts["pole"].preview.ior == 1.0 and all(parts[u].preview.ior == 1.5 for u in ("floor", "ball", "lamp", "crate"))
    assert parts["lamp"].preview.base_color == (0.5, 0.5, 0.5)  # principled's own (its default) base colour
    ball = np.array(parts["ball"].preview.base_color)
    np.testing.assert_allclose(ball / ball[0], np.array([0.8, 0.2, 0.1]) / 0.8, rtol=0.01)
    assert 0.5 < ball[0] < 0.8
    assert min(parts["floor"].preview.base_color) > 0.85  # roughconductor's default: a perfect mirror, less what α masks
    assert len(said) == len(SHAPES) and all("previewed as base colour" in line for line in said)


def test_the_set_exports_to_usd_and_gltf_as_their_validators_and_readers_want(stage_with_set, tmp_path):
    """USD (usd-core's validators) and glTF (the Khronos validator, where node has it) accept the avatar with its set;
    USD's prims hold each part's points and its preview material, bound."""
    from pxr import Usd, UsdGeom, UsdShade

    from gra_mi.apps.export import export_avatar, gltf_validator
    from gra_mi.subject.sequence import tiny_subject

    _, parts, _ = stage_with_set
    albedo, roughness = np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8, 1), 0.5, np.float32)
    avatar = (tiny_subject(2), albedo, roughness)
    for name in ("a.usdz", "a.usda", "a.glb"):
        report = export_avatar(tmp_path / name, *avatar, set_parts=list(parts.values()))
        assert report.errors == [] and report.warnings == [], report
        assert name != "a.glb" or gltf_validator() is None or report.validator.startswith("glTF-Validator")
    stage = Usd.Stage.Open(str(tmp_path / "a.usda"))
    for part in parts.values():
        mesh = UsdGeom.Mesh.Get(stage, f"/Set/Geometry/{part.name}")
        np.testing.assert_allclose(np.array(mesh.GetPointsAttr().Get()), part.vertices)
        material = UsdShade.MaterialBindingAPI(mesh.GetPrim()).ComputeBoundMaterial()[0]
        surface = material.ComputeSurfaceSource()[0]
        np.testing.assert_allclose(tuple(surface.GetInput("diffuseColor").Get()), part.preview.base_color, rtol=1e-6)
        assert surface.GetInput("metallic").Get() == part.preview.metallic
        assert surface.GetInput("ior").Get() == part.preview.ior


def test_prim_names_from_any_id_are_unique_and_usable():
    """Ids a user's scene may hold (a path, spaces, a leading digit, none, two that read alike) become distinct names
    USD's prim paths take."""
    from pxr import Sdf

    from gra_mi.apps.usd import prim_name

    used: set[str] = set()
    names = [prim_name(i, f"set_{k:03d}", used) for k, i in enumerate(["../x", "/abs", "a b", "a_b", "1st", "", "set_006", "ünï"])]
    assert len(set(names)) == len(names) and all(Sdf.Path.IsValidIdentifier(n) for n in names), names


def test_a_stage_folder_without_a_set_and_nan_roughness(stage_with_set, tmp_path):
    """A stage folder reads as its scene.xml; a stage whose scene holds the subject alone says that no set is written;
    a roughness texture's NaN texels are left out of its mean."""
    import mitsuba as mi

    from gra_mi.apps.set_export import bsdf_roughness, read_set
    from gra_mi.cli.main import main
    from gra_mi.core.io import write_exr

    from .test_from_scene import write_user_scene
    from .test_scene_set import BODY

    folder, parts, _ = stage_with_set
    assert [p.name for p in read_set(folder / "stage")[0]] == sorted(p.name for p in parts.values())
    (tmp_path / "user").mkdir()
    assert main(["from-scene", str(write_user_scene(tmp_path / "user", shapes=BODY)), "--out", str(tmp_path / "stage")]) == 0
    assert read_set(tmp_path / "stage") == ([], ["the scene holds no shape besides the subject: no set is written"])
    xml = (tmp_path / "stage" / "scene.xml").read_text()  # a panel light added by hand: its light is said to stay behind
    panel = '<shape type="rectangle" id="panel"><emitter type="area"><rgb name="radiance" value="5"/></emitter></shape>'
    (tmp_path / "stage" / "scene.xml").write_text(xml.replace("</scene>", panel + "</scene>"))
    (part,), (said,) = read_set(tmp_path / "stage")
    assert part.preview.base_color == (0.0, 0.0, 0.0) and "its area light is not carried" in said  # (Mitsuba's lamp: black)
    write_exr(tmp_path / "alpha.exr", np.array([[[np.nan], [0.25]]], np.float32))
    bsdf = mi.load_dict({"type": "roughconductor", "alpha": {"type": "bitmap", "filename": str(tmp_path / "alpha.exr"), "raw": True}})
    assert bsdf_roughness(bsdf) == pytest.approx(0.5, rel=1e-6)


def test_export_set_says_each_shape_and_refuses_what_is_not_a_lightstage_scene(stage_with_set, tmp_path, capsys):
    from gra_mi.cli.main import main
    from gra_mi.core.io import write_exr
    from gra_mi.subject.sequence import save_sequence, tiny_subject

    save_sequence(tiny_subject(2), tmp_path / "subject")
    write_exr(tmp_path / "albedo.exr", np.full((8, 8, 3), 0.5, np.float32))
    (tmp_path / "plain.xml").write_text('<scene version="3.0.0"><shape type="sphere"/></scene>')
    (tmp_path / "broken.xml").write_text('<scene version="3.0.0"><shape type="sph')
    base = ["export", "--out", str(tmp_path / "a.usdz"), "--subject", str(tmp_path / "subject")]
    base += ["--albedo", str(tmp_path / "albedo.exr"), "--roughness", str(tmp_path / "albedo.exr")]
    for scene, said in (("plain.xml", "plain.xml"), ("broken.xml", "broken.xml"), ("gone.xml", "not found")):
        assert main([*base, "--set", str(tmp_path / scene)]) == 2
        assert said in capsys.readouterr().err
    assert not (tmp_path / "a.usdz").exists()
    assert main([*base, "--set", str(stage_with_set[0] / "stage")]) == 0
    told = capsys.readouterr().out
    assert "0 errors" in told and all(f"set: {p.name}: its " in told for p in stage_with_set[1].values()), told


@pytest.mark.skipif(__import__("gra_mi.eval.blender", fromlist=["x"]).find_blender() is None, reason="no Blender (bpy)")
@pytest.mark.parametrize("name", ["a.glb", "a.usda"])
def test_blender_imports_the_set_where_it_stands_with_its_preview(stage_with_set, tmp_path, name):
    """Blender's own importers: each part where Mitsuba's shape stands (its bounds in gra-mi's world) with the
    preview's base colour, roughness and metallic on its Principled BSDF."""
    from gra_mi.apps.export import export_avatar
    from gra_mi.eval.blender import inventory_in_blender
    from gra_mi.subject.sequence import tiny_subject

    _, parts, _ = stage_with_set
    maps = (np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8, 1), 0.5, np.float32))
    export_avatar(tmp_path / name, tiny_subject(2), *maps, set_parts=list(parts.values()))
    seen = {m["name"]: m for m in inventory_in_blender(tmp_path / name, tmp_path / "inventory.json")["meshes"]}
    for part in parts.values():
        mesh = seen[part.name]
        np.testing.assert_allclose(mesh["min"], part.vertices.min(axis=0), atol=1e-5)
        np.testing.assert_allclose(mesh["max"], part.vertices.max(axis=0), atol=1e-5)
        np.testing.assert_allclose(mesh["Base Color"], part.preview.base_color, atol=1e-5)
        assert mesh["Roughness"] == pytest.approx(part.preview.roughness, abs=1e-5)
        assert mesh["Metallic"] == pytest.approx(part.preview.metallic, abs=1e-6)
        assert mesh["IOR"] == pytest.approx(part.preview.ior, abs=1e-6)  # (1: no specular, the diffuse pole's)


def test_an_avatar_exported_with_its_set_reads_back_as_the_avatar(stage_with_set, tmp_path):
    """An export is a subject too (`--subject a.glb`): with a set beside it, the avatar is still the one read (USD: the
    default prim; glTF: the node gra-mi's export marks); a .glb of several meshes none marked is refused, naming them."""
    import json
    import struct

    from gra_mi.apps.export import export_avatar
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.subject.sequence import load_sequence, tiny_subject

    _, parts, _ = stage_with_set
    seq = tiny_subject(3)
    maps = (np.full((8, 8, 3), 0.5, np.float32), np.full((8, 8, 1), 0.5, np.float32))
    for name in ("a.usdz", "a.glb"):
        export_avatar(tmp_path / name, seq, *maps, set_parts=list(parts.values()))
        np.testing.assert_allclose(load_sequence(tmp_path / name).vertices, seq.vertices, atol=1e-6)
    data = (tmp_path / "a.glb").read_bytes()
    length = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20 : 20 + length])
    del gltf["nodes"][0]["extras"]  # (a file from another tool: nothing says which mesh is the body)
    text = json.dumps(gltf).encode()
    text += b" " * (-len(text) % 4)
    rest = data[20 + length :]
    (tmp_path / "b.glb").write_bytes(
        struct.pack("<4sII", b"glTF", 2, 20 + len(text) + len(rest)) + struct.pack("<I4s", len(text), b"JSON") + text + rest
    )
    with pytest.raises(GraMiInputError, match=r"expected one node with a mesh, found 6 \('avatar', 'set_000'"):
        load_sequence(tmp_path / "b.glb")


def test_a_principled_bsdf_previews_as_its_own_parameters(llvm_variant, tmp_path):
    """A principled BSDF's base colour (a texture's mean per channel: a grey one of 12 texels is not read as 4 RGB
    triples), metallic and roughness, inside a twosided too; another BSDF has none."""
    import mitsuba as mi

    from gra_mi.apps.set_export import principled_preview
    from gra_mi.core.io import write_exr

    write_exr(tmp_path / "grey.exr", np.where(np.arange(12).reshape(3, 4, 1) % 3 == 0, 0.1, 0.4).astype(np.float32))
    write_exr(tmp_path / "rgb.exr", np.tile(np.float32([0.1, 0.2, 0.9]), (2, 2, 1)))
    for name, base in (("grey.exr", (0.3, 0.3, 0.3)), ("rgb.exr", (0.1, 0.2, 0.9))):
        bitmap = {"type": "bitmap", "filename": str(tmp_path / name), "raw": True}
        preview = principled_preview(mi.load_dict({"type": "principled", "base_color": bitmap, "metallic": 0.3, "roughness": 0.2}))
        np.testing.assert_allclose(preview.base_color, base, rtol=1e-6)
        assert preview.metallic == pytest.approx(0.3) and preview.roughness == pytest.approx(0.2) and preview.ior == 1.5
    inner = {"type": "principled", "base_color": {"type": "rgb", "value": [0.2, 0.4, 0.6]}, "roughness": 0.6}
    np.testing.assert_allclose(principled_preview(mi.load_dict({"type": "twosided", "bsdf": inner})).base_color, (0.2, 0.4, 0.6), rtol=1e-6)
    assert principled_preview(mi.load_dict({"type": "diffuse"})) is None


def test_a_metals_preview_reflects_as_much_as_the_metal(llvm_variant):
    """glTF's GGX metal's albedos (F = 1, and Schlick's rise (1 − cos)⁵) against their analytic values for a mirror (1 and
    1/21) and against Mitsuba's principled metal (GGX, Schlick; its separable masking a little darker) at base colour 1
    and 0. A GGX metal that reflects all the light its microfacets meet previews white; one that reflects half of it, a
    little under 0.5 (Schlick's F rises toward grazing, its F does not). A rough Beckmann gold, brighter than any GGX
    metal of its roughness, previews at its own hue's brightest (not red clipped at 1 and the rest left)."""
    import mitsuba as mi

    from gra_mi.apps.set_export import metal_albedos, preview_material
    from gra_mi.capture.set_albedo import shape_albedos

    def plane(bsdf):
        scene = mi.load_dict({"type": "scene", "plane": {"type": "rectangle", "bsdf": bsdf}})
        return scene, scene.shapes()[0]

    assert metal_albedos(0.0) == pytest.approx((1.0, 1 / 21), rel=0.02)
    for roughness in (0.3, 0.55, 0.8):
        full, edge = metal_albedos(roughness)
        for base, expected, tolerance in ((1.0, full, 0.03 * full), (0.0, edge, 0.005)):
            bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": [base] * 3}, "metallic": 1.0, "roughness": roughness}
            assert np.mean(shape_albedos(*plane(bsdf))[1]) == pytest.approx(expected, abs=tolerance), (roughness, base)
    white = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}  # (material "none": F = 1)
    assert min(preview_material(*plane(white)).base_color) > 0.98
    half = preview_material(*plane(white | {"specular_reflectance": {"type": "rgb", "value": [0.5] * 3}}))
    assert half.metallic == 1.0 and 0.44 < min(half.base_color) <= max(half.base_color) < 0.5
    gold = {"type": "roughconductor", "material": "Au", "alpha": 0.3}  # (Beckmann: brighter than a GGX metal can be)
    scene, shape = plane(gold)
    every, (full, edge) = shape_albedos(scene, shape)[1], metal_albedos(round(np.sqrt(0.3), 3))
    unclipped = (every - edge) / (full - edge)
    assert unclipped.max() > 1.0 and max(preview_material(scene, shape).base_color) == pytest.approx(1.0)
    np.testing.assert_allclose(preview_material(scene, shape).base_color, unclipped / unclipped.max(), rtol=1e-6)  # its hue
