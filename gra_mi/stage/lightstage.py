"""The lightstage: LEDs, cameras, and the calibration file that holds them.

World frame (docs/conventions.md): right-handed, metres, +Y up; the subject stands on y = 0 facing +Z.
Cameras use the OpenCV convention in the calibration file (x right, y down, z forward; ``camera_to_world`` maps
camera coordinates to world) because real lightstage calibrations come that way; :meth:`Camera.mitsuba_to_world`
converts to Mitsuba's camera frame (x left, y up, z forward).

The calibration file format is documented in docs/data-format.md. :func:`load_calibration` validates every field
and raises :class:`GraMiInputError` naming the file and the field.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.guard import path_component
from gra_mi.core.io import atomic_write_text, read_json
from gra_mi.core.limits import MAX_INTENSITY, require_memory

CALIBRATION_FORMAT = "gra-mi-lightstage/1"


@dataclass
class Camera:
    """A pinhole camera (OpenCV convention)."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    camera_to_world: np.ndarray  # (4, 4), OpenCV camera axes

    @property
    def position(self) -> np.ndarray:
        return self.camera_to_world[:3, 3].copy()

    @property
    def rotation(self) -> np.ndarray:
        return self.camera_to_world[:3, :3].copy()

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2.0 * math.atan(self.width / (2.0 * self.fx)))

    def mitsuba_to_world(self) -> np.ndarray:
        """``to_world`` for Mitsuba's perspective sensor: flip x and y of the OpenCV frame."""
        return self.camera_to_world @ np.diag([-1.0, -1.0, 1.0, 1.0])

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space origin (3,) and unit directions (H, W, 3) through the pixel centres."""
        xs = (np.arange(self.width) + 0.5 - self.cx) / self.fx
        ys = (np.arange(self.height) + 0.5 - self.cy) / self.fy
        d_cam = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.ones((1, 1))), axis=-1)
        d_world = d_cam @ self.rotation.T
        d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
        return self.position, d_world

    def device_rays(self, offset: tuple[float, float] = (0.5, 0.5)):
        """``mi.Ray3f`` through the point ``offset`` (in pixels, (0.5, 0.5) the centre) of each pixel, row-major, built
        on the Dr.Jit device (needs a variant set)."""
        import drjit as dr
        import mitsuba as mi

        from gra_mi.core.runtime import opaque

        index = dr.arange(mi.UInt32, self.width * self.height)
        row = index // self.width  # the image size stays a literal: it changes only when a window is resized
        ox, oy = (opaque(mi.Float, v) for v in offset)  # (a literal would compile a kernel per sub-pixel offset)
        return self.rays_through(mi.Float(index - row * self.width) + ox, mi.Float(row) + oy)

    def rays_through(self, x, y):
        """``mi.Ray3f`` through the image points (``x``, ``y``) (Dr.Jit arrays, in pixels from the top-left corner).
        The camera's numbers are kernel inputs, not literals: a moving camera reuses one kernel
        (:func:`~gra_mi.core.runtime.opaque`). (Rays made from NumPy arrays would not do: Mitsuba's tracing kernel's
        code depends on their buffers' alignment, an LLVM compile for about every camera.)"""
        import drjit as dr
        import mitsuba as mi

        from gra_mi.core.runtime import opaque

        x = (x - opaque(mi.Float, self.cx)) / opaque(mi.Float, self.fx)
        y = (y - opaque(mi.Float, self.cy)) / opaque(mi.Float, self.fy)
        r = self.rotation.T
        d = dr.normalize(x * opaque(mi.Vector3f, r[0]) + y * opaque(mi.Vector3f, r[1]) + opaque(mi.Vector3f, r[2]))
        return mi.Ray3f(opaque(mi.Point3f, self.position), d)

    def resized(self, scale: float) -> Camera:
        """The same camera with its image area-downscaled by ``scale`` (sizes floored, as torch's ``area`` resampling)."""
        from dataclasses import replace

        return replace(
            self,
            width=int(self.width * scale),
            height=int(self.height * scale),
            fx=self.fx * scale,
            fy=self.fy * scale,
            cx=self.cx * scale,
            cy=self.cy * scale,
        )

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (N, 3) → pixel coordinates (N, 2) and depth; returns (N, 3) as (x, y, z_cam)."""
        world_to_camera = np.linalg.inv(self.camera_to_world)
        p = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
        z = p[:, 2]
        return np.stack([self.fx * p[:, 0] / z + self.cx, self.fy * p[:, 1] / z + self.cy, z], axis=1)


@dataclass
class Lightstage:
    """LEDs (point emitters) and cameras around a stage centre."""

    led_positions: np.ndarray  # (L, 3) metres, world frame
    cameras: list[Camera]
    center: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    radius: float = 2.0
    led_normals: np.ndarray | None = None  # (L, 3) unit, pointing at the stage; informational
    led_gains: np.ndarray | None = None  # (L, 3) linear RGB gain per LED
    max_led_intensity: float = 1.0  # W/sr of the brightest LED setting (envmaps are normalised to it)

    @property
    def num_leds(self) -> int:
        return int(self.led_positions.shape[0])

    @property
    def gains(self) -> np.ndarray:
        return np.ones((self.num_leds, 3)) if self.led_gains is None else self.led_gains

    def led_directions(self) -> np.ndarray:
        """Unit directions from the stage centre to each LED, (L, 3)."""
        d = self.led_positions - self.center
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def led_distances(self) -> np.ndarray:
        return np.linalg.norm(self.led_positions - self.center, axis=1)

    def camera(self, index_or_name: int | str | Camera) -> Camera:
        """One of the rig's cameras by index or name; a :class:`Camera` itself passes through (a viewer's free camera
        renders like a rig camera)."""
        if isinstance(index_or_name, Camera):
            return index_or_name
        if isinstance(index_or_name, str) and not index_or_name.isdigit():
            for cam in self.cameras:
                if cam.name == index_or_name:
                    return cam
            raise GraMiParameterError("camera", f"no camera named '{index_or_name}'")
        index = int(index_or_name)
        if not 0 <= index < len(self.cameras):
            raise GraMiParameterError("camera", f"camera index {index} out of range [0, {len(self.cameras)})")
        return self.cameras[index]


# --------------------------------------------------------------------------------------------------------------
# Default rig
# --------------------------------------------------------------------------------------------------------------


def fibonacci_sphere(count: int) -> np.ndarray:
    """``count`` nearly uniform unit vectors (golden-angle spiral from +Y down to -Y)."""
    i = np.arange(count) + 0.5
    y = 1.0 - 2.0 * i / count
    r = np.sqrt(np.maximum(0.0, 1.0 - y * y))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return np.stack([r * np.sin(phi), y, r * np.cos(phi)], axis=1)


def look_at_opencv(origin: np.ndarray, target: np.ndarray, up: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """OpenCV camera-to-world matrix looking from ``origin`` at ``target`` (image y points down the world up)."""
    forward = target - origin
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-8:  # looking straight up or down
        right = np.cross(forward, np.array([0.0, 0.0, 1.0]))
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, down, forward, origin
    return m


def camera_rings(
    count: int = 40,
    distance: float = 1.8,
    elevations_deg: tuple[float, ...] = (-15.0, 0.0, 15.0, 30.0),
    target: np.ndarray = np.array([0.0, 0.9, 0.0]),
    width: int = 1024,
    height: int = 540,
    fov_y_deg: float = 62.0,
) -> list[Camera]:
    """Cameras on rings at several heights, looking at ``target``; each ring is rotated half a step."""
    rings = len(elevations_deg)
    per_ring = [count // rings + (1 if r < count % rings else 0) for r in range(rings)]
    fy = (height / 2.0) / math.tan(math.radians(fov_y_deg) / 2.0)
    cameras = []
    for r, (elev, n) in enumerate(zip(elevations_deg, per_ring, strict=True)):
        for k in range(n):
            azimuth = 2.0 * math.pi * (k + 0.5 * (r % 2)) / n
            e = math.radians(elev)
            offset = distance * np.array([math.cos(e) * math.sin(azimuth), math.sin(e), math.cos(e) * math.cos(azimuth)])
            cameras.append(
                Camera(
                    name=f"cam{len(cameras):02d}",
                    width=width,
                    height=height,
                    fx=fy,
                    fy=fy,
                    cx=width / 2.0,
                    cy=height / 2.0,
                    camera_to_world=look_at_opencv(target + offset, target),
                )
            )
    return cameras


RIG_ITEM_BYTES = 4096  # the peak of writing a rig, per LED or camera (measured: 2.2 kB an LED at 100,000 LEDs)
RIG_ITEMS = {"num_leds": "LEDs", "num_cameras": "cameras"}


@dataclass(kw_only=True)
class RigLayout:
    """The default rig's layout (:func:`default_lightstage`)."""

    num_leds: int = 331
    """LEDs spread evenly over the sphere (Fibonacci spiral)."""
    radius: float = 2.0
    """LED sphere radius in metres."""
    num_cameras: int = 40
    """Cameras on four rings at several heights."""
    camera_distance: float = 1.8
    """Camera distance from the stage centre in metres."""
    width: int = 1024
    """Image width in pixels."""
    height: int = 540
    """Image height in pixels."""
    max_led_intensity: float = 4.0
    """Radiant intensity (W/sr) of a fully driven LED; envmaps are normalised to it."""
    center: tuple[float, float, float] = (0.0, 1.0, 0.0)
    """The stage centre (metres, Y up): the sphere's centre; cameras aim 10 cm below it."""

    def validate(self) -> None:
        require_positive(
            {"num_leds": self.num_leds, "num_cameras": self.num_cameras, "width": self.width, "height": self.height}
            | {"radius": self.radius, "camera_distance": self.camera_distance, "max_led_intensity": self.max_led_intensity}
        )
        if self.camera_distance >= self.radius:
            raise GraMiInputError("rig", f"cameras ({self.camera_distance} m) must stand inside the LED sphere ({self.radius} m)")
        for name in RIG_ITEMS:  # a typed zero too many would write for an hour and fill the disk
            count = getattr(self, name)
            require_memory(name, count * RIG_ITEM_BYTES, f"a rig of {count:,} {RIG_ITEMS[name]}")

    def build(self) -> Lightstage:
        self.validate()
        c = np.asarray(self.center, dtype=np.float64)
        directions = fibonacci_sphere(self.num_leds)
        target = c - np.array([0.0, 0.1, 0.0])
        return Lightstage(
            led_positions=c + self.radius * directions,
            led_normals=-directions,
            cameras=camera_rings(self.num_cameras, self.camera_distance, target=target, width=self.width, height=self.height),
            center=c,
            radius=self.radius,
            max_led_intensity=self.max_led_intensity,
        )


def default_lightstage(**layout) -> Lightstage:
    """The default rig: LEDs evenly over a sphere (Fibonacci spiral), cameras on four rings (keywords: :class:`RigLayout`)."""
    return RigLayout(**layout).build()


# --------------------------------------------------------------------------------------------------------------
# Lighting patterns
# --------------------------------------------------------------------------------------------------------------


def olat_pattern(stage: Lightstage, led: int, intensity: float | None = None) -> np.ndarray:
    """One light at a time: (L, 3) intensities, LED ``led`` at ``intensity`` (default: the stage maximum)."""
    if not 0 <= led < stage.num_leds:
        raise GraMiParameterError("olat", f"LED index {led} out of range [0, {stage.num_leds})")
    pattern = np.zeros((stage.num_leds, 3))
    pattern[led] = stage.max_led_intensity if intensity is None else intensity
    return pattern


def uniform_pattern(stage: Lightstage, fraction: float = 1.0) -> np.ndarray:
    """All LEDs on at ``fraction`` of the maximum: the tracking ("uniformly lit") frames of a capture."""
    return np.full((stage.num_leds, 3), stage.max_led_intensity * fraction)


def validate_pattern(stage: Lightstage, pattern: np.ndarray, source: str = "pattern") -> np.ndarray:
    """Check an arbitrary LED intensity pattern: (L,) grey or (L, 3) RGB, finite, non-negative."""
    try:
        given = np.asarray(pattern)
        real = given.astype(np.float64) if not np.iscomplexobj(given) else None
    except (ValueError, TypeError):  # strings, ragged rows
        raise GraMiInputError(source, "expected a list of numbers (one per LED) or of [r, g, b] rows of numbers") from None
    if real is None:  # converting would drop the imaginary part unsaid
        raise GraMiInputError(source, "expected real LED intensities, got complex numbers")
    pattern = real
    if pattern.ndim == 1:
        pattern = np.repeat(pattern[:, None], 3, axis=1)
    if pattern.shape != (stage.num_leds, 3):
        raise GraMiInputError(source, f"expected ({stage.num_leds},) or ({stage.num_leds}, 3) LED intensities, got {pattern.shape}")
    if not np.all(np.isfinite(pattern)) or np.any(pattern < 0):
        raise GraMiInputError(source, "LED intensities must be finite and non-negative")
    if pattern.max(initial=0.0) > MAX_INTENSITY:  # drives are W/sr (emitted = drive × gain), not fractions of the maximum
        raise GraMiInputError(source, f"LED drives must be at most {MAX_INTENSITY:g} W/sr (float32's range), got {pattern.max():g}")
    return pattern


def load_pattern(stage: Lightstage, path: str | Path) -> np.ndarray:
    """An LED pattern from JSON (``{"intensities": [[r,g,b], ...]}`` or a bare list) or .npy."""
    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "file not found")
    if path.suffix == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise GraMiInputError(path, f"not a readable .npy array ({exc})") from None
    else:
        raw = read_json(path)
        data = raw.get("intensities") if isinstance(raw, dict) else raw
        if data is None:
            raise GraMiInputError(path, "missing", field="intensities")
    return validate_pattern(stage, data, source=str(path))


# --------------------------------------------------------------------------------------------------------------
# Calibration file
# --------------------------------------------------------------------------------------------------------------


def lightstage_to_dict(stage: Lightstage) -> dict:
    leds = []
    for i, p in enumerate(stage.led_positions):
        led = {"position": [round(float(x), 6) for x in p]}
        if stage.led_normals is not None:
            led["normal"] = [round(float(x), 6) for x in stage.led_normals[i]]
        if stage.led_gains is not None:
            led["gain"] = [round(float(x), 6) for x in stage.led_gains[i]]
        leds.append(led)
    cameras = [
        {
            "name": c.name,
            "image_size": [c.width, c.height],
            "intrinsics": {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy},
            "camera_to_world": [[round(float(x), 9) for x in row] for row in c.camera_to_world],
        }
        for c in stage.cameras
    ]
    return {
        "format": CALIBRATION_FORMAT,
        "units": "metres",
        "stage": {
            "center": [float(x) for x in stage.center],
            "radius": float(stage.radius),
            "max_led_intensity": float(stage.max_led_intensity),
        },
        "leds": leds,
        "cameras": cameras,
    }


def save_calibration(stage: Lightstage, path: str | Path) -> None:
    atomic_write_text(path, json.dumps(lightstage_to_dict(stage), indent=1) + "\n")


def _vector(value, length: int, source: str, field_name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise GraMiInputError(source, f"expected {length} numbers, got {value!r}", field=field_name) from None
    if arr.shape != (length,):
        raise GraMiInputError(source, f"expected {length} numbers, got {value!r}", field=field_name)
    if not np.all(np.isfinite(arr)):
        raise GraMiInputError(source, f"values must be finite, got {value!r}", field=field_name)
    return arr


def _number(obj: dict, key: str, source: str, prefix: str, positive: bool = True) -> float:
    if key not in obj:
        raise GraMiInputError(source, "missing", field=f"{prefix}{key}")
    value = obj[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise GraMiInputError(source, f"expected a finite number, got {value!r}", field=f"{prefix}{key}")
    if positive and value <= 0:
        raise GraMiInputError(source, f"expected a positive number, got {value!r}", field=f"{prefix}{key}")
    return float(value)


def lightstage_from_dict(data: dict, source: str = "<calibration>") -> Lightstage:
    """Build and validate a :class:`Lightstage` from the calibration JSON structure."""
    if not isinstance(data, dict):
        raise GraMiInputError(source, "top level must be a JSON object")
    if data.get("format") != CALIBRATION_FORMAT:
        raise GraMiInputError(source, f"expected '{CALIBRATION_FORMAT}', got {data.get('format')!r}", field="format")
    stage = data.get("stage")
    if not isinstance(stage, dict):
        raise GraMiInputError(source, "missing or not an object", field="stage")
    center = _vector(stage.get("center"), 3, source, "stage.center")
    radius = _number(stage, "radius", source, "stage.")
    max_intensity = _number(stage, "max_led_intensity", source, "stage.") if "max_led_intensity" in stage else 1.0
    positions, normals, gains = _read_leds(data.get("leds"), center, source)
    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise GraMiInputError(source, "expected a non-empty list of cameras", field="cameras")
    cameras = [_read_camera(cam, i, source) for i, cam in enumerate(cams)]
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise GraMiInputError(source, "camera names must be unique", field="cameras")
    return Lightstage(
        led_positions=positions, cameras=cameras, center=center, radius=radius, led_normals=normals, led_gains=gains,
        max_led_intensity=max_intensity,
    )  # fmt: skip


def _read_leds(leds, center: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(positions, normals or None, gains or None) of the calibration's ``leds``, checked: finite, unit normals,
    non-negative gains, given for all LEDs or none, no LED at the centre, no two at one position."""
    if not isinstance(leds, list) or not leds:
        raise GraMiInputError(source, "expected a non-empty list of LEDs", field="leds")
    positions, normals, gains = [], [], []
    has_normal = "normal" in leds[0] if isinstance(leds[0], dict) else False
    has_gain = "gain" in leds[0] if isinstance(leds[0], dict) else False
    for i, led in enumerate(leds):
        where = f"leds[{i}]"
        if not isinstance(led, dict):
            raise GraMiInputError(source, "expected an object", field=where)
        positions.append(_vector(led.get("position"), 3, source, f"{where}.position"))
        if has_normal != ("normal" in led) or has_gain != ("gain" in led):
            raise GraMiInputError(source, "'normal' and 'gain' must be given for all LEDs or for none", field=where)
        if has_normal:
            n = _vector(led["normal"], 3, source, f"{where}.normal")
            if abs(np.linalg.norm(n) - 1.0) > 1e-3:
                raise GraMiInputError(source, f"normal must have unit length, got |n| = {np.linalg.norm(n):.4f}", field=f"{where}.normal")
            normals.append(n)
        if has_gain:
            g = _vector(led["gain"], 3, source, f"{where}.gain")
            if np.any(g < 0):
                raise GraMiInputError(source, f"gain must be non-negative, got {led['gain']}", field=f"{where}.gain")
            gains.append(g)
    positions = np.stack(positions)
    distances = np.linalg.norm(positions - center, axis=1)
    if np.any(distances < 1e-6):
        raise GraMiInputError(source, "an LED sits at the stage centre", field=f"leds[{int(np.argmin(distances))}].position")
    if len(positions) > 1:
        from scipy.spatial import cKDTree

        pairs = sorted(cKDTree(positions).query_pairs(1e-6))
        if pairs:
            i, j = pairs[0]
            raise GraMiInputError(
                source, f"LEDs {i} and {j} are at the same position ({len(pairs)} such pair(s))", field=f"leds[{j}].position"
            )
    return positions, (np.stack(normals) if has_normal else None), (np.stack(gains) if has_gain else None)


def _read_camera(cam, i: int, source: str) -> Camera:
    """Camera ``i`` of the calibration, checked: image size, intrinsics (square pixels), a rigid camera-to-world."""
    where = f"cameras[{i}]"
    if not isinstance(cam, dict):
        raise GraMiInputError(source, "expected an object", field=where)
    size = cam.get("image_size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(s, int) and 0 < s <= MAX_IMAGE_SIDE for s in size)):
        raise GraMiInputError(
            source, f"expected [width, height] as integers in [1, {MAX_IMAGE_SIDE}], got {size!r}", field=f"{where}.image_size"
        )
    intr = cam.get("intrinsics")
    if not isinstance(intr, dict):
        raise GraMiInputError(source, "missing or not an object", field=f"{where}.intrinsics")
    fx = _number(intr, "fx", source, f"{where}.intrinsics.")
    fy = _number(intr, "fy", source, f"{where}.intrinsics.")
    cx = _number(intr, "cx", source, f"{where}.intrinsics.", positive=False)
    cy = _number(intr, "cy", source, f"{where}.intrinsics.", positive=False)
    if abs(fx - fy) > 1e-3 * fx:
        raise GraMiInputError(
            source,
            f"non-square pixels (fx={fx}, fy={fy}) are not supported by Mitsuba's perspective sensor",
            field=f"{where}.intrinsics",
        )
    try:
        m = np.asarray(cam.get("camera_to_world"), dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros(0)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise GraMiInputError(source, "expected a finite 4x4 matrix", field=f"{where}.camera_to_world")
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-4) or np.linalg.det(r) < 0 or not np.allclose(m[3], [0, 0, 0, 1]):
        raise GraMiInputError(
            source, "rotation part must be orthonormal with det +1 and last row [0,0,0,1]", field=f"{where}.camera_to_world"
        )
    name = path_component(cam.get("name", f"cam{i:02d}"), source, f"{where}.name")
    return Camera(name, size[0], size[1], fx, fy, cx, cy, m)


MAX_IMAGE_SIDE = 16384
"""The largest image side a calibration may give (Mitsuba's film allocates it whole; no real camera is larger)."""


def load_calibration(path: str | Path) -> Lightstage:
    """Load and validate a lightstage calibration JSON file."""
    return lightstage_from_dict(read_json(path), source=str(path))
