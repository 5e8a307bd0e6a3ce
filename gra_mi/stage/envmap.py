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

import hashlib
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.core.config import option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import read_hdr_image
from gra_mi.stage.lightstage import Camera, Lightstage, fibonacci_sphere

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

    @property
    def total(self) -> int:
        return self.nan + self.inf

    def describe(self) -> str:
        return f"{self.nan} NaN and {self.inf} Inf pixel values"


def repair_negative_flux(image: np.ndarray, radius: int = 3) -> np.ndarray:
    """Remove negative lobes (the ringing of lossy DWA compression around a sun) while keeping every channel's flux.

    Each negative pixel's flux deficit is taken from the positive pixels within ``radius`` pixels, in proportion to
    their flux, so the ringing's overshoot and undershoot cancel where they were made (clamping to 0 alone would
    add the undershoot's energy back as light). A deficit with no positive neighbour is spread over the whole map.
    """
    from scipy.ndimage import uniform_filter

    h, w = image.shape[:2]
    omega = pixel_solid_angles(h, w)[..., None]
    flux = image.astype(np.float64) * omega
    positive, deficit = np.maximum(flux, 0.0), np.minimum(flux, 0.0)
    size, mode = (1, 2 * radius + 1, 2 * radius + 1), ("nearest", "wrap", "constant")
    box = np.transpose(positive, (2, 0, 1))  # channels first: filter rows (clamped) and columns (wrapping) only
    local = np.transpose(uniform_filter(box, size=size, mode=mode), (1, 2, 0))
    share = np.where(local > 0, deficit / np.where(local > 0, local, 1.0), 0.0)
    taken = positive * np.transpose(uniform_filter(np.transpose(share, (2, 0, 1)), size=size, mode=mode), (1, 2, 0))
    repaired = np.maximum(positive + taken, 0.0)
    # What could not be taken locally (no or too little positive flux nearby) comes off the whole map.
    target = flux.sum(axis=(0, 1))
    total = repaired.sum(axis=(0, 1))
    repaired *= np.where(total > 0, np.maximum(target, 0.0) / np.where(total > 0, total, 1.0), 0.0)
    return (repaired / omega).astype(np.float32)


def downsample_envmap(image: np.ndarray, height: int) -> np.ndarray:
    """A lat-long map at ``height`` rows (width 2 x height) with each channel's flux exactly preserved: every source
    pixel's flux ``L Ω`` goes to the target pixel its direction falls in, divided by that pixel's solid angle."""
    h, w = image.shape[:2]
    if height >= h:
        return image
    u, v = pixel_uv(h, w)
    cols = np.minimum((u * 2 * height).astype(np.int64), 2 * height - 1)
    rows = np.rint(v * (height - 1)).astype(np.int64)
    index = (rows[:, None] * (2 * height) + cols[None, :]).ravel()
    flux = (image[..., :3].astype(np.float64) * pixel_solid_angles(h, w)[..., None]).reshape(-1, 3)
    out = np.stack([np.bincount(index, weights=flux[:, c], minlength=2 * height * height) for c in range(3)], axis=-1)
    return (out.reshape(height, 2 * height, 3) / pixel_solid_angles(height, 2 * height)[..., None]).astype(np.float32)


# Where other tools put the image centre, as a longitude shift into gra-mi's convention: out(u) = source(u + shift).
# Blender's world texture (and so Poly Haven maps) and three.js / glTF viewers centre the image on +X of their
# worlds; with the usual Y-up conversion (Blender (x, y, z) -> (x, z, -y), as glTF exporters do) that is gra-mi's
# +X, a quarter turn from gra-mi's (and Mitsuba's) centre at +Z. Rows are top = zenith everywhere.
ENVMAP_CONVENTIONS = {"mitsuba": 0.0, "gra-mi": 0.0, "blender": 0.25, "polyhaven": 0.25, "threejs": 0.25, "gltf": 0.25}


def shift_longitude(image: np.ndarray, shift: float) -> np.ndarray:
    """out(u) = image(u + shift), wrapping around; whole-pixel shifts are exact, others interpolate linearly."""
    w = image.shape[1]
    columns = shift * w
    whole = math.floor(columns)
    frac = columns - whole
    rolled = np.roll(image, -whole, axis=1)
    if abs(frac) < 1e-9:
        return rolled.copy()
    return ((1.0 - frac) * rolled + frac * np.roll(rolled, -1, axis=1)).astype(image.dtype)


BRIGHT_FACTOR = 100.0
"""A pixel is "very bright" (a light source) at this many times the map's median brightness (max channel)."""


def destroyed_colour(image: np.ndarray) -> np.ndarray:
    """Mask of very bright pixels (:data:`BRIGHT_FACTOR`) with a colour channel at or below zero: the signature of a
    light source whose colour lossy (DWA) compression destroyed (seen in real maps: a sun of (0, 0, 11800), which
    lights a subject violet). Real light sources, even a deep-orange sun, keep every channel above zero."""
    peak = image.max(axis=2)
    lit = peak[peak > 0]
    if lit.size == 0:
        return np.zeros(peak.shape, bool)
    return (peak > BRIGHT_FACTOR * float(np.median(lit))) & (image.min(axis=2) <= 0)


def _warn_destroyed_colour(image: np.ndarray, source: str) -> None:
    bad = destroyed_colour(image)
    if not bad.any():
        return
    h, w = image.shape[:2]
    flux = np.maximum(image, 0).astype(np.float64).sum(axis=2) * pixel_solid_angles(h, w)
    row, col = np.unravel_index(np.argmax(np.where(bad, image.max(axis=2), -np.inf)), bad.shape)
    rgb = ", ".join(f"{v:.4g}" for v in image[row, col])
    logger.warning(
        "%s: %d very bright pixel(s) have a colour channel at zero (brightest: row %d, column %d = (%s)), carrying "
        "%.0f %% of the map's light: the signature of a light source destroyed by lossy (DWA) compression, which "
        "would light the subject in that false colour. Re-export the map losslessly (ZIP/PIZ) or repaint the source.",
        source, int(bad.sum()), row, col, rgb, 100 * flux[bad].sum() / max(flux.sum(), 1e-300),
    )  # fmt: skip


def validate_envmap(image: np.ndarray, source: str = "<envmap>", repair: bool = False) -> np.ndarray:
    """Check shape (lat-long: W = 2 H, 1/3/4 channels) and values; return an (H, W, 3) float32 copy.

    Negative values (lossy compression's ringing) are removed with the flux kept (:func:`repair_negative_flux`)
    and a one-line warning; a light source with a channel at zero is warned about (:func:`destroyed_colour`). NaN/Inf raise :class:`GraMiInputError`, or with ``repair=True`` become 0 (NaN, −Inf)
    and the largest finite value (+Inf), with a warning. A map with no positive energy is an error.
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
    issues = EnvmapIssues(nan=int(np.isnan(image).sum()), inf=int(np.isinf(image).sum()))
    if issues.total:
        if not repair:
            raise GraMiInputError(
                source, f"contains {issues.describe()} (--repair-envmap, or repair=True in Python, replaces them with a warning)"
            )
        finite = image[np.isfinite(image)]
        top = float(finite.max()) if finite.size else 0.0
        image = np.nan_to_num(image, nan=0.0, posinf=top, neginf=0.0)
        logger.warning("%s: repaired %s", source, issues.describe())
    _warn_destroyed_colour(image, source)  # before the ringing is removed: the destroyed channels are <= 0 there
    negative = image < 0
    if negative.any():
        low = float(image.min())
        image = repair_negative_flux(image)
        logger.warning(
            "%s: %d negative values (down to %.4g; lossy-compression ringing) removed, flux of each channel kept",
            source,
            int(negative.sum()),
            low,
        )
    flux = float((image.astype(np.float64) * pixel_solid_angles(h, w)[..., None]).sum())
    if not flux > 0:
        raise GraMiInputError(source, "the map carries no light (its total energy is zero)")
    return image


DEFAULT_ENVMAP_HEIGHT = 256  # larger maps are downsampled (flux kept) before the LED mapping: 331 LEDs see no more


def load_envmap(
    path: str | Path, repair: bool = False, convention: str = "mitsuba", rotate_deg: float = 0.0, max_height: int = DEFAULT_ENVMAP_HEIGHT
) -> np.ndarray:
    """Read a lat-long HDR map (OpenEXR or Radiance .hdr), validate it (:func:`validate_envmap`), bring it into
    gra-mi's convention (``convention``: where the source tool puts the image centre, see ``ENVMAP_CONVENTIONS``;
    ``rotate_deg``: a further turn about the up axis, counter-clockwise seen from above) and downsample it to at
    most ``max_height`` rows with its flux kept."""

    if convention not in ENVMAP_CONVENTIONS:
        raise GraMiInputError(path, f"unknown envmap convention '{convention}', expected one of {sorted(ENVMAP_CONVENTIONS)}")
    if not math.isfinite(rotate_deg):
        raise GraMiInputError(path, f"rotation must be finite, got {rotate_deg}")
    image = validate_envmap(read_hdr_image(path), source=str(path), repair=repair)
    image = downsample_envmap(image, max_height)
    # A counter-clockwise turn moves light from u to u - angle/360 (see :func:`rotate`), so out(u) = in(u + angle/360).
    shift = ENVMAP_CONVENTIONS[convention] + rotate_deg / 360.0
    return shift_longitude(image, shift) if shift % 1.0 else image


@dataclass
class EnvmapOptions:
    """How the user's HDR maps are read (:func:`load_envmap`): the options every command that takes envmaps shares."""

    envmap_convention: str = field(default="mitsuba", metadata=option(choices=tuple(sorted(ENVMAP_CONVENTIONS))))
    """Which tool's lat-long layout the envmaps follow: mitsuba/gra-mi (image centre = +Z), blender/polyhaven or
    threejs/gltf (centre = +X after the usual Y-up conversion); see docs/conventions.md."""
    envmap_rotate: float = 0.0
    """Turn the envmaps about the up axis by this many degrees (counter-clockwise seen from above)."""
    envmap_height: int = DEFAULT_ENVMAP_HEIGHT
    """Larger envmaps are downsampled to this many rows, flux kept, before the LED mapping."""
    repair_envmap: bool = False
    """Replace NaN/Inf envmap pixels (with a warning) instead of stopping. Negative pixels (lossy-compression ringing)
    are always removed with the flux kept, with a warning."""

    def validate(self) -> None:
        if self.envmap_height < 2:
            raise GraMiParameterError("envmap_height", f"must be >= 2, got {self.envmap_height}")
        if not math.isfinite(self.envmap_rotate):
            raise GraMiParameterError("envmap_rotate", f"must be a finite angle in degrees, got {self.envmap_rotate}")

    def load(self, path: str | Path) -> np.ndarray:
        return load_envmap(path, self.repair_envmap, self.envmap_convention, self.envmap_rotate, self.envmap_height)


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
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(led_directions)
    except (QhullError, ValueError) as exc:  # fewer than 4 LEDs, or all in one plane: no hull to look through
        raise ValueError(f"the LED directions span no convex hull ({str(exc).splitlines()[0][:80]})") from None
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
            index, weights = _rig_table("triangles", (h, w), led_dirs, lambda: led_triangle_weights(directions, led_dirs))
        except ValueError as exc:
            logger.warning("LEDs do not surround the stage centre (%s): using nearest-LED (Voronoi) cells", exc)
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
    cells = _led_cells(stage.led_directions(), height)
    per_led = np.asarray(intensities, np.float64) / (stage.led_distances()[:, None] ** 2 * (4.0 * math.pi / stage.num_leds))
    return per_led[cells].astype(np.float32)


_RIG_TABLES: dict[tuple, object] = {}


def _rig_table(kind: str, size: tuple[int, int], led_directions: np.ndarray, compute):
    """A per-pixel table of a rig at one lat-long height (each pixel's LED triangle and weights, or its nearest LED),
    made once: every envmap of that size on that rig shares it, so a new map, a rotation or a video's frames pay only
    the sums (a 331-LED rig at 64 rows: 210 ms to make, then free)."""
    key = (kind, size, hashlib.sha1(np.ascontiguousarray(led_directions, np.float64).tobytes()).hexdigest())
    if key not in _RIG_TABLES:
        if len(_RIG_TABLES) > 16:
            _RIG_TABLES.clear()
        _RIG_TABLES[key] = compute()
    return _RIG_TABLES[key]


def _led_cells(led_directions: np.ndarray, height: int) -> np.ndarray:
    """Each lat-long pixel's nearest LED (the Voronoi cells) for this rig and height."""
    return _rig_table(
        "nearest", (height, 2 * height), led_directions, lambda: nearest_led(pixel_directions(height, 2 * height), led_directions)
    )


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


FIDELITY_NORMALS = 256


def led_fidelity(envmap: np.ndarray, stage: Lightstage, num_normals: int = FIDELITY_NORMALS) -> dict[str, float]:
    """How well the LED mapping reproduces the envmap's irradiance at the stage centre, over ``num_normals`` normals
    spread evenly over the sphere: max and mean relative error per normal (luminance-free: channels averaged), for
    the barycentric mapping and for the least-squares optimum under non-negativity (NNLS on LED intensities, solved
    on another, denser set of normals so the figure is not the fit's own residual). The error is relative to each
    normal's irradiance, floored at 5 % of the mean so that normals facing away from all light do not divide by ~0.
    ``glossy_*``: the same for a glossy lobe, where the optimum for irradiance falls apart (it moves the light).
    """
    from scipy.optimize import nnls

    def errors(normals, intensities):
        truth = envmap_irradiance(envmap, normals).mean(axis=1)
        got = led_irradiance(stage, intensities, normals).mean(axis=1)
        floor = 0.05 * truth.mean()
        return np.abs(got - truth) / np.maximum(truth, floor)

    normals = fibonacci_sphere(num_normals)
    mapped = envmap_to_leds(envmap, stage, normalize=False).radiant_intensity(stage)
    barycentric = errors(normals, mapped)
    # The optimum, fitted on 4x as many normals (turned, so none coincides with an evaluation normal).
    fit_normals = fibonacci_sphere(4 * num_normals) @ rotation_y(17.0).T
    truth = envmap_irradiance(envmap, fit_normals)
    weights = 1.0 / np.maximum(truth.mean(axis=1), 0.05 * truth.mean())
    design = np.maximum(fit_normals @ stage.led_directions().T, 0.0) / stage.led_distances()[None, :] ** 2
    optimum = np.stack([nnls(design * weights[:, None], truth[:, c] * weights, maxiter=20 * stage.num_leds)[0] for c in range(3)], axis=1)
    best = errors(normals, optimum)

    def glossy(intensities):
        # What a glossy surface reflects: the light convolved with a lobe exp(κ(cos − 1)), κ = 20 (about GGX
        # roughness 0.35), toward the same directions. Irradiance alone cannot tell where the light comes from.
        h, w = envmap.shape[:2]
        flux = (envmap[..., :3].astype(np.float64) * pixel_solid_angles(h, w)[..., None]).reshape(-1, 3).mean(axis=1)
        truth = np.exp(20.0 * (normals @ pixel_directions(h, w).reshape(-1, 3).T - 1.0)) @ flux
        got = np.exp(20.0 * (normals @ stage.led_directions().T - 1.0)) @ (intensities.mean(axis=1) / stage.led_distances() ** 2)
        return float((np.abs(got - truth) / np.maximum(truth, 0.05 * truth.mean())).mean())

    return {
        "normals": num_normals,
        "max_rel_error": float(barycentric.max()),
        "mean_rel_error": float(barycentric.mean()),
        "optimum_max_rel_error": float(best.max()),
        "optimum_mean_rel_error": float(best.mean()),
        "glossy_mean_rel_error": glossy(mapped),
        "optimum_glossy_mean_rel_error": glossy(optimum),
    }


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
