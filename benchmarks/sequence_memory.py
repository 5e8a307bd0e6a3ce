"""Memory and time of a long tracked mesh sequence: the same `gra-mi relight` of three frames (start, middle, end)
of the walking body repeated to 130, 2,600 and 28,420 frames (the paper's capture length), from a `sequence.npz`
whose per-frame arrays are compressed (as gra-mi wrote them before they were mapped, and as NumPy's
``savez_compressed`` writes them: read whole) and from one whose arrays are stored (as `save_sequence` writes them
now: mapped, each frame read when it is used).

Each relight is its own process; *peak* is its maximum resident memory (Python, Dr.Jit's LLVM backend and its caches
included), so the 130-frame row is the baseline every process pays.

    .venv/bin/python benchmarks/sequence_memory.py [--frames 130,2600,28420] [--write docs/results/sequence-memory.md]
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, gra_mi_command, run_benchmark, run_measured, table_page
from gra_mi.core.errors import GraMiParameterError


def write_legacy(seq, folder: Path) -> None:
    """``sequence.npz`` with every array compressed, as :func:`save_sequence` wrote it before the frames were mapped."""
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        folder / "sequence.npz", faces=seq.faces, uvs=seq.uvs, vertices=seq.vertices, normals=seq.normals, fps=np.float32(seq.fps),
        frame_labels=np.array(seq.frame_labels), vertex_colors=seq.vertex_colors,
    )  # fmt: skip


def long_scene(folder: Path, walk, frames: int, layout: str) -> Path:
    """A 331-LED, one-camera scene of ``walk`` repeated to ``frames`` frames, its sequence in ``layout``."""
    from dataclasses import replace

    from gra_mi.capture.synthetic import PRESETS
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import write_rig, write_scene_file
    from gra_mi.subject.sequence import ply_name, save_sequence, write_ply

    small = PRESETS["small"]
    stage = default_lightstage(num_leds=331, num_cameras=1, width=small.width, height=small.height, camera_distance=small.camera_distance)
    write_rig(stage, folder / "rig")
    repeat = -(-frames // walk.num_frames)
    seq = replace(
        walk, vertices=np.tile(walk.vertices, (repeat, 1, 1))[:frames], normals=np.tile(walk.normals, (repeat, 1, 1))[:frames],
        frame_labels=(walk.frame_labels * repeat)[:frames],
    )  # fmt: skip
    subject = folder / "subject"
    if layout == "compressed":
        write_legacy(seq, subject)
    else:
        save_sequence(seq, subject, write_plys=False)
    for t in sorted({0, frames // 2, frames - 1}):  # the scene file loads the first frame's PLY; set_frame the others
        write_ply(subject / "frames" / ply_name(t), seq.vertices[t], seq.normals[t], seq.uvs, seq.faces, seq.vertex_colors)
    return write_scene_file(folder / "scene.xml", folder / "rig", subject)


def relight(scene: Path, frames: int, envmap: Path, out: Path) -> dict:
    picked = ",".join(str(t) for t in sorted({0, frames // 2, frames - 1}))
    return run_measured(
        gra_mi_command("relight", str(scene), "--frames", picked, "--envmap", str(envmap), "--out", str(out), "--uv-resolution", "256")
    )


def render_difference(reference: Path, relit: Path) -> float:
    """The largest difference of any pixel between two relights' EXRs (every file of ``reference`` must be there)."""
    from gra_mi.core.io import read_exr

    names = sorted(p.relative_to(reference) for p in reference.rglob("*.exr"))
    if not names:
        raise RuntimeError(f"no EXR in {reference}")
    return max(float(np.abs(read_exr(reference / n) - read_exr(relit / n)).max()) for n in names)


def measure(run: BenchmarkRun) -> str:
    from gra_mi.core.io import write_exr
    from gra_mi.stage.envmap_library import reference_map
    from gra_mi.subject.anny_body import anny_sequence

    counts = [int(x) for x in run.args.frames.split(",")]
    if min(counts) < 1:
        raise GraMiParameterError("frames", f"frame counts must be positive, got {run.args.frames}")
    walk = anny_sequence(["walk"], 130)
    envmap = run.work / "sun.exr"
    write_exr(envmap, reference_map("sun", 64))
    rows = []
    for frames in counts:
        for layout in ("compressed", "stored"):
            folder = run.work / f"{layout}_{frames}"
            start = time.perf_counter()
            scene = long_scene(folder, walk, frames, layout)
            written = time.perf_counter() - start
            result = relight(scene, frames, envmap, folder / "relit")
            size = (folder / "subject" / "sequence.npz").stat().st_size / 2**20
            differs = render_difference(run.work / f"compressed_{frames}" / "relit", folder / "relit")
            rows.append(
                (
                    f"{frames:,}",
                    layout,
                    f"{size:,.0f}",
                    f"{written:.1f}",
                    f"{result['seconds']:.1f}",
                    f"{result['peak_mb']:,.0f}",
                    f"{differs:g}",
                )
            )
            print(rows[-1], file=sys.stderr, flush=True)
    notes = [
        f"The anny body walking ({walk.num_vertices:,} vertices, {walk.num_frames} frames) repeated to each length; "
        "`gra-mi relight SCENE --frames first,middle,last --envmap sun.exr --uv-resolution 256`, one camera of `small`'s rig "
        "(331 LEDs, 256×135). *write s*: writing the sequence (this script, in its process); *relight s* and *peak MB*: "
        "the relight's own process, from its start to its end (loading, three visibility traces, the renders); "
        "*renders vs compressed*: the largest difference of any pixel of the three EXRs from the compressed run's "
        "(0: the same images).",
    ]
    columns = ("frames", "per-frame arrays", "sequence.npz MB", "write s", "relight s", "peak MB", "renders vs compressed")
    return table_page("A long tracked mesh sequence: mapped, not read", "sequence_memory.py", run.stamp("anny walk"), rows, notes, columns)


def arguments(parser) -> None:
    parser.add_argument(
        "--frames", default="130,2600,28420", help="Sequence lengths, comma separated. Default: 130,2600,28420 (the paper's capture)."
    )


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments)
