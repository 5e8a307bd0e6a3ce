"""A source's tracked mesh, one file per mesh frame (gra_mi/capture/mesh_frames.py): read when used, each frame's
positions as a full parse reads them, a frame with another topology or a broken line named, and a long sequence
imported holding one frame at a time."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from gra_mi.capture.mesh_frames import MeshFrames, read_meshes
from gra_mi.capture.source_files import read_obj, write_obj
from gra_mi.core.errors import GraMiInputError
from gra_mi.subject.sequence import tiny_subject


def obj_sequence(folder: Path, frames: int) -> tuple[list[Path], np.ndarray]:
    """The tiny subject's frames as one OBJ each, as a tracker exports them: the same lines but for the ``v`` ones."""
    seq = tiny_subject(8)
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for k in range(frames):
        write_obj(folder, seq.vertices[k % 8], seq.uvs, seq.faces, None)
        files.append((folder / "model.obj").rename(folder / f"frame_{k:05d}.obj"))
    return files, seq.vertices


def test_later_frames_read_their_positions_alone_and_match_a_full_parse(tmp_path, monkeypatch):
    import gra_mi.capture.mesh_frames as mesh_frames

    files, _ = obj_sequence(tmp_path / "meshes", 6)
    full_reads = []
    monkeypatch.setattr(mesh_frames, "read_mesh", lambda path: full_reads.append(path) or read_obj(path))
    meshes = read_meshes(tmp_path / "meshes", 6)
    for k, path in enumerate(files):
        np.testing.assert_array_equal(meshes.positions(k), read_obj(path).positions)
    assert full_reads == [files[0]]  # the first file alone was parsed whole


def test_a_frame_written_otherwise_is_read_whole_and_still_right(tmp_path):
    files, _ = obj_sequence(tmp_path / "meshes", 3)
    text = files[1].read_text().splitlines()
    # vertex colours after the positions, and a comment: read whole, the same positions
    files[1].write_text("# exported later\n" + "\n".join(line + " 0.5 0.5 0.5" if line.startswith("v ") else line for line in text))
    meshes = MeshFrames(files)
    np.testing.assert_array_equal(meshes.positions(1), read_obj(files[1]).positions)


def _reversed(face: str) -> str:
    return " ".join(["f", *face.split()[:0:-1]])


@pytest.mark.parametrize(
    "edit, needles",
    [
        (
            lambda lines: [_reversed(line) if line.startswith("f ") else line for line in lines],
            ["frame_00002.obj", "another topology", "frame_00000.obj"],
        ),
        (
            lambda lines: [line.replace("v ", "v nan ", 1) if i == 9 else line for i, line in enumerate(lines)],
            ["frame_00002.obj", "line 10"],
        ),
        (lambda lines: lines[:-40], ["frame_00002.obj", "another topology"]),
    ],
    ids=["faces changed", "a NaN position", "truncated"],
)
def test_a_bad_frame_is_named_by_its_file(tmp_path, edit, needles):
    files, _ = obj_sequence(tmp_path / "meshes", 4)
    files[2].write_text("\n".join(edit(files[2].read_text().splitlines())) + "\n")
    meshes = MeshFrames(files)
    meshes.positions(1)
    with pytest.raises(GraMiInputError) as info:
        meshes.positions(2)
    for needle in needles:
        assert needle in str(info.value)


def test_a_folder_of_frames_is_in_the_numbers_order_and_one_name_per_frame(tmp_path):
    from gra_mi.capture.mesh_frames import mesh_files_in_order

    for name in ("frame_10.obj", "frame_2.obj", "frame_1.obj", "notes.txt", "frame_0.ply"):
        (tmp_path / name).write_text("")
    assert [p.name for p in mesh_files_in_order(tmp_path)] == ["frame_0.ply", "frame_1.obj", "frame_2.obj", "frame_10.obj"]
    (tmp_path / "frame_02.ply").write_text("")
    with pytest.raises(GraMiInputError, match="frame_02.ply and frame_2.obj are one mesh frame"):
        read_meshes(tmp_path, 3)


def test_ply_frames_are_compared_by_topology(tmp_path):
    import trimesh

    seq = tiny_subject(2)
    files = []
    for k, faces in enumerate((seq.faces, seq.faces[::-1])):
        files.append(tmp_path / f"f{k}.ply")
        trimesh.Trimesh(seq.vertices[k], faces, process=False).export(files[-1])
    meshes = MeshFrames(files)
    np.testing.assert_allclose(meshes.positions(0), seq.vertices[0], atol=1e-6)
    with pytest.raises(GraMiInputError, match="another topology"):
        meshes.positions(1)


def test_a_long_mesh_sequence_is_written_holding_one_frame(tmp_path):
    """The import's subject (SubjectPlan.write) from 1,500 OBJ frames: what it allocates is about one frame's worth, not
    the sequence's, and every frame arrives in the world frame."""
    import tracemalloc

    from gra_mi.capture.placement import WorldFrame, plan_subject
    from gra_mi.subject.sequence import load_sequence

    count = 1500
    _, truth = obj_sequence(tmp_path / "meshes", count)
    source = SimpleNamespace(meshes=read_meshes(tmp_path / "meshes", count), mesh_metres=lambda p: p * 0.001, folder=tmp_path)
    frame = WorldFrame(np.eye(3), np.array([0.0, 0.5, 0.0]), np.array([0.0, 1.0, 0.0]), False, 0.0, 2.0, 0.0)
    subject = plan_subject(source, 64)
    tracemalloc.start()
    try:
        subject.write(source, frame, tmp_path / "subject")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    back = load_sequence(tmp_path / "subject")
    whole = 2 * back.vertices.nbytes  # vertices and normals
    assert back.num_frames == count and peak < 0.1 * whole, (peak, whole)
    for k in (0, 1, count - 1):
        np.testing.assert_allclose(back.vertices[k], truth[k % 8][subject.position_of] * 0.001 + [0, 0.5, 0], atol=1e-6)
