"""``gra-mi export``: the avatar (tracked mesh sequence + fitted maps, optionally the capture's cameras and a lighting)
as USD or glTF binary, chosen by the file name, then checked by the format's own validator:

- USD: usd-core's validation framework (the rules ``usdchecker`` runs: stage metadata, material bindings, shader
  compliance, package encapsulation and the usdz layout, ...), in-process;
- glTF: the Khronos glTF-Validator (npm ``gltf-validator``, run with node; ``scripts/setup.sh`` installs it into
  ``.tools/``). Where node or the validator is missing the export says so and is not checked.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from gra_mi.apps.gltf import export_glb
from gra_mi.apps.usd import UsdLighting, export_usd
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.stage.lightstage import Lightstage
from gra_mi.subject.interchange import GLTF_SUFFIXES, USD_SUFFIXES
from gra_mi.subject.sequence import MeshSequence

logger = logging.getLogger(__name__)

GLTF_VALIDATOR_MODULES = Path(__file__).resolve().parents[2] / ".tools" / "node_modules"
"""Where scripts/setup.sh installs the npm package ``gltf-validator``; ``GRA_MI_NODE_PATH`` names another."""
_VALIDATE_JS = """
const validator = require('gltf-validator');
const data = new Uint8Array(require('fs').readFileSync(process.argv[1]));
validator.validateBytes(data, {maxIssues: 200}).then(r => console.log(JSON.stringify(r)))
    .catch(e => { console.error(String(e)); process.exit(3); });
"""


@dataclass
class ExportReport:
    path: Path
    validator: str  # what checked it, or why nothing did
    errors: list[str]
    warnings: list[str]

    def summary(self) -> str:
        return f"{self.path}: {self.validator}: {len(self.errors)} errors, {len(self.warnings)} warnings"


def validate_usd(path: Path) -> ExportReport:
    """Every validator usd-core registers, on the stage ``path`` opens."""
    from pxr import Usd, UsdValidation

    stage = Usd.Stage.Open(str(path))
    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    found = UsdValidation.ValidationContext(validators).Validate(stage)
    kinds = UsdValidation.ValidationErrorType
    errors = [f"{e.GetName()}: {e.GetMessage()}" for e in found if e.GetType() == kinds.Error]
    warnings = [f"{e.GetName()}: {e.GetMessage()}" for e in found if e.GetType() == kinds.Warn]
    return ExportReport(
        path, f"usd-core {'.'.join(map(str, Usd.GetVersion()[1:]))} validation ({len(validators)} validators)", errors, warnings
    )


def gltf_validator() -> tuple[str, dict[str, str]] | None:
    """(node, its environment) that can ``require('gltf-validator')``, or None."""
    node = shutil.which("node")
    modules = os.environ.get("GRA_MI_NODE_PATH") or str(GLTF_VALIDATOR_MODULES)
    if node is None or not (Path(modules) / "gltf-validator").is_dir():
        return None
    return node, {**os.environ, "NODE_PATH": modules}


def validate_glb(path: Path) -> ExportReport:
    """The Khronos glTF-Validator's verdict on ``path`` (not checked, saying why, where it is missing)."""
    found = gltf_validator()
    if found is None:
        return ExportReport(path, "not checked (node or the npm package gltf-validator is missing: scripts/setup.sh)", [], [])
    node, env = found
    done = subprocess.run([node, "-e", _VALIDATE_JS, str(path)], capture_output=True, text=True, env=env, timeout=300)
    if done.returncode != 0:
        return ExportReport(path, "glTF-Validator", [f"the validator failed: {done.stderr.strip()[-500:]}"], [])
    result = json.loads(done.stdout)
    messages = result["issues"]["messages"]
    said = [f"{m['code']} at {m.get('pointer', '')}: {m['message']}" for m in messages]
    errors = [s for s, m in zip(said, messages, strict=True) if m["severity"] == 0]
    warnings = [s for s, m in zip(said, messages, strict=True) if m["severity"] == 1]
    return ExportReport(path, f"glTF-Validator {result.get('validatorVersion', '')}", errors, warnings)


def off_centre_cameras(cameras: list) -> list[str]:
    """What a glTF camera loses: its principal point (glTF's look through the image's centre)."""
    said = []
    for cam in cameras:
        dx, dy = cam.cx - cam.width / 2.0, cam.cy - cam.height / 2.0
        if max(abs(dx), abs(dy)) > 0.5:
            said.append(
                f"camera {cam.name}: its principal point is ({dx:+.1f}, {dy:+.1f}) px off the image's centre, which glTF cannot hold"
            )
    return said


def check_glb_spots(out: Path, tracks: list) -> None:
    """Refuse a spot wider than a hemisphere in a .glb (glTF's outer cone angle is at most 90°), before writing."""
    for track in tracks:
        widest = max((state.cutoff_angle for state in track.states if state.is_spot), default=0.0)
        if widest > 90.0:
            raise GraMiInputError(out, f"light '{track.name}' is a spot of cutoff {widest:g}°, wider than glTF's spot lights "
                                  "reach (90°): export it to .usd* (a SphereLight with a cone of any angle)")  # fmt: skip


def glb_light_losses(tracks: list) -> list[str]:
    """What a .glb's punctual lights lose of a light path's: a light's radius (they are points) and, where they change
    over the exported frames, its intensity, colour and cone (glTF animates a light's node, not the light)."""
    said = []
    for track in tracks:
        lost = [f"its {track.states[0].radius:g} m radius (glTF's lights are points)"] if track.states[0].radius > 0 else []
        changing = [name for name, read in (("intensity and colour", lambda s: s.intensity),
                    ("cone", lambda s: (s.cutoff_angle, s.beam_width or 0.0))) if track.varies(read)]  # fmt: skip
        if changing:
            lost.append(f"its changing {' and '.join(changing)} (glTF cannot animate a light's: the first frame's is written)")
        if lost:
            said.append(f"light '{track.name}': the .glb leaves out {'; '.join(lost)}")
    return said


def export_avatar(
    out: Path, seq: MeshSequence, albedo: np.ndarray, roughness: np.ndarray, frames: list[int] | None = None,
    rig: Lightstage | None = None, envmap: np.ndarray | None = None, led_intensities: np.ndarray | None = None,
    set_parts: list | None = None, tracks: list | None = None,
) -> ExportReport:  # fmt: skip
    """Write ``out`` in the format its suffix names and validate it. ``frames``: the sequence's frames to export, in
    order (default: all). The rig's cameras and its lit LEDs travel in both formats; an environment map in USD only
    (glTF's punctual lights cannot hold one): asking for it in a .glb is an error, not a silent drop. ``set_parts``: a
    scene's set (:func:`gra_mi.apps.set_export.read_set`), and ``tracks``, a light path's lights at each exported frame
    (:func:`gra_mi.apps.export_lights.light_tracks`), in both formats."""
    if frames is not None and not frames:
        raise GraMiParameterError("frames", "selects no frame")
    if frames is not None and (bad := [f for f in frames if not 0 <= f < seq.num_frames]):
        raise GraMiParameterError("frames", f"frame {bad[0]} is not in the subject's {seq.num_frames} frames (0 … {seq.num_frames - 1})")
    suffix = out.suffix.lower()
    if suffix in GLTF_SUFFIXES:
        if envmap is not None:
            raise GraMiInputError(out, "glTF has no environment light: export the environment map to .usd* (a DomeLight)")
        check_glb_spots(out, tracks or [])
        leds = None if led_intensities is None else (rig.led_positions, led_intensities)
        cameras = rig.cameras if rig is not None else None
        report = validate_glb(export_glb(out, seq, albedo, roughness, frames, cameras, leds, set_parts, tracks))
        return replace(report, warnings=report.warnings + off_centre_cameras(cameras or []) + glb_light_losses(tracks or []))
    if suffix not in USD_SUFFIXES:
        raise GraMiInputError(out, f"unknown format '{suffix}': expected one of {', '.join(USD_SUFFIXES + GLTF_SUFFIXES)}")
    lighting = None
    if envmap is not None or led_intensities is not None or tracks:
        lighting = UsdLighting(envmap=envmap, stage=rig, led_intensities=led_intensities, tracks=tracks)
    return validate_usd(export_usd(out, seq, albedo, roughness, frames, rig.cameras if rig is not None else None, lighting, set_parts))
