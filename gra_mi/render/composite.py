"""Composites: the relit subject over the environment's background plate, standing on a platform with its shadow.

The paper's supplementary renders the platform and the subject's shadow in Blender under the same environment; here
Mitsuba does it (no Blender). The platform (a disc of ``radius`` and ``thickness`` under the subject's lowest point,
grey diffuse) and the tracked mesh of the frame are path-traced under the environment at infinity, the subject as a
**black holdout**: it casts its shadow and hides what is behind it, but adds no light of its own. That layer holds
exactly what the subject changes in the background (the shadow, the occluded platform), so the composite is

    subject (premultiplied RGBA, the relit render) + layer (premultiplied) + (1 − layer alpha) · plate

where the layer's alpha covers the platform and the subject. Differential rendering (a render with and without
the subject, their ratio applied to a photographed plate) is what one does when the floor is real; this floor is
rendered, so the layer itself is the floor with its shadow. What is left out: light the subject bounces onto the
platform (a black holdout reflects none) and the platform's bounce onto the subject.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gra_mi.core.errors import GraMiParameterError, require_positive
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.envmap import background_plate
from gra_mi.stage.scene import MAX_SPP, camera_sensor_dict, render_mean
from gra_mi.subject.sequence import extent


@dataclass
class PlatformConfig:
    """The platform under a composite: a grey disc under the subject, path-traced under the envmap with its shadow."""

    radius: float = 0.6
    """Platform disc radius (m), centred under the subject's mean position over the sequence."""
    thickness: float = 0.06
    """Platform height (m); its top is at the subject's lowest point over the sequence."""
    reflectance: float = 0.45
    """Grey diffuse reflectance (albedo) of the platform."""
    spp: int = 64
    """Samples per pixel of the platform layer (path-traced, 3 bounces)."""

    def validate(self) -> None:
        require_positive({"radius": self.radius, "thickness": self.thickness, "spp": self.spp})
        if self.spp > MAX_SPP:
            raise GraMiParameterError("spp", f"must be in [1, {MAX_SPP}], got {self.spp}")
        if not 0.0 <= self.reflectance <= 1.0:
            raise GraMiParameterError("reflectance", f"must be in [0, 1], got {self.reflectance}")


PLATFORM_FLAGS = tuple((name, f"--platform-{name}") for name in ("radius", "thickness", "reflectance", "spp"))
"""How a command that also has its own ``--spp`` spells the platform's options."""


def _subject_mesh(vertices: np.ndarray, faces: np.ndarray):
    import mitsuba as mi

    from gra_mi.render.rasterize import mesh_shape  # loads Mitsuba

    black = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
    return mesh_shape(vertices, faces, "subject_holdout", black)


def platform_layer(sequence, frame: int, camera, envmap: np.ndarray, config: PlatformConfig | None = None, seed: int = 0) -> np.ndarray:
    """The platform with the subject's shadow, the subject a black holdout: (H, W, 4) premultiplied linear RGBA seen by
    ``camera``, lit by ``envmap`` (linear lat-long radiance in the units of the relit render, e.g. × the LED mapping's
    scale), the environment itself hidden (alpha 0)."""
    import mitsuba as mi

    ensure_mitsuba()
    config = config or PlatformConfig()
    config.validate()
    if not 0 <= frame < sequence.num_frames:
        raise GraMiParameterError("frame", f"frame {frame} out of range [0, {sequence.num_frames})")
    low, _, mean = extent(sequence.vertices, sequence.origin)
    top, cx, cz = float(low[1]), float(mean[0]), float(mean[2])
    grey = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [config.reflectance] * 3}}
    transform = mi.ScalarTransform4f
    scene = mi.load_dict(
        {
            "type": "scene",
            "sensor": camera_sensor_dict(camera, config.spp),
            "environment": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(np.asarray(envmap, np.float32)[..., :3]))},
            "platform_top": {
                "type": "disk",
                # the disk faces +z; rotating by −90° about x turns it to face +y (up)
                "to_world": transform().translate([cx, top, cz]).rotate([1, 0, 0], -90).scale([config.radius, config.radius, 1]),
                "bsdf": grey,
            },
            "platform_side": {
                "type": "cylinder",
                "p0": [cx, top - config.thickness, cz],
                "p1": [cx, top, cz],
                "radius": config.radius,
                "bsdf": grey,
            },
            "subject": _subject_mesh(sequence.vertices[frame], sequence.faces),
        }
    )
    integrator = mi.load_dict({"type": "path", "max_depth": 4, "hide_emitters": True})
    return render_mean(scene, 0, integrator, config.spp, seed + frame).astype(np.float32)


def composite_on_platform(subject: np.ndarray, layer: np.ndarray, plate: np.ndarray) -> np.ndarray:
    """The relit subject (premultiplied: black where it is not) + the platform layer + the plate where the layer is
    not: (H, W, 3). The subject's alpha is not needed: the layer's holdout already covers the subject."""
    if subject.shape[:2] != layer.shape[:2] or layer.shape[:2] != plate.shape[:2]:
        raise GraMiParameterError("layer", f"sizes differ: subject {subject.shape[:2]}, layer {layer.shape[:2]}, plate {plate.shape[:2]}")
    return subject[..., :3] + layer[..., :3] + (1.0 - layer[..., 3:4]) * plate[..., :3]


class PlatformCompositor:
    """Composites of a subject sequence's renders, the platform layer and background plate of the last few (frame,
    camera, lighting) kept: the renders of several stages, or lights of one frame, share them."""

    def __init__(self, sequence, config: PlatformConfig | None = None, keep: int = 16):
        self.sequence, self.config, self.keep = sequence, config or PlatformConfig(), keep
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, subject: np.ndarray, frame: int, camera, envmap: np.ndarray, scale: float, lighting: str) -> np.ndarray:
        """``subject`` (H, W, >= 3 linear, black background) of ``frame`` seen by ``camera``, lit by ``envmap`` × ``scale``
        (the LED mapping's normalisation: the units of the render); ``lighting`` names the envmap for the cache."""

        key = (frame, camera.name, camera.width, camera.height, lighting)
        if key not in self._cache:
            if len(self._cache) >= self.keep:
                self._cache.pop(next(iter(self._cache)))
            layer = platform_layer(self.sequence, frame, camera, np.asarray(envmap, np.float32) * scale, self.config)
            self._cache[key] = (layer, background_plate(envmap, camera) * scale)
        layer, plate = self._cache[key]
        return composite_on_platform(subject, layer, plate)
