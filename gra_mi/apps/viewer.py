"""What ``gra-mi view`` shows, without the browser: a subject relit for any camera under the lighting a viewer picks.

:class:`ViewerSession` holds a lightstage scene, its maps (fitted, or the subject's colours) and, where its weights
exist, RelightNet. :meth:`ViewerSession.render` relights the current frame for a free camera — gra-mi's own one-bounce
UV texture (or RelightNet's), shaded for that camera's position so highlights follow the view, rasterised by gra-mi's
rasteriser — and says how long each part took. Per-frame visibility is cached (in memory, and in ``vis_cache`` if
given), so a new envmap, rotation or LED on a frame seen before re-shades only. The browser page
(:mod:`gra_mi.apps.viewer_page`) only turns controls into :class:`Lighting` changes and images into pixels.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.stage.envmap import EnvmapOptions, envmap_to_leds, rotate, rotation_y
from gra_mi.stage.envmap_library import REFERENCE_MAPS, reference_map
from gra_mi.stage.lightstage import Camera, olat_pattern

logger = logging.getLogger(__name__)

MODES = ("envmap", "olat", "point light")
STAGES = ("microfacet", "relightnet", "albedo", "roughness", "confidence")
BACKGROUND = np.array([0.02, 0.02, 0.025], np.float32)  # linear; the page's dark grey behind the subject
VIEW_SAMPLES = 2  # 2×2 sub-samples per pixel: anti-aliased edges at 4/9 of the rasteriser's cost for files
# Visibility held in memory: about 7 MB a frame at 512² × 331 LEDs, so a long sequence's frames, all traced in the
# background, would fill any machine. Beyond this the least recently shown frames are dropped (read back from
# --vis-cache where given, traced again where not).
VISIBILITY_BYTES = 2 << 30


@dataclass
class ViewSources:
    """Where the viewer's subject comes from: a capture (its scene.xml) or a lightstage scene, with optional stages."""

    scene: Path
    capture: Path | None = None
    fit: Path | None = None
    relightnet: Path | None = None
    envmaps: list[Path] = field(default_factory=list)
    vis_cache: Path | None = None
    uv_resolution: int = 256
    named: frozenset[str] = frozenset()  # stages the user named ("fit", "relightnet"): refused, not noted, when unusable

    @classmethod
    def of_run(cls, run: Path, **kw) -> ViewSources:
        """A folder ``gra-mi demo`` wrote (capture/, fit/, relightnet/); stages it lacks are simply absent."""
        if not (run / "capture" / "capture.json").is_file():
            raise GraMiInputError(run, "not a run folder: no capture/capture.json (give --capture or --scene instead)")
        present = {name: run / name for name in ("fit", "relightnet") if (run / name).is_dir()}
        return cls(scene=run / "capture" / "scene.xml", capture=run / "capture", **present, **kw)


@dataclass
class Lighting:
    """What the viewer is lit by and shows (every control of the page, as values)."""

    mode: str = "envmap"
    envmap: str = "sun"
    rotation: float = 0.0  # degrees about the up axis
    far_field: bool = True  # envmaps: an environment at infinity (True) or the stage's LEDs where they are
    olat: int = 0
    point: tuple[float, float, float] = (0.6, 1.3, 0.6)
    point_intensity: float = 2.0
    stage: str = "microfacet"
    frame: int = 0
    exposure: float = 0.0  # EV on top of the automatic exposure
    bounces: int = 1  # of light (gra_mi.render.transport): 2 adds what the body reflects onto itself


@dataclass
class ViewImage:
    image: np.ndarray  # (H, W, 3) uint8 sRGB
    timings: dict[str, float]  # milliseconds per part
    depth: np.ndarray | None = None  # (H, W) metres along the camera's axis (far where no subject): the page's occlusion


class ViewerSession:
    """The subject, its maps and the lighting; renders views for free cameras (thread-safe: one render at a time)."""

    def __init__(self, sources: ViewSources, envmap_options: EnvmapOptions | None = None, device: str = "cpu", transport=None):
        from gra_mi.render.relighter import Relighter
        from gra_mi.stage.scene import LightstageScene

        self.sources, self.notices = sources, []
        self.lock = threading.RLock()
        self.ls = LightstageScene.load(sources.scene, every_frame=False)  # a frame is checked when it is shown
        albedo, roughness, self.confidence = self._maps()
        self.relighter = Relighter(self.ls, sources.uv_resolution, albedo, roughness, cache_dir=sources.vis_cache, transport=transport)
        frame_bytes = 4 * self.relighter.atlas.num_texels * -(-self.ls.stage.num_leds // 32)  # a frame's bits, every LED on
        self.relighter.cache.keep = max(4, VISIBILITY_BYTES // frame_bytes)
        if sources.vis_cache is None and self.ls.sequence.num_frames > self.relighter.cache.keep:
            self.notices.append(
                f"the first {self.relighter.cache.keep} of {self.ls.sequence.num_frames} frames' visibility is traced in the background "
                "(what memory holds); later frames are traced when shown. Give --vis-cache to trace and keep them all on disk"
            )
        self.model = self._relightnet(device)
        self.envmap_options = envmap_options or EnvmapOptions()
        self.envmap_sources = self._envmap_sources()
        self.lighting = Lighting(envmap=next(iter(self.envmap_sources)), bounces=self.relighter.transport.bounces)
        self._envmaps: dict[str, np.ndarray] = {}
        self._base_exposure: dict[tuple, float] = {}
        self.capture = self._capture()

    # ---------------------------------------------------------------- what there is
    def _maps(self):
        from gra_mi.render.relighter import load_texture

        fit = self.sources.fit
        if fit is not None and "fit" in self.sources.named and not (fit / "albedo.exr").is_file():
            raise GraMiInputError(fit, "not a fit folder: no albedo.exr (made by `gra-mi fit`)")
        if fit is None or not (fit / "albedo.exr").is_file():
            self.notices.append("no fit: the subject shows its own colours (vertex colours baked to UV, roughness 0.5)")
            return None, None, None
        albedo = load_texture(fit / "albedo.exr", 3, "albedo")
        roughness = load_texture(fit / "roughness.exr", 1, "roughness")
        confidence = confidence_picture(fit / "confidence.exr") if (fit / "confidence.exr").is_file() else None
        return albedo, roughness, confidence

    def _relightnet(self, device: str):
        folder = self.sources.relightnet
        if folder is None:
            return None
        from gra_mi.relightnet.model import RelightNet

        try:
            model = RelightNet.load(folder, device)
        except (GraMiInputError, OSError, RuntimeError, ValueError) as exc:
            if "relightnet" in self.sources.named:
                raise exc if isinstance(exc, GraMiInputError) else GraMiInputError(folder, str(exc).splitlines()[0]) from None
            self.notices.append(f"RelightNet not available: {str(exc).splitlines()[0]}")
            return None
        if model.config.resolution != self.relighter.atlas.resolution:
            self.notices.append(
                f"RelightNet runs at {model.config.resolution}², the maps are {self.relighter.atlas.resolution}²: not shown"
            )
            return None
        return model

    def _envmap_sources(self) -> dict[str, object]:
        """Name → a file or a reference map's name; loaded when first chosen (a bad file is said then, not fatal)."""
        found: dict[str, object] = {}
        if self.sources.capture is not None:
            for path in sorted((self.sources.capture / "envmaps").rglob("*.exr")):
                found.setdefault(path.stem, path)
        for path in self.sources.envmaps:
            found[path.stem] = path
        for name in REFERENCE_MAPS:
            found.setdefault(name, name)
        return found

    def _capture(self):
        if self.sources.capture is None:
            return None
        from gra_mi.capture.dataset import Capture

        return Capture.load(self.sources.capture)

    @property
    def stages(self) -> list[str]:
        shown = ["microfacet"] + (["relightnet"] if self.model is not None else []) + ["albedo", "roughness"]
        return shown + (["confidence"] if self.confidence is not None else [])

    def subject_center(self) -> np.ndarray:
        """The centre of the subject's bounding box at the current frame (where the page's camera orbits)."""
        vertices = self.ls.sequence.vertices[self.lighting.frame]
        return 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))

    @property
    def num_frames(self) -> int:
        return self.ls.sequence.num_frames

    # ---------------------------------------------------------------- lighting
    def envmap(self, name: str) -> np.ndarray:
        """The named map (loaded once); a file that fails to load raises GraMiInputError naming it."""
        if name not in self._envmaps:
            source = self.envmap_sources[name]
            self._envmaps[name] = self.envmap_options.load(source) if isinstance(source, Path) else reference_map(str(source), 64)
        return self._envmaps[name]

    def rotated_envmap(self) -> np.ndarray:
        return rotate(self.envmap(self.lighting.envmap), rotation_y(self.lighting.rotation))

    def lighting_preview(self) -> np.ndarray:
        """What lights the subject as a lat-long map: the envmap, or the LEDs' pattern (an OLAT, the point light's
        envmap conditioning, as RelightNet sees it)."""
        from gra_mi.render.point_light import conditioning_envmap, conditioning_of
        from gra_mi.stage.envmap import leds_to_envmap

        if self.lighting.mode == "envmap":
            return self.rotated_envmap()
        intensities, near, _ = self.lights()
        if near:
            with self.lock:
                return conditioning_envmap(self.ls.stage, conditioning_of(self.ls.stage, self.ls.scene, near), 32)
        return leds_to_envmap(self.ls.stage, intensities, 32)

    def lights(self) -> tuple[np.ndarray, list, bool]:
        """(LED radiant intensities, near-field lights, far field) of the current lighting."""
        from gra_mi.render.point_light import PointLight

        stage, light = self.ls.stage, self.lighting
        off = np.zeros((stage.num_leds, 3))
        if light.mode == "olat":
            return olat_pattern(stage, light.olat) * stage.gains, [], False
        if light.mode == "point light":
            return off, [PointLight(np.array(light.point), light.point_intensity)], False
        return envmap_to_leds(self.rotated_envmap(), stage).radiant_intensity(stage), [], light.far_field

    # ---------------------------------------------------------------- rendering
    def render(self, camera: Camera) -> ViewImage:
        """The current frame under the current lighting, seen by ``camera``."""
        with self.lock:
            light, timings, start = self.lighting, {}, time.perf_counter()
            intensities, near, far = self.lights()
            texture = self._texture(light, camera, intensities, near, far)
            timings["shade"] = 1000 * (time.perf_counter() - start)
            start = time.perf_counter()
            image = self.relighter.rasterize(light.frame, camera, texture, VIEW_SAMPLES)
            depth = self._depth(camera)
            timings["rasterize"] = 1000 * (time.perf_counter() - start)
        start = time.perf_counter()
        shown = self._display(image, light)
        timings["tonemap"] = 1000 * (time.perf_counter() - start)
        return ViewImage(shown, timings, depth)

    def _depth(self, camera: Camera) -> np.ndarray:
        """The subject's depth at each pixel centre (one ray each), so the page hides LEDs and the gizmo behind it."""
        import drjit as dr
        import mitsuba as mi

        ray = self.ls.camera_rays(camera)
        si = self.ls.subject_hits(ray, mi.RayFlags.Minimal)
        forward = [float(v) for v in camera.rotation[:, 2]]
        depth = dr.select(si.is_valid(), si.t * dr.dot(ray.d, mi.Vector3f(forward)), 1e4)
        return np.asarray(depth, np.float32).reshape(camera.height, camera.width)

    def _texture(self, light: Lighting, camera: Camera, intensities, near, far) -> np.ndarray:
        from gra_mi.relightnet.infer import relightnet_texture

        atlas = self.relighter.atlas
        if light.stage == "albedo":
            return self.relighter.albedo_tex
        if light.stage == "roughness":
            return np.repeat(self.relighter.roughness_tex, 3, axis=2)
        if light.stage == "confidence" and self.confidence is not None:
            return self.confidence
        if light.stage == "relightnet" and self.model is not None:
            return relightnet_texture(self.model, self.relighter, light.frame, camera, intensities, near, far)[0]
        shading, _ = self.relighter.shade(light.frame, camera, intensities, near, far)
        return atlas.scatter(shading.radiance)

    def _display(self, image: np.ndarray, light: Lighting) -> np.ndarray:
        """sRGB8 over the page's background; the exposure is set once per lighting (so orbiting does not flicker),
        then the page's EV on top. Maps (albedo, roughness, confidence) are shown as they are."""
        from gra_mi.core.color import display_exposure

        rgb, alpha = image[..., :3], image[..., 3:4]
        if light.stage in ("albedo", "roughness", "confidence"):
            base = 1.0
        else:
            key = (light.mode, light.envmap, light.rotation, light.olat, light.point_intensity, light.stage, light.far_field, light.bounces)
            if key not in self._base_exposure:
                self._base_exposure = {key: display_exposure(rgb, alpha[..., 0] > 0.5) if alpha.max() > 0 else 1.0}
            base = self._base_exposure[key]
        scale = base * 2.0**light.exposure
        return srgb8_fast(rgb * scale + (1 - alpha) * BACKGROUND)

    def frames_to_precompute(self) -> list[int]:
        """The frames whose visibility the page traces in the background: every frame where a disk cache keeps them,
        else as many as memory holds (:data:`VISIBILITY_BYTES`; the others are traced when shown)."""
        frames = list(range(self.num_frames))
        return frames if self.sources.vis_cache is not None else frames[: self.relighter.cache.keep]

    def precompute(self, frames: list[int], far_field: bool, progress=None, stop: threading.Event | None = None) -> list[str]:
        """Trace each frame's visibility into the cache (one frame per lock, so the page stays responsive). A frame the
        sequence holds badly (checked as it is used) is skipped; returns what was wrong with each skipped one."""
        skipped = []
        for k, frame in enumerate(frames):
            if stop is not None and stop.is_set():
                break
            with self.lock:
                try:
                    self.relighter.visibility(frame, far_field)
                except GraMiInputError as exc:
                    skipped.append(str(exc))
            if progress is not None:
                progress(k + 1, len(frames))
        return skipped

    def ground_truth(self, camera: str, frame: int) -> tuple[np.ndarray, str] | None:
        """The capture's image of ``camera`` at a frame showing this pose, as sRGB8, and what lit it."""
        if self.capture is None or camera not in self.capture.train_cameras + self.capture.eval_cameras:
            return None
        from gra_mi.core.color import display_exposure
        from gra_mi.core.io import read_exr, to_srgb8

        for entry in self.capture.frames:
            path = self.capture.image_path(camera, entry.frame)
            if entry.mesh_frame == frame and path.is_file():
                image = read_exr(path)
                lit = entry.envmap or entry.pattern or entry.kind
                return to_srgb8(image[..., :3], display_exposure(image[..., :3])), f"capture frame {entry.frame}: {Path(str(lit)).stem}"
        return None


def confidence_picture(path: Path) -> np.ndarray:
    """``confidence.exr`` (views, highlights, information per texel) as a picture, as the fit's confidence.png draws it:
    red = views seen in (relative to the most), green = highlights seen (4 or more: full)."""
    from gra_mi.core.io import read_exr_channels

    channels = read_exr_channels(path)
    missing = {"views", "highlights"} - set(channels)
    if missing:
        raise GraMiInputError(path, f"expected the fit's channels views, highlights, information; missing {sorted(missing)}")
    views, highlights = channels["views"], channels["highlights"]
    return np.stack([views / max(float(views.max()), 1.0), np.minimum(highlights / 4.0, 1.0), np.zeros_like(views)], axis=-1)


_SRGB_LEVELS = 4096


def _srgb_table() -> np.ndarray:
    from gra_mi.core.color import srgb_encode

    return (srgb_encode(np.linspace(0.0, 1.0, _SRGB_LEVELS)) * 255.0 + 0.5).astype(np.uint8)


_SRGB8 = None


def srgb8_fast(linear: np.ndarray) -> np.ndarray:
    """Linear RGB → sRGB8 through a 4096-entry table: 6× faster than the exact curve and within one 8-bit level of
    it (:func:`gra_mi.core.io.to_srgb8`), which a live view needs more than the last bit."""
    global _SRGB8
    if _SRGB8 is None:
        _SRGB8 = _srgb_table()
    index = np.clip(np.nan_to_num(linear, nan=0.0, posinf=1.0) * (_SRGB_LEVELS - 1) + 0.5, 0, _SRGB_LEVELS - 1).astype(np.int32)
    return _SRGB8[index]


def viewer_camera(position, wxyz, fov_y: float, width: int, height: int, name: str = "viewer") -> Camera:
    """A pinhole :class:`Camera` for the page's camera (OpenCV axes, as viser's): vertical field of view in radians."""
    w, x, y, z = (float(v) for v in wxyz)
    rotation = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    to_world = np.eye(4)
    to_world[:3, :3], to_world[:3, 3] = rotation, np.asarray(position, np.float64)
    f = 0.5 * height / math.tan(0.5 * fov_y)
    return Camera(name, int(width), int(height), f, f, width / 2.0, height / 2.0, to_world)


def camera_pose(camera: Camera) -> tuple[np.ndarray, np.ndarray, float]:
    """(position, wxyz, vertical field of view in radians) of a rig camera, to put the page's camera there."""
    r = camera.rotation
    w = math.sqrt(max(0.0, 1 + r[0, 0] + r[1, 1] + r[2, 2])) / 2
    if w > 1e-6:
        q = np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w), (r[1, 0] - r[0, 1]) / (4 * w)])
    else:  # a half turn: take the largest diagonal
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(max(0.0, 1 + r[i, i] - r[j, j] - r[k, k])) * 2
        q = np.zeros(4)
        q[0], q[1 + i], q[1 + j], q[1 + k] = (r[k, j] - r[j, k]) / s, s / 4, (r[j, i] + r[i, j]) / s, (r[k, i] + r[i, k]) / s
    return camera.position, q / np.linalg.norm(q), 2 * math.atan(0.5 * camera.height / camera.fy)


def scaled_to(width: int, height: int, longest: int) -> tuple[int, int]:
    """A viewport's size with its longest side at most ``longest`` (the image the server renders)."""
    scale = min(1.0, longest / max(width, height, 1))
    return max(8, round(width * scale)), max(8, round(height * scale))


def with_lighting(session: ViewerSession, **changes) -> Lighting:
    """Change the session's lighting (validated: a mode, stage or frame it does not have is refused)."""
    light = replace(session.lighting, **changes)
    if light.mode not in MODES or light.stage not in session.stages or not 0 <= light.frame < session.num_frames:
        raise GraMiInputError("viewer", f"no such choice: mode {light.mode!r}, stage {light.stage!r}, frame {light.frame}")
    if not 0 <= light.olat < session.ls.stage.num_leds or light.envmap not in session.envmap_sources:
        raise GraMiInputError("viewer", f"no LED {light.olat} or envmap {light.envmap!r}")
    if light.mode == "envmap":
        session.envmap(light.envmap)  # a map that cannot be read says so here, before the lighting changes
    transport = replace(session.relighter.transport, bounces=light.bounces)
    transport.validate()
    if session.model is not None and light.stage == "relightnet":
        from gra_mi.relightnet.model import check_input_transport

        try:
            check_input_transport(session.model.config, transport, session.sources.relightnet)
        except GraMiParameterError as exc:
            raise GraMiInputError("viewer", str(exc)) from None
    with session.lock:
        session.relighter.transport = transport
        session.lighting = light
    return light
