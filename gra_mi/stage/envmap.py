"""Environment maps: one lat-long convention, HDR I/O, LED integration, rotation, camera-space projection.

The convention (docs/conventions.md), identical to Mitsuba's ``envmap`` emitter with an identity ``to_world``:

    u = atan2(x, -z) / (2 pi)  (mod 1),     v = acos(y) / pi,
    direction(u, v) = (sin(pi v) sin(2 pi u), cos(pi v), -sin(pi v) cos(2 pi u)),

where (u, v) ∈ [0, 1]² spans the image (u → columns, v → rows). The image centre (u = 0.5) looks toward +Z,
u = 0.25 toward +X, row 0 toward +Y (the zenith). Sampling, as Mitsuba's ``envmap`` reads a bitmap:
columns are pixel *centres*, u_j = (j + 0.5) / W, wrapping around; rows run pole to pole *inclusive*,
v_i = i / (H − 1), so row 0 is the zenith itself and row H − 1 the nadir. Pixel (i, j) stands for the band
θ ∈ [π (i − ½)/(H − 1), π (i + ½)/(H − 1)] ∩ [0, π] of width 2π/W. Look-ups are bilinear in these coordinates.
Values are linear Rec.709 radiance (W m⁻² sr⁻¹ per channel).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_exr
from gra_mi.stage.lightstage import Camera, Lightstage

logger = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------------------
# Convention: pixel <-> direction
# --------------------------------------------------------------------------------------------------------------


def uv_to_direction(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Lat-long coordinates in [0, 1]² → unit directions (..., 3)."""
    phi, theta = np.broadcast_arrays(2.0 * np.pi * np.asarray(u), np.pi * np.asarray(v))
    s = np.sin(theta)
    return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], axis=-1)


def direction_to_uv(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions (..., 3) → lat-long (u, v) in [0, 1)² × [0, 1]."""
    d = np.asarray(d, dtype=np.float64)
    u = np.mod(np.arctan2(d[..., 0], -d[..., 2]) / (2.0 * np.pi), 1.0)
    v = np.arccos(np.clip(d[..., 1], -1.0, 1.0)) / np.pi
    return u, v


def pixel_uv(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(u of each column, v of each row): column centres, rows from pole to pole."""
    return (np.arange(width) + 0.5) / width, np.arange(height) / (height - 1)


def pixel_directions(height: int, width: int) -> np.ndarray:
    """The direction each pixel stands for, (H, W, 3)."""
    u, v = pixel_uv(height, width)
    return uv_to_direction(u[None, :], v[:, None])


def _row_band_edges(height: int) -> np.ndarray:
    """Polar angle of the band edges of each row, (H + 1,), clipped to [0, pi]."""
    return np.clip(np.pi * (np.arange(height + 1) - 0.5) / (height - 1), 0.0, np.pi)


def pixel_solid_angles(height: int, width: int) -> np.ndarray:
    """Exact solid angle of each pixel's band, (H, 1): (2 pi / W)(cos θ_top − cos θ_bottom). Sums to 4π."""
    edges = np.cos(_row_band_edges(height))
    return ((2.0 * np.pi / width) * (edges[:-1] - edges[1:]))[:, None]


def pixel_subsamples(height: int, width: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n×n directions inside each pixel's band, (H, W, n², 3), and their solid-angle weights, (H, 1, n²).

    Weights of one pixel sum to 1, so averaging sub-sample values with them is flux-preserving box filtering.
    ``n = 1`` is point sampling at each pixel's own direction.
    """
    if n == 1:
        return pixel_directions(height, width)[:, :, None, :], np.ones((height, 1, 1))
    edges = _row_band_edges(height)
    k = (np.arange(n) + 0.5) / n
    cos_edges = np.cos(edges)
    # Equal-area strata within the band (uniform in cos θ), uniform strata in φ.
    cos_theta = cos_edges[:-1, None] + (cos_edges[1:, None] - cos_edges[:-1, None]) * k[None, :]  # (H, n)
    v = np.arccos(np.clip(cos_theta, -1.0, 1.0)) / np.pi
    u = (np.arange(width)[:, None] + k[None, :]) / width  # (W, n)
    uu = np.broadcast_to(u[None, :, None, :], (height, width, n, n))
    vv = np.broadcast_to(v[:, None, :, None], (height, width, n, n))
    d = uv_to_direction(uu, vv).reshape(height, width, n * n, 3)
    return d, np.full((height, 1, n * n), 1.0 / (n * n))


def lookup(envmap: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Bilinear radiance look-up along world directions (..., 3) → (..., C), exactly as Mitsuba filters."""
    h, w = envmap.shape[:2]
    u, v = direction_to_uv(directions)
    x = u * w - 0.5
    y = v * (h - 1)
    x0 = np.floor(x).astype(np.int64)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    x0w, x1w = np.mod(x0, w), np.mod(x0 + 1, w)
    y1 = y0 + 1
    top = envmap[y0, x0w] * (1 - fx) + envmap[y0, x1w] * fx
    bottom = envmap[y1, x0w] * (1 - fx) + envmap[y1, x1w] * fx
    return top * (1 - fy) + bottom * fy


# --------------------------------------------------------------------------------------------------------------
# Loading and validation
# --------------------------------------------------------------------------------------------------------------


@dataclass
class EnvmapIssues:
    nan: int
    inf: int
    negative: int

    @property
    def total(self) -> int:
        return self.nan + self.inf + self.negative

    def describe(self) -> str:
        return f"{self.nan} NaN, {self.inf} Inf and {self.negative} negative pixel values"


def validate_envmap(image: np.ndarray, source: str = "<envmap>", repair: bool = False) -> np.ndarray:
    """Check shape (lat-long: W = 2 H, 1/3/4 channels) and values; return an (H, W, 3) float32 copy.

    NaN/Inf/negative values raise :class:`GraMiInputError`, or with ``repair=True`` are replaced (NaN → 0,
    +Inf → the largest finite value, −Inf and negatives → 0) with a warning that says how many.
    """
    image = np.asarray(image)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[2] not in (1, 3, 4):
        raise GraMiInputError(source, f"expected an (H, W, 1|3|4) image, got shape {image.shape}")
    h, w = image.shape[:2]
    if w != 2 * h or h < 2:
        raise GraMiInputError(source, f"a lat-long envmap must be twice as wide as high (W = 2H, H >= 2), got {w}x{h}")
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    image = np.array(image[..., :3], dtype=np.float32)
    issues = EnvmapIssues(nan=int(np.isnan(image).sum()), inf=int(np.isinf(image).sum()), negative=int((image < 0).sum()))
    if issues.total:
        if not repair:
            raise GraMiInputError(source, f"contains {issues.describe()} (use the repair option to fix them)")
        finite = image[np.isfinite(image)]
        top = float(finite.max()) if finite.size else 0.0
        image = np.nan_to_num(image, nan=0.0, posinf=top, neginf=0.0)
        image = np.maximum(image, 0.0)
        logger.warning("%s: repaired %s", source, issues.describe())
    return image


def load_envmap(path: str | Path, repair: bool = False) -> np.ndarray:
    """Read a lat-long HDR EXR and validate it (see :func:`validate_envmap`)."""
    return validate_envmap(read_exr(path), source=str(path), repair=repair)


# --------------------------------------------------------------------------------------------------------------
# Integration onto the lightstage LEDs
# --------------------------------------------------------------------------------------------------------------


def nearest_led(directions: np.ndarray, led_directions: np.ndarray, chunk: int = 16384) -> np.ndarray:
    """Index of the LED whose direction is closest to each direction: the LED's (Voronoi) cell on the sphere."""
    flat = directions.reshape(-1, 3)
    out = np.empty(flat.shape[0], dtype=np.int64)
    for start in range(0, flat.shape[0], chunk):
        out[start : start + chunk] = np.argmax(flat[start : start + chunk] @ led_directions.T, axis=1)
    return out.reshape(directions.shape[:-1])


def led_triangle_weights(directions: np.ndarray, led_directions: np.ndarray, chunk: int = 8192) -> tuple[np.ndarray, np.ndarray]:
    """For each direction ω, the three LEDs of the triangle (of the LEDs' convex hull) that ω points through,
    and weights w ≥ 0 summing to 1 with Σ w_k d_k ∥ ω (spherical barycentric coordinates): (N, 3), (N, 3).

    Raises ValueError when the LEDs do not surround the stage centre (then no such triangle exists everywhere).
    """
    from scipy.spatial import ConvexHull

    hull = ConvexHull(led_directions)
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]
    if np.any(offsets >= -1e-6):
        raise ValueError("the LEDs do not surround the stage centre")
    inverse = np.linalg.inv(np.transpose(led_directions[hull.simplices], (0, 2, 1)))  # (F, 3, 3): ω -> w
    flat = directions.reshape(-1, 3)
    index = np.empty((flat.shape[0], 3), dtype=np.int64)
    weights = np.empty((flat.shape[0], 3))
    for start in range(0, flat.shape[0], chunk):
        d = flat[start : start + chunk]
        face = np.argmax((d @ normals.T) / -offsets[None, :], axis=1)  # the first face the ray leaves through
        index[start : start + chunk] = hull.simplices[face]
        weights[start : start + chunk] = np.einsum("nij,nj->ni", inverse[face], d)
    weights = np.maximum(weights, 0.0)
    # Normalised to sum 1 so that flux is conserved exactly; Σ w d is then ω shortened by the triangle's sagitta
    # (0.6 % for 331 LEDs), which scales the irradiance of that pixel by the same factor.
    return index, weights / weights.sum(axis=1, keepdims=True)


@dataclass
class LedLighting:
    """LED drive values for one envmap, and how to get back to physical units."""

    drive: np.ndarray  # (L, 3) what the stage is told, normalised so that max == stage.max_led_intensity
    scale: float  # drive = scale * (physical radiant intensity / gain)

    def radiant_intensity(self, stage: Lightstage) -> np.ndarray:
        """Emitted radiant intensity (W/sr) per LED after the normalisation: drive * gain."""
        return self.drive * stage.gains


CELL_MODES = ("triangle", "voronoi")


def envmap_to_leds(envmap: np.ndarray, stage: Lightstage, normalize: bool = True, cells: str = "triangle") -> LedLighting:
    """Integrate an envmap onto the LEDs, solid-angle weighted, pixel by pixel.

    Each pixel's flux ``L Ω`` (Ω its exact solid angle) is shared among LEDs, so a one-pixel sun is never missed:
      - ``cells="triangle"`` (default): among the three LEDs around its direction, with barycentric weights that
        keep the direction (Σ w_k d_k ∥ ω). Each LED's cell is the hat-shaped footprint of its triangles.
        Irradiance E(n) is linear in ω wherever no cosine is clamped, so it is matched there up to the
        triangles' curvature (0.6 % for 331 LEDs); a sun keeps its direction instead of snapping to an LED.
      - ``cells="voronoi"``: all of it to the LED nearest in direction (hard cells; the sun snaps to an LED).
    An LED at distance r from the stage centre needs radiant intensity ``I = r² Σ w L Ω`` to give the stage
    centre the irradiance of its share. With ``normalize`` the drive values are scaled so the brightest LED is at
    the stage maximum, as the paper does (Supp. "Details about the Dataset").
    """
    if cells not in CELL_MODES:
        raise ValueError(f"cells must be one of {CELL_MODES}, got {cells!r}")
    h, w = envmap.shape[:2]
    directions = pixel_directions(h, w).reshape(-1, 3)
    flux = (envmap[..., :3].astype(np.float64) * pixel_solid_angles(h, w)[..., None]).reshape(-1, 3)
    led_dirs = stage.led_directions()
    if cells == "triangle":
        try:
            index, weights = led_triangle_weights(directions, led_dirs)
        except ValueError:
            logger.warning("LEDs do not surround the stage centre: using nearest-LED (Voronoi) cells")
            cells = "voronoi"
    if cells == "voronoi":
        index = nearest_led(directions, led_dirs)[:, None]
        weights = np.ones((directions.shape[0], 1))
    per_led = np.zeros((stage.num_leds, 3))
    for c in range(3):
        per_led[:, c] = np.bincount(index.ravel(), weights=(weights * flux[:, c : c + 1]).ravel(), minlength=stage.num_leds)
    physical = per_led * stage.led_distances()[:, None] ** 2
    drive = physical / np.maximum(stage.gains, 1e-12)
    scale = 1.0
    if normalize and drive.max() > 0:
        scale = stage.max_led_intensity / float(drive.max())
    return LedLighting(drive=drive * scale, scale=scale)


def leds_to_envmap(stage: Lightstage, intensities: np.ndarray, height: int = 16) -> np.ndarray:
    """The lat-long envmap an LED pattern stands for, seen from the stage centre: each pixel takes its nearest
    LED's radiant intensity spread over that LED's cell (radiance = I / (r² Ω_cell)). The inverse of
    :func:`envmap_to_leds` up to the cells' resolution; it turns any lighting (OLAT, patterns, point-light
    conditioning) into an envmap for the learned stages."""
    cells = nearest_led(pixel_directions(height, 2 * height), stage.led_directions())
    per_led = np.asarray(intensities, np.float64) / (stage.led_distances()[:, None] ** 2 * (4.0 * math.pi / stage.num_leds))
    return per_led[cells].astype(np.float32)


def envmap_irradiance(envmap: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance E(n) = ∫ L(ω) max(0, n·ω) dω at the stage centre for unit normals (N, 3) → (N, 3)."""
    h, w = envmap.shape[:2]
    d = pixel_directions(h, w).reshape(-1, 3)
    weights = np.maximum(normals @ d.T, 0.0) * np.repeat(pixel_solid_angles(h, w), w, axis=1).reshape(1, -1)
    return weights @ envmap.reshape(-1, 3).astype(np.float64)


def led_irradiance(stage: Lightstage, intensities: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Irradiance at the stage centre from point LEDs of radiant intensity (L, 3): Σ I max(0, n·d) / r²."""
    cos = np.maximum(normals @ stage.led_directions().T, 0.0)
    return (cos / stage.led_distances()[None, :] ** 2) @ intensities


# --------------------------------------------------------------------------------------------------------------
# Rotation, camera space, background plates
# --------------------------------------------------------------------------------------------------------------


def rotation_y(angle_deg: float) -> np.ndarray:
    """Rotation about +Y (the up axis), counter-clockwise seen from above for positive angles."""
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def resample(envmap: np.ndarray, frame_to_world: np.ndarray, supersample: int = 2) -> np.ndarray:
    """The envmap re-expressed in another frame: out(ω) = envmap(frame_to_world · ω), box-filtered per pixel."""
    h, w = envmap.shape[:2]
    d, weights = pixel_subsamples(h, w, supersample)
    values = lookup(envmap, d @ np.asarray(frame_to_world).T)  # (H, W, n², C)
    return (values * weights[..., None]).sum(axis=2).astype(np.float32)


def rotate(envmap: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Rotate the lighting by ``rotation`` (3x3): light that came from ω now comes from R ω."""
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape == (3, 3) and np.allclose(r, rotation_y(math.degrees(math.atan2(r[0, 2], r[0, 0])))):
        # About the up axis by a whole number of pixels: an exact column shift.
        h, w = envmap.shape[:2]
        shift = math.degrees(math.atan2(r[0, 2], r[0, 0])) / 360.0 * w
        if abs(shift - round(shift)) < 1e-6:
            # Light from u moves to u - angle/360 (a counter-clockwise turn seen from above lowers u).
            return np.roll(envmap, -int(round(shift)), axis=1).copy()
    return resample(envmap, r.T)


def camera_envmap_frame(camera: Camera) -> np.ndarray:
    """Rotation from the camera's envmap frame to world: x left, y up (image up), z forward (Mitsuba's camera)."""
    return camera.mitsuba_to_world()[:3, :3]


def to_camera_space(envmap: np.ndarray, camera: Camera, supersample: int = 2) -> np.ndarray:
    """The paper's E^κ: the envmap in the camera's frame, so its centre is what the camera looks toward."""
    return resample(envmap, camera_envmap_frame(camera), supersample)


def background_plate(envmap: np.ndarray, camera: Camera) -> np.ndarray:
    """The envmap as ``camera`` sees it (no subject): (H, W, 3) linear radiance, one look-up per pixel centre."""
    _, directions = camera.pixel_rays()
    return lookup(envmap, directions).astype(np.float32)


def stage_background_plate(envmap: np.ndarray, camera: Camera, stage: Lightstage) -> np.ndarray:
    """The background plate in the units of a render lit by ``envmap`` on ``stage``: the LED mapping normalises the
    whole lighting to the stage's maximum (:func:`envmap_to_leds`), so the plate takes the same scale."""
    return background_plate(envmap, camera) * envmap_to_leds(envmap, stage).scale
