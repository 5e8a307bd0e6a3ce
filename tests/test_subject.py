"""Tracked mesh sequences: the tiny procedural subject, the anny body, files and validation."""

from __future__ import annotations

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError
from gra_mi.subject.sequence import MeshSequence, load_sequence, save_sequence, sequence_from_frames, tiny_subject, vertex_normals

from .conftest import SCENES


def check_sequence(seq: MeshSequence) -> None:
    assert seq.vertices.shape[1:] == (seq.num_vertices, 3)
    assert np.isfinite(seq.vertices).all() and np.isfinite(seq.normals).all()
    assert seq.uvs.min() >= 0 and seq.uvs.max() <= 1
    np.testing.assert_allclose(np.linalg.norm(seq.normals, axis=-1), 1.0, atol=1e-4)
    assert seq.faces.min() >= 0 and seq.faces.max() < seq.num_vertices


def test_tiny_subject():
    seq = tiny_subject(8)
    check_sequence(seq)
    assert 300 <= len(seq.faces) <= 600
    assert not np.allclose(seq.vertices[0], seq.vertices[2]), "it moves"
    # Normals point outward: away from the torso centre for torso vertices.
    torso = slice(0, 11 * 17)
    outward = seq.vertices[0, torso] - np.array([0.0, 1.0, 0.0])
    assert (np.sum(outward * seq.normals[0, torso], axis=1) > 0).mean() > 0.95


def test_vertex_normals_of_a_tetrahedron_point_outward():
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
    n = vertex_normals(v, f)
    np.testing.assert_allclose(n, v / np.sqrt(3), atol=1e-6)


def test_save_load_round_trip(tmp_path):
    seq = tiny_subject(4)
    save_sequence(seq, tmp_path / "s")
    back = load_sequence(tmp_path / "s")
    np.testing.assert_array_equal(back.vertices, seq.vertices)
    np.testing.assert_array_equal(back.faces, seq.faces)
    assert back.frame_labels == seq.frame_labels
    assert sorted(p.name for p in (tmp_path / "s" / "frames").iterdir()) == [f"frame_{i:04d}.ply" for i in range(4)]


def test_ply_loads_in_mitsuba_with_uvs_and_normals(tmp_path, variant):
    import mitsuba as mi

    seq = tiny_subject(2)
    save_sequence(seq, tmp_path / "s")
    mesh = mi.load_dict({"type": "ply", "filename": str(tmp_path / "s" / "frames" / "frame_0001.ply"), "face_normals": False})
    params = mi.traverse(mesh)
    np.testing.assert_allclose(np.array(params["vertex_positions"]).reshape(-1, 3), seq.vertices[1], atol=1e-6)
    np.testing.assert_allclose(np.array(params["vertex_texcoords"]).reshape(-1, 2), seq.uvs, atol=1e-6)
    np.testing.assert_allclose(np.array(params["vertex_normals"]).reshape(-1, 3), seq.normals[1], atol=1e-5)


def test_bad_sequences_are_rejected(tmp_path):
    seq = tiny_subject(3)
    frames = list(seq.vertices)
    frames[1] = frames[1][:-1]
    with pytest.raises(GraMiInputError, match="vertex count changes across frames"):
        sequence_from_frames(frames, seq.faces, seq.uvs)
    frames = list(seq.vertices.copy())
    frames[2][7, 1] = np.nan
    with pytest.raises(GraMiInputError, match="frame 2"):
        sequence_from_frames(frames, seq.faces, seq.uvs)
    with pytest.raises(GraMiInputError, match="UVs"):
        sequence_from_frames(list(seq.vertices), seq.faces, seq.uvs + 1.5)
    with pytest.raises(GraMiInputError, match="not found"):
        load_sequence(tmp_path / "nothing")


def test_anny_body_sequence(tmp_path, llvm_variant):
    # Builds the real anny body (about 1.5 minutes the first time on a fresh machine, then cached).
    from gra_mi.subject.anny_body import MOTION_CLIPS, anny_sequence

    clips = ["walk", "arm_raise", "turn", "squat", "march"]
    seq = anny_sequence(clips, frames_per_clip=4)
    check_sequence(seq)
    assert seq.num_frames == 20 and seq.frame_labels == [c for c in clips for _ in range(4)]
    assert seq.num_vertices > 10000 and len(seq.faces) > 20000
    lo = seq.vertices.min(axis=(0, 1))
    assert abs(lo[1]) < 1e-6, "feet on the floor"
    assert 1.4 < seq.vertices[0, :, 1].max() < 2.1, "standing height in metres, +Y up"
    # Every clip starts at the rest pose, so clips loop and join without jumps.
    for k in range(1, 5):
        if clips[k] != "turn":
            np.testing.assert_allclose(seq.vertices[4 * k], seq.vertices[0], atol=1e-5)
    # Looping: the frame after the last of a clip is its first, so the last frame is close to the first.
    step = np.abs(seq.vertices[1] - seq.vertices[0]).max()
    assert np.abs(seq.vertices[3] - seq.vertices[0]).max() < 1.5 * step + 1e-6
    # The arm raise lifts the hands above the head at mid-clip.
    mid = seq.vertices[4 + 2]
    assert mid[:, 1].max() > seq.vertices[0, :, 1].max() + 0.05
    # The march lifts a knee (a quarter into the clip) and stands at full height on the other leg.
    lifted, rest = seq.vertices[16 + 1], seq.vertices[0]
    knees = [(v[:, 1] > 0.35) & (v[:, 1] < 0.7) for v in (lifted, rest)]  # thigh and knee height
    assert np.ptp(lifted[:, 1]) > 0.97 * np.ptp(rest[:, 1]) and lifted[knees[0], 2].max() > rest[knees[1], 2].max() + 0.2
    assert set(MOTION_CLIPS) >= set(clips)
    # The body faces +Z: the toes are in front of the heels.
    feet = seq.vertices[0][seq.vertices[0, :, 1] < 0.03]
    assert feet[:, 2].max() > 0.1 and feet[:, 2].max() > -feet[:, 2].min()

    # The real scene file renders the animated body inside the default lightstage.
    from gra_mi.stage.lightstage import uniform_pattern
    from gra_mi.stage.scene import LightstageScene, render

    save_sequence(seq, tmp_path / "anny")
    ls = LightstageScene.load(SCENES / "body_lightstage.xml", frame=9, spp=1, subject=str(tmp_path / "anny"))
    ls.set_pattern(uniform_pattern(ls.stage, 0.5))
    image = render(ls, "cam05", spp=2)
    assert image.shape == (540, 1024, 4) and 0.02 < (image[..., 3] > 0.5).mean() < 0.5
