"""Texture editing and glTF export."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from gra_mi.apps.texture_edit import edit_albedo
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_exr, write_exr

from .conftest import SCENES
from .test_cli import run_cli

TINY = SCENES / "tiny_lightstage.xml"


def test_mask_and_colour_edit_changes_only_the_mask():
    albedo = np.full((8, 8, 3), 0.4, np.float32)
    mask = np.zeros((8, 8, 1), np.float32)
    mask[2:4, 5:7] = 1.0
    edited = edit_albedo(albedo, mask=mask, color=(0.9, 0.1, 0.1))
    np.testing.assert_allclose(edited[2:4, 5:7], [[[0.9, 0.1, 0.1]] * 2] * 2, atol=1e-6)
    untouched = np.ones((8, 8), bool)
    untouched[2:4, 5:7] = False
    np.testing.assert_array_equal(edited[untouched], albedo[untouched])
    half = edit_albedo(albedo, mask=mask, color=(0.9, 0.1, 0.1), opacity=0.5)
    np.testing.assert_allclose(half[2, 5], [0.65, 0.25, 0.25], atol=1e-6)
    with pytest.raises(GraMiInputError):
        edit_albedo(albedo, mask=mask, color=(2.0, 0.0, 0.0))
    with pytest.raises(GraMiInputError):
        edit_albedo(albedo)


def test_edit_then_rerender_changes_the_painted_region(tmp_path):
    import imageio.v3 as iio

    albedo = np.full((64, 64, 3), 0.5, np.float32)
    write_exr(tmp_path / "albedo.exr", albedo)
    # Paint the arm's chart (right half of the tiny subject's atlas) red with an RGBA PNG layer.
    layer = np.zeros((64, 64, 4), np.uint8)
    layer[:, 33:, :] = [230, 20, 20, 255]
    iio.imwrite(tmp_path / "paint.png", layer)
    out = run_cli(
        "edit-texture",
        "--albedo",
        str(tmp_path / "albedo.exr"),
        "--image",
        str(tmp_path / "paint.png"),
        "--out",
        str(tmp_path / "edited.exr"),
    )
    assert out.returncode == 0, out.stderr
    edited = read_exr(tmp_path / "edited.exr")
    assert edited[10, 50, 0] > 0.7 and edited[10, 50, 1] < 0.02 and edited[10, 10, 0] == pytest.approx(0.5)
    renders = {}
    for name in ("albedo", "edited"):
        r = run_cli(
            "relight", str(TINY), "--frames", "0", "--olat", "20", "--albedo", str(tmp_path / f"{name}.exr"), "--out", str(tmp_path / name)
        )
        assert r.returncode == 0, r.stderr
        renders[name] = read_exr(tmp_path / name / "olat020" / "cam00" / "frame_0000.exr")
    change = np.abs(renders["edited"] - renders["albedo"])[..., :3].sum(axis=-1)
    assert change.max() > 0 and (change > 1e-4).mean() < 0.5, "only the arm changes"
    bad = run_cli(
        "edit-texture", "--albedo", str(tmp_path / "albedo.exr"), "--mask", str(tmp_path / "paint.png"), "--out", str(tmp_path / "x.exr")
    )
    assert bad.returncode == 2 and "--color" in bad.stderr


def _glb_json(path):
    data = path.read_bytes()
    magic, version, length = struct.unpack("<4sII", data[:12])
    assert magic == b"glTF" and version == 2 and length == len(data)
    chunk_len, chunk_type = struct.unpack("<I4s", data[12:20])
    assert chunk_type == b"JSON"
    return json.loads(data[20 : 20 + chunk_len])


def test_export_gltf_opens_and_carries_textures_and_frames(tmp_path):
    import trimesh

    from gra_mi.subject.sequence import tiny_subject

    seq = tiny_subject(4)
    from gra_mi.subject.sequence import save_sequence

    save_sequence(seq, tmp_path / "subject")
    write_exr(tmp_path / "albedo.exr", np.full((16, 16, 3), 0.3, np.float32))
    write_exr(tmp_path / "rough.exr", np.full((16, 16, 1), 0.6, np.float32))
    out = run_cli(
        "export",
        "--out",
        str(tmp_path / "avatar.glb"),
        "--subject",
        str(tmp_path / "subject"),
        "--albedo",
        str(tmp_path / "albedo.exr"),
        "--roughness",
        str(tmp_path / "rough.exr"),
    )
    assert out.returncode == 0, out.stderr
    gltf = _glb_json(tmp_path / "avatar.glb")
    primitive = gltf["meshes"][0]["primitives"][0]
    assert len(primitive["targets"]) == 3 and gltf["animations"][0]["channels"][0]["target"]["path"] == "weights"
    material = gltf["materials"][0]["pbrMetallicRoughness"]
    assert "baseColorTexture" in material and "metallicRoughnessTexture" in material
    scene = trimesh.load(tmp_path / "avatar.glb")
    mesh = next(iter(scene.geometry.values()))
    assert len(mesh.vertices) == seq.num_vertices and len(mesh.faces) == len(seq.faces)
    np.testing.assert_allclose(np.sort(mesh.vertices[:, 1]), np.sort(seq.vertices[0][:, 1]), atol=1e-5)
    image = mesh.visual.material.baseColorTexture
    assert np.asarray(image).shape[:2] == (16, 16)
