"""Procedural HDR environment maps: outdoor skies (Mitsuba's ``sunsky`` baked to lat-long) and indoor rooms.

No HDRI set can be downloaded, so training and held-out test lighting is generated. Each map is a pure function of
its seed; the training and test sets use disjoint seed ranges (:data:`SPLIT_SEED_BASE`), so a test envmap can never
leak into training.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.io import atomic_write_text, write_exr, write_png
from gra_mi.core.progress import progress
from gra_mi.stage.envmap import direction_to_uv, pixel_directions, pixel_solid_angles, pixel_subsamples

logger = logging.getLogger(__name__)

SPLIT_SEED_BASE = {"train": 0, "test": 1_000_000}
SUN_ANGULAR_RADIUS = math.radians(0.2667)

BAKE_BYTES_PER_PIXEL = 512  # the peak of baking one map (measured: about 400 bytes a pixel, the sky's directions)


def _bake(height: int, supersample: int, radiance_of) -> np.ndarray:
    """Box-filtered lat-long map of ``radiance_of(directions (..., 3)) -> (..., 3)``."""
    d, weights = pixel_subsamples(height, 2 * height, supersample)
    return (radiance_of(d) * weights[..., None]).sum(axis=2).astype(np.float32)


def splat_flux(envmap: np.ndarray, direction: np.ndarray, flux: np.ndarray) -> None:
    """Add a point source of ``flux`` (W/m² per channel at the centre) at ``direction``, bilinearly, in place.

    Radiance = flux / pixel solid angle, so the integral over the map gains exactly ``flux``: this is how a sun
    far smaller than a pixel keeps its energy.
    """
    h, w = envmap.shape[:2]
    u, v = direction_to_uv(direction)
    x, y = float(u) * w - 0.5, float(v) * (h - 1)
    x0, y0 = math.floor(x), min(max(math.floor(y), 0), h - 2)
    fx, fy = x - x0, y - y0
    sa = pixel_solid_angles(h, w)[:, 0]
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            row, col = y0 + dy, (x0 + dx) % w
            envmap[row, col] += (wx * wy) * flux / sa[row]


# --------------------------------------------------------------------------------------------------------------
# Outdoor skies
# --------------------------------------------------------------------------------------------------------------


@dataclass
class SkyParams:
    sun_elevation_deg: float
    sun_azimuth_deg: float  # 0 = toward +Z, 90 = toward +X
    turbidity: float
    ground_albedo: float
    sky_scale: float = 1.0
    sun_scale: float = 1.0


def sun_direction(params: SkyParams) -> np.ndarray:
    e, a = math.radians(params.sun_elevation_deg), math.radians(params.sun_azimuth_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def _eval_emitter(emitter, directions: np.ndarray) -> np.ndarray:
    import drjit as dr
    import mitsuba as mi

    flat = directions.reshape(-1, 3).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, flat.shape[0])
    si.wi = mi.Vector3f(-flat[:, 0], -flat[:, 1], -flat[:, 2])
    value = emitter.eval(si)
    return np.array(value, dtype=np.float64).T.reshape(*directions.shape[:-1], 3)


def bake_sunsky(params: SkyParams, height: int = 128, supersample: int = 2) -> np.ndarray:
    """Bake Mitsuba's ``sunsky`` emitter to a lat-long map (needs a Mitsuba variant set).

    The sky is evaluated at sub-pixel centres; the sun (0.53° wide, smaller than a pixel) is integrated over its
    disc and splatted with exact flux. Below the horizon: a diffuse ground lit by sun and sky.
    """
    import mitsuba as mi

    # Mitsuba's sunsky is Z-up in its local frame; to_world turns local +Z into our +Y. sun_direction is in world.
    z_up_to_y_up = mi.ScalarTransform4f([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
    sun = sun_direction(params)
    common = {
        "type": "sunsky",
        "to_world": z_up_to_y_up,
        "sun_direction": mi.ScalarVector3f(*sun),
        "turbidity": params.turbidity,
        "albedo": params.ground_albedo,
    }
    sky = mi.load_dict({**common, "sun_scale": 0.0, "sky_scale": params.sky_scale})
    d, weights = pixel_subsamples(height, 2 * height, supersample)
    values = _eval_emitter(sky, d)

    # Sun: integrate its radiance over a cone a bit wider than the disc (stratified in area).
    sun_only = mi.load_dict({**common, "sun_scale": params.sun_scale, "sky_scale": 0.0})
    n = 64
    cone = 1.5 * SUN_ANGULAR_RADIUS
    r = cone * np.sqrt((np.arange(n) + 0.5) / n)
    phi = np.pi * (3.0 - math.sqrt(5.0)) * np.arange(n)
    t = np.cross(sun, [0.0, 1.0, 0.0] if abs(sun[1]) < 0.9 else [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(sun, t)
    offsets = np.sin(r)[:, None] * (np.cos(phi)[:, None] * t + np.sin(phi)[:, None] * b)
    samples = np.cos(r)[:, None] * sun + offsets
    sun_radiance = _eval_emitter(sun_only, samples)
    cone_solid_angle = 2.0 * math.pi * (1.0 - math.cos(cone))
    sun_flux = sun_radiance.mean(axis=0) * cone_solid_angle

    # Ground: Lambertian, irradiance from the sky hemisphere plus the sun.
    solid_angle = pixel_solid_angles(height, 2 * height)[..., None] * weights  # (H, 1, n²)
    irradiance = (values * (np.maximum(d[..., 1], 0.0) * solid_angle)[..., None]).sum(axis=(0, 1, 2))
    irradiance += sun_flux * max(sun[1], 0.0)
    values[d[..., 1] < 0] = params.ground_albedo * irradiance / math.pi
    image = (values * weights[..., None]).sum(axis=2)
    if sun[1] > -SUN_ANGULAR_RADIUS:
        splat_flux(image, sun, sun_flux)
    return image.astype(np.float32)


# --------------------------------------------------------------------------------------------------------------
# Indoor rooms
# --------------------------------------------------------------------------------------------------------------


@dataclass
class RoomParams:
    half_size: tuple[float, float, float]  # room half-extent in x, y, z around the stage centre (m)
    wall_colors: list[list[float]]  # albedo of -x, +x, floor, ceiling, -z, +z
    ambient: float  # radiance scale of the inter-reflected light on walls
    lamps: list[dict]  # on the ceiling: {"center": [x, z], "size": [sx, sz], "radiance": [r, g, b]}
    windows: list[dict]  # on a wall: {"wall": 0|1|4|5, "center": [a, b], "size": [sa, sb], "radiance": [r, g, b]}


def _box_hit(d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exit point of rays from the box centre, and the face index (0:-x 1:+x 2:-y 3:+y 4:-z 5:+z)."""
    with np.errstate(divide="ignore"):
        t = np.where(np.abs(d) > 1e-12, half / np.abs(d), np.inf)
    axis = np.argmin(t, axis=-1)
    tmin = np.take_along_axis(t, axis[..., None], axis=-1)
    p = d * tmin
    sign = np.take_along_axis(d, axis[..., None], axis=-1)[..., 0] > 0
    return p, 2 * axis + sign


def bake_room(params: RoomParams, height: int = 128, supersample: int = 2) -> np.ndarray:
    """A box room seen from its centre: coloured walls, rectangular ceiling lamps and bright windows."""
    half = np.asarray(params.half_size)
    colors = np.asarray(params.wall_colors)

    def radiance(d: np.ndarray) -> np.ndarray:
        p, face = _box_hit(d, half)
        image = colors[face] * params.ambient
        for lamp in params.lamps:
            (cx, cz), (sx, sz) = lamp["center"], lamp["size"]
            inside = (face == 3) & (np.abs(p[..., 0] - cx) < sx / 2) & (np.abs(p[..., 2] - cz) < sz / 2)
            image[inside] = lamp["radiance"]
        for window in params.windows:
            wall = window["wall"]
            a_axis, b_axis = {0: (2, 1), 1: (2, 1), 4: (0, 1), 5: (0, 1)}[wall]
            (ca, cb), (sa, sb) = window["center"], window["size"]
            inside = (face == wall) & (np.abs(p[..., a_axis] - ca) < sa / 2) & (np.abs(p[..., b_axis] - cb) < sb / 2)
            # Brighter toward the top: sky through the window, ground light below.
            grad = 0.6 + 0.4 * np.clip((p[..., 1] - cb) / max(sb, 1e-6) + 0.5, 0.0, 1.0)
            image[inside] = np.asarray(window["radiance"]) * grad[inside][:, None]
        return image

    return _bake(height, supersample, radiance)


# --------------------------------------------------------------------------------------------------------------
# Seeded sets
# --------------------------------------------------------------------------------------------------------------


def random_sky(rng: np.random.Generator) -> SkyParams:
    return SkyParams(
        sun_elevation_deg=float(rng.uniform(5.0, 70.0)),
        sun_azimuth_deg=float(rng.uniform(0.0, 360.0)),
        turbidity=float(rng.uniform(2.0, 8.0)),
        ground_albedo=float(rng.uniform(0.1, 0.4)),
        sky_scale=1.0,
        sun_scale=1.0,
    )


def random_room(rng: np.random.Generator) -> RoomParams:
    half = (float(rng.uniform(2.0, 4.0)), float(rng.uniform(1.3, 1.8)), float(rng.uniform(2.0, 4.0)))
    base = rng.uniform(0.2, 0.8, size=(6, 3))
    tint = rng.uniform(0.6, 1.0, size=(1, 3))
    walls = np.clip(base * tint, 0.02, 0.9)
    walls[2] *= 0.6  # floors are darker than walls
    lamps = []
    for _ in range(int(rng.integers(1, 4))):
        warmth = rng.uniform(0.0, 1.0)
        color = np.array([1.0, 0.85 + 0.1 * (1 - warmth), 0.6 + 0.4 * (1 - warmth)])
        lamps.append(
            {
                "center": [float(rng.uniform(-half[0] + 0.5, half[0] - 0.5)), float(rng.uniform(-half[2] + 0.5, half[2] - 0.5))],
                "size": [float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.2, 0.8))],
                "radiance": (color * rng.uniform(20.0, 80.0)).tolist(),
            }
        )
    windows = []
    for _ in range(int(rng.integers(0, 3))):
        wall = int(rng.choice([0, 1, 4, 5]))
        along = half[2] if wall in (0, 1) else half[0]
        windows.append(
            {
                "wall": wall,
                "center": [float(rng.uniform(-along + 0.8, along - 0.8)), float(rng.uniform(-0.2, 0.5))],
                "size": [float(rng.uniform(0.6, 1.5)), float(rng.uniform(0.6, 1.2))],
                "radiance": (np.array([0.75, 0.85, 1.0]) * rng.uniform(3.0, 15.0)).tolist(),
            }
        )
    return RoomParams(half, walls.tolist(), float(rng.uniform(0.05, 0.3)), lamps, windows)


def envmap_from_seed(seed: int, height: int = 128) -> tuple[np.ndarray, dict]:
    """One procedural envmap (sky or room, chosen by the seed) and its parameters."""
    rng = np.random.default_rng(seed)
    if rng.uniform() < 0.5:
        params = random_sky(rng)
        return bake_sunsky(params, height), {"kind": "sky", "seed": seed, **asdict(params)}
    params = random_room(rng)
    return bake_room(params, height), {"kind": "room", "seed": seed, **asdict(params)}


def split_seeds(split: str, count: int) -> list[int]:
    if split not in SPLIT_SEED_BASE:
        raise ValueError(f"split must be one of {list(SPLIT_SEED_BASE)}, got {split!r}")
    return [SPLIT_SEED_BASE[split] + i for i in range(count)]


def write_envmap_set(out_dir: str | Path, split: str, count: int, height: int = 128) -> list[Path]:
    """Write ``count`` envmaps of a split as EXR + PNG preview, with an index.json of their parameters.

    Existing maps are kept (so an interrupted run resumes where it stopped).
    """

    out_dir = Path(out_dir) / split
    paths, index = [], []
    for seed in progress(split_seeds(split, count), description=f"envmaps ({split})"):
        path = out_dir / f"{split}_{seed - SPLIT_SEED_BASE[split]:04d}.exr"
        meta_path = path.with_suffix(".json")
        if path.exists() and meta_path.exists():
            meta = json.loads(meta_path.read_text())
        else:
            image, meta = envmap_from_seed(seed, height)
            write_png(path.with_suffix(".png"), image, exposure=None)
            atomic_write_text(meta_path, json.dumps(meta, indent=1) + "\n")
            write_exr(path, image)
        paths.append(path)
        index.append({"file": path.name, **meta})
    atomic_write_text(out_dir / "index.json", json.dumps(index, indent=1) + "\n")
    return paths


# --------------------------------------------------------------------------------------------------------------
# Reference lighting: the hard cases of real HDRIs, as fixed maps
# --------------------------------------------------------------------------------------------------------------

REFERENCE_MAPS = ("sun", "studio", "interior", "night")


def _direction(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    e, a = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(e) * math.sin(a), math.sin(e), math.cos(e) * math.cos(a)])


def _add_disc(envmap: np.ndarray, center: np.ndarray, radius_deg: float, radiance, supersample: int = 4) -> None:
    """Add a uniform disc of ``radiance`` (angular radius ``radius_deg``), box-filtered into the pixels, in place.
    Discs smaller than a pixel are splatted with their exact flux (:func:`splat_flux`) instead."""
    h, w = envmap.shape[:2]
    radius = math.radians(radius_deg)
    flux = np.asarray(radiance, np.float64) * 2.0 * math.pi * (1.0 - math.cos(radius))
    if radius < 2.0 * math.pi / w:
        splat_flux(envmap, center, flux)
        return
    d, weights = pixel_subsamples(h, w, supersample)
    inside = (d @ center > math.cos(radius)).astype(np.float64) * weights
    envmap += (inside.sum(axis=2)[..., None] * np.asarray(radiance, np.float64)).astype(np.float32)


def reference_map(name: str, height: int = 64) -> np.ndarray:
    """One of :data:`REFERENCE_MAPS`, the cases that break a relighting method on real HDRIs:

    - ``sun``: a clear sky and a 2°-wide sun of 10⁴× the sky's mean radiance (half of the light, from one point);
    - ``studio``: a dark room with a key, a fill and a rim softbox (large, bright area lights, strong contrast);
    - ``interior``: a room with a ceiling lamp, a window and coloured walls (soft, coloured bounce light);
    - ``night``: a dark sky, a moon and two warm street lamps near the horizon (low, small, coloured sources).
    """
    w = 2 * height
    d = pixel_directions(height, w)
    image = np.zeros((height, w, 3), np.float32)
    up = np.clip(d[..., 1:2], 0.0, 1.0)
    if name == "sun":
        sky = np.array([0.35, 0.55, 1.0]) * (0.6 + 0.4 * (1.0 - up)) * (d[..., 1:2] > 0)  # brighter toward the horizon
        ground = np.array([0.18, 0.16, 0.13]) * (d[..., 1:2] <= 0)
        image += (sky + ground).astype(np.float32)
        sky_mean = float(image[: height // 2].mean())
        _add_disc(image, _direction(40.0, 60.0), 1.0, np.array([1.0, 0.95, 0.88]) * 1e4 * sky_mean)
    elif name == "studio":
        image += np.float32(0.01)
        _add_disc(image, _direction(35.0, -40.0), 14.0, [30.0, 29.0, 27.0])  # key
        _add_disc(image, _direction(10.0, 70.0), 20.0, [4.0, 4.2, 4.6])  # fill
        _add_disc(image, _direction(50.0, 170.0), 8.0, [40.0, 40.0, 40.0])  # rim, behind
    elif name == "interior":
        room = RoomParams(
            half_size=(3.0, 1.5, 2.5),
            wall_colors=[[0.7, 0.55, 0.4], [0.35, 0.45, 0.6], [0.25, 0.2, 0.15], [0.85, 0.85, 0.85], [0.6, 0.6, 0.55], [0.5, 0.3, 0.3]],
            ambient=0.2,
            lamps=[{"center": [0.5, 0.3], "size": [0.6, 0.6], "radiance": [60.0, 50.0, 35.0]}],
            windows=[{"wall": 1, "center": [0.0, 0.2], "size": [1.4, 1.0], "radiance": [9.0, 10.0, 12.0]}],
        )
        image += bake_room(room, height)
    elif name == "night":
        image += (np.array([0.002, 0.003, 0.006]) * (d[..., 1:2] > 0) + np.array([0.003, 0.0025, 0.002]) * (d[..., 1:2] <= 0)).astype(
            np.float32
        )
        _add_disc(image, _direction(30.0, -120.0), 2.0, [0.5, 0.5, 0.55])  # moon (wider than the real one: a pixel)
        _add_disc(image, _direction(8.0, 30.0), 3.0, [40.0, 22.0, 6.0])  # sodium street lamps
        _add_disc(image, _direction(5.0, 100.0), 3.0, [40.0, 22.0, 6.0])
    else:
        raise ValueError(f"reference map must be one of {REFERENCE_MAPS}, got {name!r}")
    return image
