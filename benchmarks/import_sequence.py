"""Time and memory of importing a long tracked mesh sequence, one OBJ per frame (a tracker's export, as EasyMocap's
and transforms.json imports read it): the mesh stages of `gra-mi import`, the way it reads and writes them now (each
frame read when used, later frames from their ``v`` lines alone; the subject written a frame at a time) beside the way
it did at c758ef1 (every file parsed whole and held, the sequence stacked, then written), each in its own process.

    .venv/bin/python benchmarks/import_sequence.py [--frames 130,1040] [--write docs/results/import-sequence.md]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, run_measured, table_page
from gra_mi.core.errors import GraMiParameterError

PAPER_FRAMES = 28_420  # frames per camera of the paper's capture

# The import's mesh stages on a folder of OBJs: the floor pass (which reads and checks every frame), then the subject.
STREAMED = """
import json, sys, time
from pathlib import Path
from types import SimpleNamespace
import numpy as np
from gra_mi.capture.mesh_frames import read_meshes
from gra_mi.capture.placement import WorldFrame, _floor, plan_subject
folder, count, out = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
start = time.perf_counter()
source = SimpleNamespace(meshes=read_meshes(folder, count), mesh_metres=lambda p: p, folder=folder)
floor = _floor(source, np.array([0.0, 1.0, 0.0]), 3.0, np.eye(3))
read = time.perf_counter() - start
frame = WorldFrame(np.eye(3), np.array([0.0, -floor, 0.0]), np.array([0.0, 1.0, 0.0]), False, 0.0, 3.0, 0.0)
plan_subject(source, 256).write(source, frame, out)
print(json.dumps({"read": read, "write": time.perf_counter() - start - read}))
"""

# What c758ef1 did with the same files (placement.world_frame and build_sequence, then save_sequence): every file
# parsed whole and held, the positions concatenated for the floor, the sequence stacked and its normals computed.
WHOLE = """
import json, sys, time
from pathlib import Path
import numpy as np
from gra_mi.capture.source_files import read_obj
from gra_mi.subject.sequence import MeshSequence, save_sequence, split_uv_seams, vertex_normals
folder, count, out = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
start = time.perf_counter()
meshes = [read_obj(f) for f in sorted(folder.glob("*.obj"))[:count]]
every = np.concatenate([m.positions for m in meshes])
floor = float((every - [0.0, 1.0, 0.0])[np.linalg.norm(every - [0.0, 1.0, 0.0], axis=1) < 3.0][:, 1].min())
read = time.perf_counter() - start
faces, position_of, uv_of = split_uv_seams(meshes[0].faces, meshes[0].face_uvs)
vertices = np.stack([m.positions[position_of] - [0.0, floor, 0.0] for m in meshes]).astype(np.float32)
labels = [f"pose {k}" for k in range(len(meshes))]
seq = MeshSequence(faces, meshes[0].uvs[uv_of].astype(np.float32), vertices, vertex_normals(vertices, faces), 1.0, labels)
save_sequence(seq, out)
print(json.dumps({"read": read, "write": time.perf_counter() - start - read}))
"""


def obj_folder(folder: Path, walk, frames: int) -> int:
    """``frames`` OBJs of the walk (looped), as a tracker writes them: the same ``vt`` and ``f`` lines in every file."""
    from gra_mi.capture.source_files import write_obj

    folder.mkdir(parents=True, exist_ok=True)
    write_obj(folder, walk.vertices[0], walk.uvs, walk.faces, None)
    lines = (folder / "model.obj").read_text().splitlines(keepends=True)
    (folder / "model.obj").unlink()
    head = "".join(line for line in lines if not line.startswith(("v ", "vt ", "f ")))
    tail = "".join(line for line in lines if line.startswith(("vt ", "f ")))
    for k in range(frames):
        positions = "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in walk.vertices[k % walk.num_frames])
        (folder / f"frame_{k:06d}.obj").write_text(head + positions + tail)
    return sum(f.stat().st_size for f in folder.iterdir())


def differences(a: Path, b: Path) -> float:
    from gra_mi.subject.sequence import load_sequence

    x, y = load_sequence(a), load_sequence(b)
    return max(float(np.abs(np.asarray(x.vertices) - y.vertices).max()), float(np.abs(np.asarray(x.normals) - y.normals).max()))


def measure(run: BenchmarkRun) -> str:
    from gra_mi.subject.anny_body import anny_sequence

    counts = [int(x) for x in run.args.frames.split(",")]
    if min(counts) < 1:
        raise GraMiParameterError("frames", f"frame counts must be positive, got {run.args.frames}")
    walk = anny_sequence(["walk"], 130)
    rows, per_frame = [], {}
    for frames in counts:
        folder = run.work / f"objs_{frames}"
        size = obj_folder(folder, walk, frames) / 2**20
        for way, script in (("whole (c758ef1)", WHOLE), ("streamed", STREAMED)):
            out = run.work / f"{way.split()[0]}_{frames}"
            result = run_measured([sys.executable, "-c", script, str(folder), str(frames), str(out)])
            times = json.loads(result["stdout"])
            per_frame[way] = (times["read"] + times["write"]) / frames, result["peak_mb"]
            same = differences(run.work / f"whole_{frames}", out)
            rows.append(
                (
                    f"{frames:,}",
                    f"{size:,.0f}",
                    way,
                    f"{times['read']:.1f}",
                    f"{times['write']:.1f}",
                    f"{result['peak_mb']:,.0f}",
                    f"{same:g}",
                )
            )
            print(rows[-1], file=sys.stderr, flush=True)
    notes = [
        f"The anny body walking ({walk.num_vertices:,} vertices after the UV seams, {walk.num_frames} frames) looped to "
        "each length, one OBJ per frame (the same `vt` and `f` lines in every file); the import's mesh stages on them: "
        "*read s*: reading and checking every frame and finding the floor; *write s*: the subject's `sequence.npz` and "
        "per-frame PLYs; *peak MB*: the process's own peak resident memory; *vs whole*: the largest difference of any "
        "vertex position or normal from the whole way's sequence (0: the same file contents).",
        f"At the paper's {PAPER_FRAMES:,} frames the largest run's per-frame cost gives "
        + "; ".join(f"{way}: about {PAPER_FRAMES * s / 60:.0f} minutes" for way, (s, _) in per_frame.items())
        + ". The whole way's memory grows with the length (about "
        + f"{(per_frame['whole (c758ef1)'][1] - per_frame['streamed'][1]) / max(counts) * PAPER_FRAMES / 1024:.0f} GB more at "
        + f"{PAPER_FRAMES:,} frames, by the largest run's growth); the streamed way's does not.",
    ]
    columns = ("frames", "OBJs MB", "way", "read s", "write s", "peak MB", "vs whole")
    return table_page("Importing a long tracked mesh sequence", "import_sequence.py", run.stamp("anny walk"), rows, notes, columns)


def arguments(parser) -> None:
    parser.add_argument("--frames", default="130,1040", help="Sequence lengths, comma separated. Default: 130,1040.")


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, mitsuba=False, variant=None)
