"""Lens distortion of a source's images, undone at import: every image (and mask) is resampled onto the pinhole
camera with the same K, as OpenCV's ``cv2.undistort`` does, so that every later stage sees pinhole images.

Two models, in the coefficients' meaning their sources give them, on normalized camera coordinates (x, y) = ((u −
cx) / fx, (v − cy) / fy) with gra-mi's pixel centres at (column + ½, row + ½):

- ``radial-tangential`` (OpenCV's full model, COLMAP's OPENCV and FULL_OPENCV, nerfstudio's ``OPENCV``): r² = x² + y²,
  d = (1 + k1 r² + k2 r⁴ + k3 r⁶ + k4 r⁸) / (1 + q1 r² + q2 r⁴ + q3 r⁶),
  x_d = x d + 2 p1 x y + p2 (r² + 2 x²) + s1 r² + s2 r⁴, y_d = y d + p1 (r² + 2 y²) + 2 p2 x y + s3 r² + s4 r⁴.
  k4 is nerfstudio's r⁸ term; the divisor's q1…q3 are what OpenCV calls k4…k6 (its rational model) and s1…s4 its
  thin-prism terms. OpenCV's tilted sensor (τx, τy, its 13th and 14th terms, a Scheimpflug camera's) then maps
  (x_d, y_d) through the projection of a plane turned by τx about x and τy about y, as its
  ``computeTiltProjectionMatrix`` does.
- ``fisheye`` (OpenCV's ``cv2.fisheye``, nerfstudio's ``OPENCV_FISHEYE``): θ = atan r,
  θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸), (x_d, y_d) = (θ_d / r) (x, y).

Past the radius where the radial map stops growing, a distortion folds back on itself: such pixels (and those that
land outside the source image) are left out, black with zero alpha, never filled from the wrong place.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from gra_mi.core.errors import GraMiInputError

MODELS = ("radial-tangential", "fisheye")
OPENCV_COUNTS = (0, 4, 5, 8, 12, 14)  # the lengths cv2's distCoeffs may have: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1…s4 [τx τy]]]]


@dataclass(frozen=True)
class LensDistortion:
    model: str  # one of MODELS
    k: tuple[float, float, float, float]  # radial terms: of r², r⁴, r⁶, r⁸ (or θ², … for the fisheye)
    p: tuple[float, float] = (0.0, 0.0)  # tangential (radial-tangential only)
    q: tuple[float, float, float] = (0.0, 0.0, 0.0)  # the radial divisor's r², r⁴, r⁶ (OpenCV's rational k4…k6)
    s: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)  # thin prism: x += s1 r² + s2 r⁴, y += s3 r² + s4 r⁴
    tilt: tuple[float, float] = (0.0, 0.0)  # the sensor's tilt τx, τy in radians (OpenCV's tilted model)
    origin: tuple[str, str] = field(default=("", ""), compare=False)  # (file, field) it was read from: what errors name

    @classmethod
    def of(cls, model: str, source, where: str, **terms: float | None) -> LensDistortion | None:
        """The distortion named by ``terms`` (k1 … k4, p1, p2, q1 … q3, s1 … s4, tau_x, tau_y; None or absent: 0), or
        None where every term is 0. ``source``/``where``: the file and field it is read from, what an error names."""
        if model not in MODELS:
            raise ValueError(f"lens model {model!r}: expected one of {MODELS}")  # a reader's mistake, not the user's
        names = ("k1", "k2", "k3", "k4", "p1", "p2", "q1", "q2", "q3", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
        if set(terms) - set(names):
            raise ValueError(f"unknown lens terms {sorted(set(terms) - set(names))}")  # a reader's mistake too
        values = {key: float(terms.get(key) or 0.0) for key in names}
        if not all(math.isfinite(v) for v in values.values()):
            raise GraMiInputError(source, f"distortion terms must be finite numbers, got {_nonzero(values)}", field=where)
        if model == "fisheye" and any(values[key] for key in names[4:]):
            raise GraMiInputError(
                source,
                "the fisheye model has only radial terms (k1 … k4): no tangential (p1, p2), rational, thin-prism or tilt ones",
                field=where,
            )
        if not any(values.values()):
            return None
        if max(abs(values["tau_x"]), abs(values["tau_y"])) >= math.pi / 4:
            raise GraMiInputError(source, f"a sensor tilted by {_nonzero(values)} radians (45° or more) is not a camera", field=where)
        k, p, q, s, tilt = ([values[key] for key in group] for group in (names[:4], names[4:6], names[6:9], names[9:13], names[13:]))
        lens = cls(model, tuple(k), tuple(p), tuple(q), tuple(s), tuple(tilt), (str(source), where))
        if lens.fold_radius() < 1e-3:
            raise GraMiInputError(source, f"the distortion {values} folds at the image centre: not a lens", field=where)
        return lens

    @classmethod
    def opencv(cls, coefficients, source, where: str) -> LensDistortion | None:
        """From OpenCV's ``distCoeffs`` order (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, τx, τy]]]]): its
        rational k4…k6 are the divisor's q1…q3 here."""
        try:
            values = [float(c) for c in np.asarray(coefficients, float).ravel()]
        except (TypeError, ValueError):
            raise GraMiInputError(source, f"distortion coefficients must be numbers, got {coefficients!r}", field=where) from None
        if not all(math.isfinite(v) for v in values):
            raise GraMiInputError(source, f"distortion coefficients must be finite numbers, got {values}", field=where)
        if len(values) not in OPENCV_COUNTS:
            raise GraMiInputError(source, f"expected 4, 5, 8, 12 or 14 OpenCV distortion coefficients, got {len(values)}", field=where)
        names = ("k1", "k2", "p1", "p2", "k3", "q1", "q2", "q3", "s1", "s2", "s3", "s4", "tau_x", "tau_y")
        return cls.of("radial-tangential", source, where, **dict(zip(names, values, strict=False)))

    def _radial(self, r2: np.ndarray) -> np.ndarray:
        """The radial factor: of r² (radial-tangential), or θ_d / r (fisheye)."""
        k1, k2, k3, k4 = self.k
        if self.model == "radial-tangential":
            q1, q2, q3 = self.q
            return (1 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))) / (1 + r2 * (q1 + r2 * (q2 + r2 * q3)))
        r = np.sqrt(r2)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        return np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Normalized pinhole coordinates (…, 2) → where the lens images them (…, 2), float64."""
        x, y = np.asarray(xy, float)[..., 0], np.asarray(xy, float)[..., 1]
        r2 = x * x + y * y
        d = self._radial(r2)
        p1, p2 = self.p
        s1, s2, s3, s4 = self.s
        x_d = x * d + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + r2 * (s1 + r2 * s2)
        y_d = y * d + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + r2 * (s3 + r2 * s4)
        return self._tilted(np.stack([x_d, y_d], axis=-1))

    def _tilted(self, xy_d: np.ndarray) -> np.ndarray:
        """Where a tilted sensor (:func:`tilt_matrix`) sees the distorted points (…, 2)."""
        if not any(self.tilt):
            return xy_d
        m = tilt_matrix(*self.tilt)
        mapped = xy_d @ m[:, :2].T + m[:, 2]
        return mapped[..., :2] / mapped[..., 2:]

    def undistort(self, xy_d: np.ndarray, iterations: int = 40) -> np.ndarray:
        """The inverse of :meth:`distort` (Newton's method with a numerical Jacobian, each point until it is within
        1e-13), for points inside the fold radius; points it cannot bring back within 1e-9 are NaN."""
        target = np.asarray(xy_d, float).reshape(-1, 2)
        xy = target.copy()
        # beyond the farthest the lens maps to (with room for tangential terms) there is no pinhole point
        active = np.flatnonzero(np.hypot(target[:, 0], target[:, 1]) <= 1.05 * self.reach())
        for _ in range(iterations):
            f = self.distort(xy[active]) - target[active]
            moving = ~(np.abs(f).max(axis=-1) <= 1e-13)  # NaN keeps moving until the last check drops it
            active, f = active[moving], f[moving]
            if active.size == 0:
                break
            xy[active] -= self._newton_step(xy[active], f)
        bad = ~(np.abs(self.distort(xy) - target).max(axis=-1) <= 1e-9) | (np.hypot(xy[:, 0], xy[:, 1]) > self.fold_radius())
        xy[bad] = np.nan
        return xy.reshape(np.shape(xy_d))

    def _newton_step(self, xy: np.ndarray, f: np.ndarray) -> np.ndarray:
        h = 1e-7
        jx = (self.distort(xy + [h, 0]) - self.distort(xy - [h, 0])) / (2 * h)
        jy = (self.distort(xy + [0, h]) - self.distort(xy - [0, h])) / (2 * h)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        return np.stack([(jy[:, 1] * f[:, 0] - jy[:, 0] * f[:, 1]) / det, (jx[:, 0] * f[:, 1] - jx[:, 1] * f[:, 0]) / det], axis=-1)

    def fold_radius(self) -> float:
        """The pinhole radius r where r·radial(r²) stops growing or meets a pole of the rational divisor (inf: never,
        within r ≤ 20, i.e. 87° off axis)."""
        r = np.linspace(0.0, 20.0, 200_001)
        with np.errstate(divide="ignore", invalid="ignore"):  # a rational divisor may reach zero: a pole is a fold
            mapped = r * self._radial(r * r)
            stops = np.flatnonzero(~(np.diff(mapped) > 0))
        return math.inf if stops.size == 0 else float(r[stops[0]])

    def reach(self) -> float:
        """The farthest (normalized, radial) a point can be imaged before the distortion folds back (inf: no fold)."""
        fold = self.fold_radius()
        if math.isinf(fold):
            return math.inf
        angle = np.linspace(0.0, 2 * math.pi, 721)
        circle = fold * float(self._radial(np.array(fold * fold))) * np.stack([np.cos(angle), np.sin(angle)], axis=-1)
        return float(np.hypot(*self._tilted(circle).T).max())

    def describe(self) -> str:
        groups = (("k", self.k), ("p", self.p), ("q", self.q), ("s", self.s), ("tau", self.tilt))
        return f"{self.model} ({', '.join(f'{name}{i + 1}={v:g}' for name, values in groups for i, v in enumerate(values) if v)})"


def tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection (its ``computeTiltProjectionMatrix``): the sensor plane turned by τx about x,
    then τy about y, and projected back along the optical axis onto the plane z = 1."""
    cx, sx, cy, sy = math.cos(tau_x), math.sin(tau_x), math.cos(tau_y), math.sin(tau_y)
    turn = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]]) @ np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    project = np.array([[turn[2, 2], 0, -turn[0, 2]], [0, turn[2, 2], -turn[1, 2]], [0, 0, 1]])
    return project @ turn


def _nonzero(values: dict[str, float]) -> dict[str, float]:
    return {key: v for key, v in values.items() if v != 0}


def undistort_image(image: np.ndarray, k_matrix: np.ndarray, lens: LensDistortion) -> np.ndarray:
    """``image`` (H, W, C) as the pinhole camera with the same K sees it: each pixel bilinearly sampled where the lens
    put it; pixels the source does not hold (outside it, or past the fold) are 0. A mask (bool) comes back as float32
    coverage, as the other resamplings give it."""
    image = image if image.dtype.kind == "f" else image.astype(np.float32)
    h, w, c = image.shape
    corner, fr, fc, inside = _remap_table(lens, _k_key(k_matrix), w, h)
    # one row and column repeated past the edges: a corner's right and lower neighbours are always one step away
    padded = np.pad(image, ((0, 1), (0, 1), (0, 0)), mode="edge").reshape(-1, c)
    out = np.take(padded, corner, axis=0)
    out *= (1 - fr) * (1 - fc)
    for step, weight in ((1, (1 - fr) * fc), (w + 1, fr * (1 - fc)), (w + 2, fr * fc)):
        term = np.take(padded, corner + step, axis=0)
        term *= weight
        out += term
    out[~inside] = 0
    return out.reshape(h, w, c).astype(image.dtype, copy=False)


def pinhole_positions(k_matrix: np.ndarray, lens: LensDistortion, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Where the pinhole image (same K) holds each pixel of the distorted ``width`` × ``height`` image: (columns,
    rows) in pixels, NaN where the lens cannot have put a pinhole point there."""
    return _pinhole_positions(lens, _k_key(k_matrix), width, height)


def held_fraction(k_matrix: np.ndarray, lens: LensDistortion, width: int, height: int, samples: int = 256) -> float:
    """The share of the pinhole image's pixels the distorted image holds (the rest are left black, alpha 0), from
    about ``samples`` pixels along the longer side: a share needs no full map (nor a place in the maps' cache)."""
    step = max(1, max(width, height) // samples)
    columns, rows = np.arange(0, width, step), np.arange(0, height, step)
    return float(_positions(lens, _k_key(k_matrix), columns, rows, width, height)[2].mean())


def _k_key(k: np.ndarray) -> tuple[float, float, float, float]:
    return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])


@lru_cache(maxsize=2)  # one camera's images are imported in turn: its table is computed once, not per image
def _remap_table(lens: LensDistortion, k: tuple, width: int, height: int) -> tuple[np.ndarray, ...]:
    """Per pinhole pixel: the flat index of its bilinear corner in the edge-padded (H + 1) × (W + 1) source, the row
    and column fractions (N, 1) and whether the source holds it. Samples within half a pixel of the border take the
    edge's value."""
    rows, cols, inside = _source_positions(lens, k, width, height)
    r0, c0 = np.floor(rows), np.floor(cols)
    fr = np.where(r0 < 0, 0, rows - r0).astype(np.float32).reshape(-1, 1)
    fc = np.where(c0 < 0, 0, cols - c0).astype(np.float32).reshape(-1, 1)
    r0, c0 = np.clip(r0, 0, height - 1).astype(np.int64), np.clip(c0, 0, width - 1).astype(np.int64)
    return (r0 * (width + 1) + c0).ravel(), fr, fc, inside.ravel()


@lru_cache(maxsize=2)
def _source_positions(lens: LensDistortion, k: tuple, width: int, height: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each pinhole pixel: the (row, column) of the distorted image it samples, and whether the source holds it."""
    return _positions(lens, k, np.arange(width), np.arange(height), width, height)


def _positions(lens: LensDistortion, k: tuple, columns: np.ndarray, rows: np.ndarray, width: int, height: int) -> tuple[np.ndarray, ...]:
    """:func:`_source_positions` of the pinhole pixels ``rows`` × ``columns`` of a ``width`` × ``height`` image."""
    fx, fy, cx, cy = k
    x = (columns + 0.5 - cx) / fx
    y = (rows + 0.5 - cy) / fy
    xy = np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1)
    d = lens.distort(xy)
    cols, rows = d[..., 0] * fx + cx - 0.5, d[..., 1] * fy + cy - 0.5
    inside = (np.hypot(xy[..., 0], xy[..., 1]) < lens.fold_radius()) & (cols >= -0.5) & (cols <= width - 0.5)
    inside &= (rows >= -0.5) & (rows <= height - 0.5)
    return rows.astype(np.float32), cols.astype(np.float32), inside


@lru_cache(maxsize=2)
def _pinhole_positions(lens: LensDistortion, k: tuple, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    fx, fy, cx, cy = k
    x_d = (np.arange(width) + 0.5 - cx) / fx
    y_d = (np.arange(height) + 0.5 - cy) / fy
    xy = lens.undistort(np.stack(np.broadcast_arrays(x_d[None, :], y_d[:, None]), axis=-1))
    return (xy[..., 0] * fx + cx - 0.5).astype(np.float32), (xy[..., 1] * fy + cy - 0.5).astype(np.float32)
