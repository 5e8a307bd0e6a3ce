"""A synthetic capture's ground truth, apart from the capture it belongs to: the renderer of its frames (exact direct
light from every LED that is on + the path tracer's interreflections) and that truth's own noise, measured against
more samples; and the truth under any environment map (the capture's subject and materials lit by an envmap instead
of the LEDs), which the evaluation scores against. :mod:`gra_mi.capture.synthetic` writes the captures."""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture, FrameLighting
from gra_mi.capture.wrinkles import pose_capture_wrinkles
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import scratch_directory
from gra_mi.core.io import write_exr
from gra_mi.core.metrics import relative_rmse
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.scene import render_mean

logger = logging.getLogger(__name__)

NOISE_REFERENCE_FACTOR = 4  # the truth's noise is measured against this many times its samples

LEDS_INCLUDE = '<include filename="rig/leds.xml"/>'
TRUTH_VERSION = 3
"""Bumped when the envmap truth changes (2: the frame's wrinkles, which version 1 left flat; 3: wrinkles that follow
the pose's compression, capture/wrinkles.py, instead of the frame's index): cached truths of
another version are rendered again."""


@dataclass
class GroundTruthRenderer:
    """Exact direct light from every LED that is on + the path tracer's interreflections (see the module doc).

    The two path renders share their seed, so their samples agree up to the first bounce and the difference holds
    only the light of the later bounces: unbiased, and as noisy as that light (a few per cent of the image) alone.
    """

    spp: int
    indirect_spp: int
    max_depth: int = 4

    def __post_init__(self):
        import mitsuba as mi

        ensure_mitsuba()  # registers gra_onebounce for the variant
        self.direct = mi.load_dict({"type": "gra_onebounce"})
        self.path = mi.load_dict({"type": "path", "max_depth": self.max_depth})
        self.first_bounce = mi.load_dict({"type": "path", "max_depth": 2})

    def render(self, scene, sensor: int, seed: int, factor: int = 1) -> np.ndarray:
        """(H, W, 4) linear RGB + alpha; ``factor`` multiplies both sample counts (the noise reference)."""

        image = render_mean(scene, sensor, self.direct, self.spp * factor, seed)
        if self.max_depth > 2 and self.indirect_spp > 0:  # the same seeds: the first bounce the two share cancels
            spp = self.indirect_spp * factor
            later, first = (render_mean(scene, sensor, integrator, spp, seed) for integrator in (self.path, self.first_bounce))
            image[..., :3] += later[..., :3] - first[..., :3]
        return image.astype(np.float32)


def own_noise(image: np.ndarray, reference: np.ndarray, mask: np.ndarray, factor: int) -> float:
    """The relative RMS noise of ``image`` measured against a ``reference`` rendered by the same estimator with
    ``factor`` times the samples (other seeds): the reference's own noise variance is 1/factor of the image's, so the
    difference's mean square is (1 + 1/factor) times the image's, divided out here."""
    return relative_rmse(image, reference, mask=mask) / math.sqrt(1 + 1 / factor)


def noise_probe_frames(capture: Capture, stage, camera: str) -> dict[str, FrameLighting]:
    """The frames the ground truth's noise is measured on: a uniform one, a sky with a sun and a room (training); in a
    static OLAT capture the white frame, an OLAT and a held-out OLAT (the images its scores use), each the one whose
    LED is nearest ``camera`` (of ``stage``), so that the subject is lit where that camera looks."""
    kinds: dict[str, str] = {}
    for folder in {Path(f.envmap).parent for f in capture.frames if f.envmap}:
        index = capture.folder / folder / "index.json"
        if index.is_file():
            kinds.update({str(folder / e["file"]): e["kind"] for e in json.loads(index.read_text())})
    probes: dict[str, FrameLighting] = {}
    olats: dict[str, list[FrameLighting]] = {}
    for entry in capture.frames:
        label = "uniform" if entry.kind == "uniform" else kinds.get(entry.envmap or "", _pattern_probe(entry))
        if label in ("uniform", "sky", "room", "white") and entry.split == "train":
            probes.setdefault(label, entry)
        elif label in ("OLAT", "held-out OLAT"):
            olats.setdefault(label, []).append(entry)
    for label, entries in olats.items():
        probes[label] = min(entries, key=lambda e: _led_distance(capture, stage, e, camera))
    return probes


def _led_distance(capture: Capture, stage, entry: FrameLighting, camera) -> float:
    led = int(np.argmax(capture.lighting(stage, entry).sum(axis=1)))
    return float(np.linalg.norm(stage.led_positions[led] - np.asarray(stage.camera(camera).position)))


def _pattern_probe(entry: FrameLighting) -> str:
    name = Path(entry.pattern or "").stem
    if name == "white":
        return "white"
    return ("OLAT" if entry.split == "train" else "held-out OLAT") if "olat_" in name else ""


def ground_truth_renderers(record: dict):
    """``renderer_for(entry)``: the renderer of a capture frame, with the environment-lit training frames' and the
    held-out frames' own sample counts where the record has them (``relit_spp``, ``held_out_spp`` and their
    ``*_indirect_spp``)."""
    depth = record["max_depth"]

    def renderer(kind: str) -> GroundTruthRenderer:
        prefix = f"{kind}_" if f"{kind}_spp" in record else ""
        return GroundTruthRenderer(spp=record[f"{prefix}spp"], indirect_spp=record[f"{prefix}indirect_spp"], max_depth=depth)

    default, relit, held_out = renderer(""), renderer("relit"), renderer("held_out")
    return lambda entry: held_out if entry.split == "test" else relit if entry.kind == "envmap" else default


def measure_ground_truth_noise(capture: Capture, source, renderer_for, camera: str, pose=None) -> dict[str, dict]:
    """Relative RMS noise of the ground truth, against a render of the same view with 4x the samples (other seeds),
    the reference's own noise divided out (:func:`own_noise`).

    ``renderer_for(entry)``: each frame's renderer (:func:`ground_truth_renderers`). ``pose(frame)`` moves
    ``source`` to a frame (default: ``source.set_frame``)."""
    import time

    out = {}
    for label, entry in noise_probe_frames(capture, source.stage, camera).items():
        (pose or source.set_frame)(entry.mesh_frame)
        source.set_led_intensities(capture.lighting(source.stage, entry))
        sensor, renderer = source.sensor_index(camera), renderer_for(entry)
        start = time.perf_counter()
        image = renderer.render(source.scene, sensor, seed=entry.frame)
        seconds = time.perf_counter() - start
        reference = renderer.render(source.scene, sensor, seed=100_003 + entry.frame, factor=NOISE_REFERENCE_FACTOR)
        out[label] = {
            "frame": entry.frame,
            "camera": camera,
            "envmap": entry.envmap,
            **({"pattern": entry.pattern} if entry.kind == "pattern" else {}),
            "relative_rmse": round(own_noise(image, reference, reference[..., 3] > 0.5, NOISE_REFERENCE_FACTOR), 5),
            "seconds_per_image": round(seconds, 3),
            "spp": [renderer.spp, renderer.indirect_spp],
            "reference_factor": NOISE_REFERENCE_FACTOR,  # older records: 16, the reference's own noise left in
        }
    return out


def envmap_truth_xml(capture: Capture) -> str:
    """The capture's ``scene_gt.xml`` with an ``envmap`` emitter (``-Denvmap=FILE``, Mitsuba's lat-long convention,
    which is gra-mi's) in place of the LEDs: the same subject, true materials and cameras. What relighting under an
    environment should reproduce: the environment itself, at infinity. Loaded from memory (:func:`load_envmap_truth`),
    so scoring never writes into the capture."""
    source = capture.folder / "scene_gt.xml"
    if not source.is_file():
        raise GraMiInputError(source, "missing: the envmap truth needs the capture's ground-truth scene (make it with `gra-mi capture`)")
    text = source.read_text()
    if LEDS_INCLUDE not in text:
        raise GraMiInputError(source, f"expected the LEDs as `{LEDS_INCLUDE}` (a scene written by `gra-mi capture`)")
    emitter = (
        '<default name="envmap" value="envmap.exr"/>\n'
        '    <emitter type="envmap" id="environment"><string name="filename" value="$envmap"/></emitter>'
    )
    return text.replace(LEDS_INCLUDE, emitter)


def load_envmap_truth(capture: Capture, envmap_path: Path, frame: int):
    """The envmap truth scene of ``frame`` (:func:`envmap_truth_xml`), posed: the frame's mesh and, unless the capture
    was made without them, the frame's wrinkles (:func:`pose_wrinkles`, as the capture's own images have them)."""
    import mitsuba as mi

    from gra_mi.stage import scene_keys as keys

    resolver = mi.file_resolver()
    saved = mi.FileResolver(resolver)
    resolver.prepend(str(capture.folder.resolve()))  # the scene's relative paths (rig/, subject/, gt/)
    try:
        scene = mi.load_string(
            envmap_truth_xml(capture), parallel=False, **{keys.PARAM_FRAME: keys.frame_param(frame), "envmap": str(envmap_path)}
        )
    finally:
        resolver.clear()
        for i in range(len(saved)):
            resolver.append(saved[i])
    pose_capture_wrinkles(mi.traverse(scene), capture, frame)
    return scene


def render_envmap_truth(
    capture: Capture, envmap: np.ndarray, frame: int, cameras: list[str], spp: int = 256, seed: int = 0
) -> dict[str, np.ndarray]:
    """Path-trace the capture's subject (true materials, sheen, the frame's wrinkles, its interreflections) under
    ``envmap`` (linear lat-long radiance, used as given): camera name → (H, W, 4) linear RGB + alpha (coverage).

    The environment is hidden from the cameras (alpha is the subject's coverage, the background black), as in
    the capture. Interreflections follow the capture's ``max_depth`` (none when it was made without them)."""
    import mitsuba as mi

    ensure_mitsuba()
    max_depth = int(capture.ground_truth.get("max_depth", 4))
    with scratch_directory() as tmp:
        env_path = Path(tmp) / "envmap.exr"
        write_exr(env_path, np.asarray(envmap, np.float32)[..., :3])
        scene = load_envmap_truth(capture, env_path, frame)
    integrator = mi.load_dict({"type": "path", "max_depth": max(max_depth, 2), "hide_emitters": True})
    sensors = {s.id(): i for i, s in enumerate(scene.sensors())}
    out = {}
    for name in cameras:
        if name not in sensors:
            raise GraMiParameterError("cameras", f"no camera '{name}' in {capture.folder / 'scene_gt.xml'}; it has {', '.join(sensors)}")
        out[name] = render_mean(scene, sensors[name], integrator, spp, seed + frame).astype(np.float32)
    return out
