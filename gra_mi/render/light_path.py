"""Near-field lights that move: point and spot lights given at keyframes, several at once (``gra-mi relight --lights``).

A light path file is JSON::

    {"lights": [
      {"name": "key", "type": "point", "radius": 0.03, "intensity": 2.0,
       "keyframes": [{"frame": 0, "position": [0.6, 1.2, 0.4]}, {"frame": 47, "position": [-0.6, 1.2, 0.4]}]},
      {"name": "rim", "type": "spot", "intensity": [4, 3.6, 3], "cutoff_angle": 25, "beam_width": 18,
       "keyframes": [{"frame": 0, "position": [0, 1.8, -0.8], "target": [0, 1.2, 0]}]}
    ]}

Each light holds its ``radius`` (metres: soft shadows), and at light level or per keyframe its ``intensity`` (W/sr, a
number or RGB), and for a spot its aim (``direction`` or ``target``), ``cutoff_angle`` and ``beam_width`` (degrees, as
Mitsuba's ``spot``). Between keyframes every value is interpolated linearly (a spot's axis too, renormalised); a
light with one keyframe stands still. Frames outside a light's first and last keyframe are refused, not extrapolated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_json
from gra_mi.core.limits import MAX_INTENSITY
from gra_mi.render.point_light import PointLight

KINDS = ("point", "spot")
PER_KEYFRAME = ("intensity", "direction", "target", "cutoff_angle", "beam_width")


@dataclass
class PathLight:
    """One light of a path: its keyframes (sorted frames, one row of values each)."""

    name: str
    kind: str
    radius: float
    frames: np.ndarray  # (K,) increasing
    position: np.ndarray  # (K, 3)
    intensity: np.ndarray  # (K, 3)
    direction: np.ndarray | None  # (K, 3) unit, spots only
    cone: np.ndarray | None  # (K, 2) cutoff, beam in degrees, spots only

    def at(self, frame: int) -> PointLight:
        weight, i, j = _bracket(self.frames, frame)
        mix = lambda values: (1 - weight) * values[i] + weight * values[j]  # noqa: E731
        spot = {}
        if self.kind == "spot":
            cutoff, beam = mix(self.cone)
            spot = {"direction": mix(self.direction), "cutoff_angle": float(cutoff), "beam_width": float(beam)}
        return PointLight(mix(self.position), mix(self.intensity), self.radius, **spot)


def _bracket(frames: np.ndarray, frame: int) -> tuple[float, int, int]:
    """(weight of the later keyframe, earlier index, later index) around ``frame`` (inside the keyframes' range)."""
    if len(frames) == 1:  # one keyframe: the light stands still
        return 0.0, 0, 0
    j = int(np.searchsorted(frames, frame))
    if j < len(frames) and frames[j] == frame:
        return 0.0, j, j
    return float((frame - frames[j - 1]) / (frames[j] - frames[j - 1])), j - 1, j


@dataclass
class LightPath:
    """The lights of a path file; :meth:`at` gives the lights of one frame."""

    source: Path
    lights: list[PathLight]

    @property
    def name(self) -> str:
        return self.source.stem

    def at(self, frame: int) -> list[PointLight]:
        return [light.at(frame) for light in self.lights]

    def check_clear_of(self, vertices: np.ndarray, frames: list[int]) -> None:
        """No light's sphere reaches into the subject (``vertices``: (T, V, 3)) at any of ``frames``: texels inside a
        light cannot be lit by it, so the render would be black where its conditioning says lit."""
        from scipy.spatial import cKDTree

        for f in frames:
            tree = cKDTree(vertices[f])
            for path_light in self.lights:
                light = path_light.at(f)
                nearest = float(tree.query(light.position)[0])
                if light.radius >= nearest:
                    raise GraMiInputError(
                        self.source,
                        f"light '{path_light.name}' (radius {light.radius:g} m) reaches into the subject at frame {f}: its centre is "
                        f"{nearest:.3g} m from the nearest vertex. Give it a radius below {nearest:.3g} m or move it away",
                    )

    def check_frames(self, frames: list[int]) -> None:
        """Every frame to render lies within every light's keyframes: no extrapolation."""
        for light in self.lights:
            if len(light.frames) == 1:
                continue
            outside = [f for f in frames if not light.frames[0] <= f <= light.frames[-1]]
            if outside:
                raise GraMiInputError(
                    self.source, f"light '{light.name}' has keyframes for frames {int(light.frames[0])}..{int(light.frames[-1])}, "
                    f"frame(s) {outside[:5]} are outside: add keyframes there or give fewer --frames"
                )  # fmt: skip

    @classmethod
    def still(cls, light: PointLight, name: str = "point_light") -> LightPath:
        """One light that does not move (``--point-light``): valid at every frame."""
        return cls(
            Path(name), [PathLight(name, "point", light.radius, np.zeros(1), light.position[None], light.intensity[None], None, None)]
        )

    @classmethod
    def load(cls, path: str | Path) -> LightPath:
        path = Path(path)
        data = read_json(path, hint=" (a light path file)")
        items = data.get("lights") if isinstance(data, dict) else None
        if not isinstance(items, list) or not items:
            raise GraMiInputError(path, 'expected {"lights": [ ... ]} with at least one light', field="lights")
        lights = [_read_light(path, k, item) for k, item in enumerate(items)]
        names = [light.name for light in lights]
        if len(set(names)) != len(names):
            raise GraMiInputError(path, f"two lights share a name: {names}", field="lights")
        return cls(path, lights)


def _read_light(path: Path, index: int, item) -> PathLight:
    where = f"lights[{index}]"
    if not isinstance(item, dict):
        raise GraMiInputError(path, "expected an object", field=where)
    kind = item.get("type", "point")
    if kind not in KINDS:
        raise GraMiInputError(path, f"type must be one of {', '.join(KINDS)}, got {kind!r}", field=f"{where}.type")
    radius = _number(path, f"{where}.radius", item.get("radius", 0.03), low=0.0)
    keyframes = item.get("keyframes")
    if not isinstance(keyframes, list) or not keyframes:
        raise GraMiInputError(path, "expected a list of at least one keyframe", field=f"{where}.keyframes")
    rows = [_read_keyframe(path, f"{where}.keyframes[{k}]", kind, _with_defaults(item, key)) for k, key in enumerate(keyframes)]
    frames = np.array([r["frame"] for r in rows])
    if np.any(np.diff(frames) <= 0):
        raise GraMiInputError(path, f"keyframe frames must increase, got {frames.tolist()}", field=f"{where}.keyframes")
    stack = {key: np.stack([r[key] for r in rows]) for key in rows[0] if key != "frame"}
    name = str(item.get("name", f"light{index}"))
    return PathLight(name, kind, radius, frames, stack["position"], stack["intensity"], stack.get("direction"), stack.get("cone"))


def _with_defaults(light: dict, keyframe):
    """A keyframe's values, the light's own (intensity, aim, cone) where it gives none; its aim replaces the light's."""
    if not isinstance(keyframe, dict):
        return keyframe  # refused, by name, in _read_keyframe
    defaults = {key: light[key] for key in PER_KEYFRAME if key in light}
    if "direction" in keyframe or "target" in keyframe:
        defaults.pop("direction", None)
        defaults.pop("target", None)
    return defaults | keyframe


def _read_keyframe(path: Path, where: str, kind: str, values) -> dict:
    if not isinstance(values, dict):
        raise GraMiInputError(path, "expected an object", field=where)
    frame = values.get("frame")
    if not isinstance(frame, int) or isinstance(frame, bool) or frame < 0:
        raise GraMiInputError(path, f"expected a frame index >= 0, got {frame!r}", field=f"{where}.frame")
    row = {"frame": frame, "position": _vector(path, f"{where}.position", values.get("position"))}
    row["intensity"] = _intensity(path, f"{where}.intensity", values.get("intensity", 1.0))
    if kind == "spot":
        row["direction"] = _aim(path, where, values, row["position"])
        cutoff = _number(path, f"{where}.cutoff_angle", values.get("cutoff_angle", 20.0), low=0.0)
        beam = _number(path, f"{where}.beam_width", values.get("beam_width", 0.75 * cutoff), low=0.0)
        if not 0 < cutoff < 180 or beam > cutoff:
            raise GraMiInputError(path, f"a spot needs 0 < beam_width <= cutoff_angle < 180 (degrees), got {beam}, {cutoff}", field=where)
        row["cone"] = np.array([cutoff, beam])
    return row


def _aim(path: Path, where: str, values: dict, position: np.ndarray) -> np.ndarray:
    if ("direction" in values) == ("target" in values):
        raise GraMiInputError(path, "a spot keyframe needs one of 'direction' or 'target'", field=where)
    key = "direction" if "direction" in values else "target"
    aim = _vector(path, f"{where}.{key}", values[key])
    aim = aim if key == "direction" else aim - position
    if np.linalg.norm(aim) == 0:
        raise GraMiInputError(path, "the spot's aim is a zero vector (target at the light?)", field=f"{where}.{key}")
    return aim / np.linalg.norm(aim)


def _intensity(path: Path, where: str, value) -> np.ndarray:
    """W/sr: a number (white) or [r, g, b], finite, >= 0 and at most :data:`MAX_INTENSITY`."""
    rgb = _vector(path, where, value) if isinstance(value, list) else np.full(3, _number(path, where, value, low=0.0))
    if np.any(rgb < 0) or np.any(rgb > MAX_INTENSITY):
        raise GraMiInputError(path, f"expected values in [0, {MAX_INTENSITY:g}] W/sr, got {rgb.tolist()}", field=where)
    return rgb


def _vector(path: Path, where: str, value) -> np.ndarray:
    numbers = isinstance(value, list) and len(value) == 3 and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    if not numbers:
        raise GraMiInputError(path, f"expected three numbers [x, y, z], got {value!r}", field=where)
    vector = np.asarray(value, np.float64)
    if not np.all(np.isfinite(vector)):
        raise GraMiInputError(path, f"expected finite numbers, got {vector.tolist()}", field=where)
    return vector


def _number(path: Path, where: str, value, low: float) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not np.isfinite(value) or value < low:
        raise GraMiInputError(path, f"expected a finite number >= {low:g}, got {value!r}", field=where)
    return float(value)
