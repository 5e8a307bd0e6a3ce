"""Does a real renderer see the exported avatar as gra-mi does? Blender (Cycles, direct light only) renders the
exported USD or .glb under an environment map from a capture camera; Mitsuba renders the same mesh and maps with
``gra_microfacet`` (or ``diffuse``, to separate the material model from the handover) under the same map as an
``envmap`` emitter (``path``, ``max_depth`` 2). :func:`agreement` scores one against the other.

Blender runs in its own process (:mod:`gra_mi.eval.blender_job`): ``bpy`` ships its own USD and NumPy, which must
not meet usd-core's and gra-mi's in one interpreter. :func:`find_blender` says where it is looked for.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_exr, write_exr
from gra_mi.core.metrics import display_psnr
from gra_mi.stage.lightstage import Camera
from gra_mi.stage.scene import camera_sensor_dict
from gra_mi.subject.sequence import MeshSequence, write_ply

BLENDER_ENV = "GRA_MI_BLENDER"
"""A Python that imports ``bpy``, or a ``blender`` executable; default: ``.venv-blender/bin/python`` of the checkout
(``scripts/setup.sh`` makes it), then ``blender`` on PATH."""
BLENDER_VENV = Path(__file__).resolve().parents[2] / ".venv-blender" / "bin" / "python"
JOB_SCRIPT = Path(__file__).with_name("blender_job.py")


def find_blender() -> list[str] | None:
    """The command prefix that runs :data:`JOB_SCRIPT` with a job file appended, or None where no Blender is found."""
    chosen = os.environ.get(BLENDER_ENV) or (str(BLENDER_VENV) if BLENDER_VENV.is_file() else shutil.which("blender"))
    if not chosen:
        return None
    if Path(chosen).name.startswith("blender"):
        return [chosen, "-b", "--factory-startup", "--python", str(JOB_SCRIPT), "--"]
    return [chosen, "-I", str(JOB_SCRIPT)]  # -I: nothing from the working folder shadows Blender's add-ons


def _run_job(job: dict, job_file: Path, timeout: float) -> None:
    command = find_blender()
    if command is None:
        raise GraMiInputError(BLENDER_ENV, "no Blender found: run scripts/setup.sh (it makes .venv-blender), or set it to a bpy Python")
    job_file.write_text(json.dumps(job))
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTHON")}  # gra-mi's paths must not reach bpy
    done = subprocess.run([*command, str(job_file)], capture_output=True, text=True, timeout=timeout, cwd=job_file.parent, env=env)
    written = job.get("reexport", job.get("inventory", job.get("out")))
    if done.returncode != 0 or not Path(written).is_file():
        raise RuntimeError(f"Blender failed ({done.returncode}):\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")


def reexport_in_blender(asset: Path, out: Path, timeout: float = 600.0) -> Path:
    """``asset`` imported into Blender and written back out by Blender's own exporter (``out``: .glb or .usd*)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    _run_job({"asset": str(Path(asset).resolve()), "reexport": str(out.resolve())}, out.with_name(f"{out.name}.job.json"), timeout)
    return out


def inventory_in_blender(
    asset: Path, out: Path, light_intensity_scale: float = 1.0, timeout: float = 600.0, at: tuple[int, float] | None = None
) -> dict:
    """The cameras, lights and meshes Blender imports from ``asset``, in gra-mi's world (:func:`blender_job.inventory`);
    ``light_intensity_scale``: the USD importer's option of that name; ``at``: (the exported frame, the sequence's
    fps) to read them at (moving lights)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    job = {"asset": str(Path(asset).resolve()), "inventory": str(out.resolve()), "light_intensity_scale": light_intensity_scale}
    if at is not None:
        job |= {"frame": at[0], "fps": at[1]}
    _run_job(job, out.with_name(f"{out.name}.job.json"), timeout)
    return json.loads(out.read_text())


MATERIALS = {"fitted": (False, None), "fitted, single-scatter GGX": (False, "GGX"), "lambert": (True, None)}
"""The materials :func:`compare_with_blender` renders: (Lambert on both sides, the Principled BSDF's distribution in
Blender: None keeps the importer's, Blender's multiple-scattering GGX)."""


def render_in_blender(
    asset: Path, frame: int, fps: float, envmap: Path, camera: Camera, folder: Path, spp: int = 128, lambert: bool = False,
    seed: int = 0, timeout: float = 900.0, distribution: str | None = None,
) -> tuple[np.ndarray, dict]:  # fmt: skip
    """(RGBA image, report) of Blender's Cycles render of ``asset`` at sequence frame ``frame``; the report has
    Blender's version and the imported mesh's vertices at that frame (gra-mi's world). ``distribution``: set the
    imported Principled BSDF's ('GGX', 'MULTI_GGX'; None: as imported)."""
    folder.mkdir(parents=True, exist_ok=True)
    tag = f"{Path(asset).name}_f{frame}{'_lambert' if lambert else ''}{f'_{distribution}' if distribution else ''}"
    job = {
        "asset": str(Path(asset).resolve()), "frame": int(frame), "fps": float(fps), "envmap": str(Path(envmap).resolve()),
        "spp": int(spp), "lambert": bool(lambert), "seed": int(seed), "distribution": distribution,
        "out": str((folder / f"blender_{tag}.exr").resolve()), "report": str((folder / f"blender_{tag}.json").resolve()),
        "camera": {
            "camera_to_world": np.asarray(camera.camera_to_world, float).tolist(), "width": camera.width, "height": camera.height,
            "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
        },
    }  # fmt: skip
    _run_job(job, folder / f"blender_{tag}.job.json", timeout)
    return read_exr(job["out"]), json.loads(Path(job["report"]).read_text())


def render_in_mitsuba(
    seq: MeshSequence, frame: int, albedo: np.ndarray, roughness: np.ndarray, envmap: Path, camera: Camera, folder: Path,
    spp: int = 128, lambert: bool = False, seed: int = 0,
) -> np.ndarray:  # fmt: skip
    """RGBA render of the mesh at ``frame`` with gra-mi's maps: ``gra_microfacet`` (or ``diffuse``), Mitsuba's
    ``envmap`` emitter (identity ``to_world``: gra-mi's convention is Mitsuba's), ``path`` with ``max_depth`` 2."""
    import mitsuba as mi

    from gra_mi.render.runtime import ensure_mitsuba

    ensure_mitsuba()
    folder.mkdir(parents=True, exist_ok=True)
    write_ply(folder / "mitsuba_frame.ply", seq.vertices[frame], seq.normals[frame], seq.uvs, seq.faces)
    write_exr(folder / "mitsuba_albedo.exr", albedo[..., :3])
    write_exr(folder / "mitsuba_roughness.exr", roughness[..., :1])
    albedo_tex = {"type": "bitmap", "filename": str(folder / "mitsuba_albedo.exr")}
    if lambert:
        bsdf = {"type": "diffuse", "reflectance": albedo_tex}
    else:
        rough_tex = {"type": "bitmap", "filename": str(folder / "mitsuba_roughness.exr"), "raw": True}
        bsdf = {"type": "gra_microfacet", "albedo": albedo_tex, "roughness": rough_tex}
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": camera_sensor_dict(camera, spp),
            "body": {"type": "ply", "filename": str(folder / "mitsuba_frame.ply"), "face_normals": False, "bsdf": bsdf},
            "sky": {"type": "envmap", "filename": str(Path(envmap).resolve())},
        }
    )
    integrator = mi.load_dict({"type": "path", "max_depth": 2, "hide_emitters": True})
    return np.array(mi.render(scene, integrator=integrator, spp=spp, seed=seed), np.float64)


def agreement(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Silhouette IoU (alpha ≥ 0.5), relative mean brightness over the pixels both cover, and the display PSNR there
    (both shown at the reference's exposure)."""
    a, b = image[..., 3] >= 0.5, reference[..., 3] >= 0.5
    both = a & b
    union = int((a | b).sum())
    mean = float(reference[both][:, :3].mean()) if both.any() else 0.0
    return {
        "iou": float(both.sum()) / union if union else 1.0,
        "brightness": float(image[both][:, :3].mean()) / mean - 1.0 if mean > 0 else float("nan"),
        "psnr": display_psnr(image[..., :3], reference[..., :3], both),
    }


def subject_window(camera: Camera, points: np.ndarray, size: int = 192, margin: float = 0.08) -> Camera:
    """``camera`` cropped to the window around ``points`` (its pixels, a principal point off the centre) and scaled so
    that the window's long side has ``size`` pixels: the capture camera, looking only where the subject is."""
    from dataclasses import replace

    xy = camera.project(points)[:, :2]
    low, high = xy.min(axis=0), xy.max(axis=0)
    pad = margin * float((high - low).max())
    x0, y0 = np.floor(low - pad).astype(int)
    x1, y1 = np.ceil(high + pad).astype(int)
    crop = replace(camera, width=int(x1 - x0), height=int(y1 - y0), cx=camera.cx - x0, cy=camera.cy - y0)
    scale = size / max(crop.width, crop.height)
    return replace(crop, width=round(crop.width * scale), height=round(crop.height * scale), fx=crop.fx * scale,
                   fy=crop.fy * scale, cx=crop.cx * scale, cy=crop.cy * scale)  # fmt: skip


def compare_with_blender(
    assets: list[Path], seq: MeshSequence, frames: list[int], albedo: np.ndarray, roughness: np.ndarray, envmap: Path,
    camera: Camera, folder: Path, spp: int = 128, materials: tuple[str, ...] = tuple(MATERIALS),
) -> tuple[list[dict], dict[str, np.ndarray]]:  # fmt: skip
    """Blender's renders of each exported asset against Mitsuba's of the same mesh and maps, at each frame, with each
    of ``materials`` (:data:`MATERIALS`: the fitted material as imported, with Blender's GGX set to single scattering
    as gra-mi's, and Lambert on both sides: the handover alone): (rows of :func:`agreement` plus the imported pose's
    largest distance from gra-mi's, images by name). Mitsuba renders with 4× Blender's samples."""
    rows, images, references = [], {}, {}
    for frame in frames:
        for material in materials:
            lambert, distribution = MATERIALS[material]
            if (frame, lambert) not in references:
                references[frame, lambert] = render_in_mitsuba(seq, frame, albedo, roughness, envmap, camera, folder, 4 * spp, lambert)
            reference = references[frame, lambert]
            images[f"mitsuba_{material}_f{frame}"] = reference
            for asset in assets:
                image, report = render_in_blender(asset, frame, seq.fps, envmap, camera, folder, spp, lambert, distribution=distribution)
                images[f"blender_{Path(asset).suffix[1:]}_{material}_f{frame}"] = image
                rows.append({"asset": Path(asset).name, "frame": frame, "material": material, "blender": report["blender"],
                             "pose_error_m": pose_error(np.asarray(report["vertices"]), seq.vertices[frame]),
                             **agreement(image, reference)})  # fmt: skip
    return rows, images


def pose_error(imported: np.ndarray, vertices: np.ndarray) -> float:
    """Largest distance from an imported vertex to the nearest of gra-mi's (an importer may split or merge vertices)."""
    from scipy.spatial import cKDTree

    return float(cKDTree(vertices).query(imported)[0].max()) if len(imported) else float("inf")
