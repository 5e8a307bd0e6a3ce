"""Tracked mesh sequences: the tiny procedural subject, the anny body, files and validation."""

from __future__ import annotations

import zipfile

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


def long_tiny_subject(frames: int) -> MeshSequence:
    """The tiny subject's 8-frame loop repeated to ``frames`` frames."""
    from dataclasses import replace

    seq, repeat = tiny_subject(8), -(-frames // 8)
    tile = lambda a: np.tile(a, (repeat, 1, 1))[:frames]  # noqa: E731
    return replace(seq, vertices=tile(seq.vertices), normals=tile(seq.normals), frame_labels=(seq.frame_labels * repeat)[:frames])


def write_archive(path, seq: MeshSequence, writer=np.savez, **arrays) -> None:
    """A sequence.npz written by NumPy itself, as another tool would write it (``arrays`` replace the sequence's)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = {"faces": seq.faces, "uvs": seq.uvs, "vertices": seq.vertices, "normals": seq.normals} | arrays
    writer(path, **fields)


def test_a_saved_sequence_is_mapped_not_read(tmp_path, monkeypatch):
    import tracemalloc

    import gra_mi.subject.sequence as sequence

    monkeypatch.setattr(sequence, "CHUNK_BYTES", 1 << 16)  # validation reads 64 kB at a time: many chunks
    seq = long_tiny_subject(1500)
    save_sequence(seq, tmp_path / "s", write_plys=False)
    tracemalloc.start()
    try:
        back = load_sequence(tmp_path / "s")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert isinstance(back.vertices, np.memmap) and isinstance(back.normals, np.memmap)
    # aligned as NumPy's own allocations: Embree refuses vertex data that is not (it warned, and traced nothing)
    assert back.vertices.ctypes.data % 64 == 0 and back.normals.ctypes.data % 64 == 0
    whole = seq.vertices.nbytes + seq.normals.nbytes  # what reading the frames would allocate
    assert peak < 0.1 * whole, f"loading allocated {peak} bytes for {whole} bytes of frames"
    np.testing.assert_array_equal(back.vertices, seq.vertices)
    np.testing.assert_array_equal(back.normals, seq.normals)
    with pytest.raises(ValueError, match="read-only"):  # a caller cannot write into the user's file through the map
        back.vertices[0, 0, 0] = 1.0
    with zipfile.ZipFile(tmp_path / "s" / "sequence.npz") as archive:  # a valid zip: every entry's CRC-32 checks
        assert archive.testzip() is None
    with np.load(tmp_path / "s" / "sequence.npz") as plain:  # still an archive NumPy itself reads
        np.testing.assert_array_equal(plain["vertices"], seq.vertices)
    save_sequence(back, tmp_path / "s", write_plys=False)  # over the file it is mapped from: replaced, not overwritten
    np.testing.assert_array_equal(load_sequence(tmp_path / "s").normals, seq.normals)


def test_a_sequence_is_written_one_frame_at_a_time(tmp_path):
    """write_sequence takes frames from a generator: writing 1,500 frames allocates about one (the vertices go into the
    archive as they come, the normals through a file), and the result is what save_sequence writes of the whole."""
    import tracemalloc

    from gra_mi.subject.sequence import SequenceLayout, write_sequence

    seq = long_tiny_subject(1500)
    layout = SequenceLayout(seq.faces, seq.uvs, seq.num_frames, seq.fps, seq.frame_labels)
    frames = ((seq.vertices[t].copy(), None) for t in range(seq.num_frames))  # normals computed per frame
    tracemalloc.start()
    try:
        write_sequence(tmp_path / "streamed", layout, frames, write_plys=False)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    whole = seq.vertices.nbytes + seq.normals.nbytes
    assert peak < 0.1 * whole, f"writing allocated {peak} bytes for {whole} bytes of frames"
    back = load_sequence(tmp_path / "streamed")
    assert isinstance(back.vertices, np.memmap) and back.vertices.ctypes.data % 64 == 0 and back.normals.ctypes.data % 64 == 0
    np.testing.assert_array_equal(back.vertices, seq.vertices)
    np.testing.assert_allclose(back.normals, seq.normals, atol=1e-6)
    assert back.frame_labels == seq.frame_labels and [p.name for p in (tmp_path / "streamed").iterdir()] == ["sequence.npz"]


@pytest.mark.parametrize(
    "frames, needle",
    [
        (lambda v: [(v[0], None)], "1 frames given for a sequence of 3"),
        (lambda v: [(v[0], None)] * 4, "more frames given"),
        (lambda v: [(v[0], None), (v[1, :-1], None), (v[2], None)], "frame 1: expected"),
        (lambda v: [(v[0], None), (v[1], None), (np.where(v[2] > 0, np.nan, v[2]), None)], "frame 2"),
    ],
)
def test_a_streamed_sequence_names_its_bad_frame_and_leaves_nothing(tmp_path, frames, needle):
    from gra_mi.subject.sequence import SequenceLayout, write_sequence

    seq = tiny_subject(3)
    layout = SequenceLayout(seq.faces, seq.uvs, 3)
    with pytest.raises(GraMiInputError, match=needle):
        write_sequence(tmp_path / "s", layout, frames(seq.vertices), write_plys=False, source="meshes/")
    assert not (tmp_path / "s" / "sequence.npz").exists() and not any(p.name.startswith(".") for p in (tmp_path / "s").iterdir())


def test_a_mapped_frame_traces_as_the_frame_in_memory(tmp_path, variant):
    """A mapped frame moved into a Mitsuba mesh (as LightstageScene.set_frame does) is hit where the same frame read
    into memory is: unaligned mapped data once reached Embree, which refused it, and every ray missed."""
    import drjit as dr
    import mitsuba as mi

    seq = tiny_subject(6)
    save_sequence(seq, tmp_path / "s")
    mapped = load_sequence(tmp_path / "s")
    scene = mi.load_dict({"type": "scene", "body": {"type": "ply", "filename": str(tmp_path / "s" / "frames" / "frame_0000.ply")}})
    params = mi.traverse(scene)
    origins = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 24), np.linspace(0.3, 1.9, 48), [2.0]), -1).reshape(-1, 3)
    rays = mi.Ray3f(mi.Point3f(*origins.T.astype(np.float32)), mi.Vector3f(0, 0, -1))
    for frame in (3, 5):
        hits = []
        for source in (seq.vertices[frame].copy(), mapped.vertices[frame]):
            params["body.vertex_positions"] = mi.Float(source.ravel())
            params.update()
            hits.append(np.array(scene.ray_intersect(rays).t))
        dr.sync_thread()
        assert np.isfinite(hits[0]).sum() > 100
        np.testing.assert_array_equal(hits[1], hits[0])


def test_an_edit_in_the_middle_of_a_long_sequence_changes_its_provenance_id(tmp_path):
    """A provenance id hashes a large file's size and ends only. An edit anywhere in the frames still reaches the end of
    the archive: the zip's central directory, its last bytes, holds every entry's CRC-32."""
    from dataclasses import replace

    from gra_mi.core.provenance import content_id

    seq = long_tiny_subject(1500)
    vertices = seq.vertices.copy()
    vertices[700, 10] += 0.01  # a re-tracked vertex in the middle of a 5 MB array: the same size, the same ends
    save_sequence(seq, tmp_path / "a", write_plys=False)
    save_sequence(replace(seq, vertices=vertices), tmp_path / "b", write_plys=False)
    a, b = ((tmp_path / k / "sequence.npz").read_bytes() for k in "ab")
    assert len(a) == len(b) and a[1 << 16 : -(1 << 16)] != b[1 << 16 : -(1 << 16)]
    assert content_id(tmp_path / "a") != content_id(tmp_path / "b")
    save_sequence(load_sequence(tmp_path / "a"), tmp_path / "c", write_plys=False)  # the same frames, mapped: the same id
    assert content_id(tmp_path / "c") == content_id(tmp_path / "a")


def test_extent_of_a_mapped_sequence_matches_the_whole_array(tmp_path, monkeypatch):
    import gra_mi.subject.sequence as sequence

    monkeypatch.setattr(sequence, "CHUNK_BYTES", 1 << 14)
    seq = long_tiny_subject(300)
    save_sequence(seq, tmp_path / "s", write_plys=False)
    low, high, mean = sequence.extent(load_sequence(tmp_path / "s").vertices)
    whole = seq.vertices.astype(np.float64).reshape(-1, 3)
    np.testing.assert_array_equal(low, whole.min(axis=0))
    np.testing.assert_array_equal(high, whole.max(axis=0))
    np.testing.assert_allclose(mean, whole.mean(axis=0), rtol=1e-12)


def test_archives_from_other_writers_load_whole(tmp_path):
    seq = tiny_subject(5)
    cases = {
        "compressed": {"writer": np.savez_compressed},  # gra-mi's own files before the frames were mapped
        "float64": {"vertices": seq.vertices.astype(np.float64)},
        "fortran": {"vertices": np.asfortranarray(seq.vertices)},
    }
    for name, case in cases.items():
        write_archive(tmp_path / name / "sequence.npz", seq, **case)
        back = load_sequence(tmp_path / name)
        assert not isinstance(back.vertices, np.memmap), name
        np.testing.assert_array_equal(back.vertices, seq.vertices)
        np.testing.assert_array_equal(back.normals, seq.normals)
    for frames in range(1, 9):  # np.savez's stored entries start wherever the zip puts them: mapped only if aligned
        write_archive(tmp_path / f"plain{frames}" / "sequence.npz", tiny_subject(frames))
        back = load_sequence(tmp_path / f"plain{frames}")
        assert not isinstance(back.vertices, np.memmap) or back.vertices.ctypes.data % 64 == 0
        np.testing.assert_array_equal(back.vertices, tiny_subject(frames).vertices)


def test_a_late_bad_frame_of_a_mapped_sequence_is_named(tmp_path, monkeypatch):
    import gra_mi.subject.sequence as sequence

    monkeypatch.setattr(sequence, "CHUNK_BYTES", 1 << 16)
    seq = long_tiny_subject(900)
    vertices, normals = seq.vertices.copy(), seq.normals.copy()
    vertices[877, 12, 2] = np.inf
    normals[641, 3] = 0.0
    write_archive(tmp_path / "nan" / "sequence.npz", seq, vertices=vertices)
    with pytest.raises(GraMiInputError, match="frame 877"):
        load_sequence(tmp_path / "nan")
    write_archive(tmp_path / "flat" / "sequence.npz", seq, normals=normals)
    with pytest.raises(GraMiInputError, match="first in frame 641"):
        load_sequence(tmp_path / "flat")


def test_a_clip_checks_its_own_frames_only(tmp_path, monkeypatch):
    """A command that uses a few frames of a long sequence (relight, export) loads it without reading every frame and
    checks those it uses: a bad frame elsewhere does not stop it, a bad frame it uses is named with its file; most of
    the frames are checked in the chunked pass. Through the CLI: an export of a clip beside the bad frame runs, one
    that takes it in is refused."""
    import gra_mi.subject.sequence as sequence
    from gra_mi.subject.sequence import check_frames

    reads = []
    original = sequence.frame_chunks
    monkeypatch.setattr(sequence, "frame_chunks", lambda array: (reads.append(1), original(array))[1])
    seq = long_tiny_subject(900)
    vertices = seq.vertices.copy()
    vertices[877, 12, 2] = np.nan
    write_archive(tmp_path / "nan" / "sequence.npz", seq, vertices=vertices)
    reads.clear()
    clip = load_sequence(tmp_path / "nan", every_frame=False)
    assert not reads
    check_frames(clip, [0, 5, 876])
    with pytest.raises(GraMiInputError, match=r"nan/sequence.npz.*frame 877"):
        check_frames(clip, [3, 877])
    with pytest.raises(GraMiInputError, match="frame 877"):
        check_frames(clip, list(range(0, 900, 2)) + [877])
    assert reads  # most of the frames: one chunked pass
    with pytest.raises(GraMiInputError, match=r"nan/sequence.npz.*frame 877"):  # the platform's extent reads every frame
        sequence.extent(clip.vertices, clip.origin)
    from gra_mi.cli.texture_commands import relit_frames

    assert relit_frames([878, 5000], 900, "microfacet") == [878]
    assert relit_frames([878, 1], 900, "relightnet") == [0, 1, 876, 877, 878]  # RelightNet reads the frames before
    from gra_mi.cli.main import main
    from gra_mi.core.io import write_exr

    write_exr(tmp_path / "albedo.exr", np.full((16, 16, 3), 0.5, np.float32))
    write_exr(tmp_path / "rough.exr", np.full((16, 16, 1), 0.5, np.float32))
    args = [
        "export",
        "--subject",
        str(tmp_path / "nan"),
        "--albedo",
        str(tmp_path / "albedo.exr"),
        "--roughness",
        str(tmp_path / "rough.exr"),
    ]
    assert main([*args, "--out", str(tmp_path / "clip.glb"), "--frames", "860:870"]) == 0
    assert main([*args, "--out", str(tmp_path / "bad.glb"), "--frames", "870:880"]) == 2 and not (tmp_path / "bad.glb").exists()


def test_a_mapped_archive_that_lies_about_its_size_is_refused(tmp_path):
    import io
    import zipfile

    seq = tiny_subject(4)
    path = tmp_path / "lies" / "sequence.npz"
    write_archive(path, seq)
    header = io.BytesIO()  # the vertices entry's .npy header claims 40 frames; its data holds 4
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (40, seq.num_vertices, 3)})
    with zipfile.ZipFile(path, "w") as archive:
        for key in ("faces", "uvs", "normals"):
            buffer = io.BytesIO()
            np.save(buffer, getattr(seq, key))
            archive.writestr(f"{key}.npy", buffer.getvalue())
        archive.writestr("vertices.npy", header.getvalue() + seq.vertices.tobytes())
    with pytest.raises(GraMiInputError, match="holds"):
        load_sequence(path.parent)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(GraMiInputError, match="sequence.npz"):
        load_sequence(path.parent)


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
    # `gra-mi subject` poses and writes a frame at a time: the same file contents as the whole sequence
    from gra_mi.cli import main

    assert main(["subject", "--kind", "anny", "--clips", ",".join(clips), "--frames-per-clip", "4", "--out", str(tmp_path / "cli")]) == 0
    written = load_sequence(tmp_path / "cli")
    np.testing.assert_array_equal(written.vertices, seq.vertices)
    np.testing.assert_array_equal(written.normals, seq.normals)
    assert written.frame_labels == seq.frame_labels and np.array_equal(written.vertex_colors, seq.vertex_colors)
