"""Pose-dependent cloth wrinkles of the synthetic ground truth.

Cloth buckles where the body compresses it: behind a bent knee, inside a bent elbow, in the fold of a raised hip.
The truth's wrinkles follow the tracked surface. At each texel the compressive strain is

    ε = max(0, 1 − A_t / A_0)

of the surface around it (the area of the triangles at its vertices in frame t against the sequence's first frame,
the cloth's rest state), and the wrinkles' slope is that of an inextensible sheet shortened by ε into a sinusoid:
amplitude (λ/π)·√ε for wavelength λ, so a slope of 2·√ε, whatever the wavelength. On top of it lies a resting
drape of slope :data:`REST_SLOPE`. The wrinkles are a function of the pose, which a model can see in the tracked mesh,
not of the clock: what a learned stage can learn, as it learns real pose-dependent wrinkles.
"""

from __future__ import annotations

import math
from functools import lru_cache
from pathlib import Path

import numpy as np

from gra_mi.core.io import read_exr

REST_SLOPE = 0.1
"""The slope of the resting drape's wrinkles (the first frame's, and everywhere the cloth is not compressed)."""
MAX_SLOPE = 1.0
"""Steeper than 45° the sheet folds over itself; the slope is clipped there."""
WAVES_PER_ATLAS = 24.0
"""Wrinkle bands across the UV atlas (a wavelength of a few centimetres on the body)."""


def wrinkle_normal_map(cloth: np.ndarray, slope: float | np.ndarray, seed: int = 0) -> np.ndarray:
    """A tangent-space normal map (values in [0, 1]) of wrinkle bands on cloth: ``slope`` is the bands' steepest
    slope, one number or one per texel (R, R)."""
    cloth = cloth if cloth.ndim == 2 else cloth[..., 0]  # (R, R) or (R, R, C): the first channel is the mask
    r = cloth.shape[0]
    rng = np.random.default_rng(seed)
    c = (np.arange(r) + 0.5) / r
    u, v = np.meshgrid(c, c, indexing="xy")
    angle = rng.uniform(0, math.pi)
    phase = 2 * math.pi * WAVES_PER_ATLAS * (u * math.cos(angle) + v * math.sin(angle))
    tilt = np.asarray(slope) * np.cos(phase) * cloth
    n = np.stack([-tilt * math.cos(angle), -tilt * math.sin(angle), np.ones_like(tilt)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return (0.5 + 0.5 * n).astype(np.float32)


def _face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    v = vertices.astype(np.float64)
    return 0.5 * np.linalg.norm(np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]), axis=-1)


def vertex_compression(rest: np.ndarray, posed: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(V,) compressive strain ε = max(0, 1 − A_t / A_0) of the triangles around each vertex (their areas summed:
    the ring's area change), 0 where the surface is stretched or unchanged."""
    rest_ring = np.zeros(rest.shape[0])
    posed_ring = np.zeros(rest.shape[0])
    rest_area, posed_area = _face_areas(rest, faces), _face_areas(posed, faces)
    for k in range(3):
        np.add.at(rest_ring, faces[:, k], rest_area)
        np.add.at(posed_ring, faces[:, k], posed_area)
    ratio = np.divide(posed_ring, rest_ring, out=np.ones_like(rest_ring), where=rest_ring > 0)
    return np.clip(1.0 - ratio, 0.0, 1.0)


class WrinkleModel:
    """The truth's wrinkles of any frame of a tracked sequence: :meth:`slopes` (per texel) and :meth:`normal_map`."""

    def __init__(self, atlas, faces: np.ndarray, rest_vertices: np.ndarray, cloth: np.ndarray):
        self.atlas, self.faces, self.rest = atlas, faces, rest_vertices
        self.cloth = cloth if cloth.ndim == 2 else cloth[..., 0]

    def slopes(self, vertices: np.ndarray) -> np.ndarray:
        """(R, R) slope of the wrinkles when the surface stands at ``vertices``: the drape's plus the buckling's."""
        strain = vertex_compression(self.rest, vertices, self.faces)
        texel_strain = self.atlas.bake_vertex_attribute(strain[:, None].astype(np.float32))[..., 0]
        return np.minimum(REST_SLOPE + 2.0 * np.sqrt(texel_strain), MAX_SLOPE) * self.cloth

    def normal_map(self, vertices: np.ndarray) -> np.ndarray:
        return wrinkle_normal_map(self.cloth, self.slopes(vertices))


@lru_cache(maxsize=2)
def _capture_model(folder: str, stamp: tuple) -> tuple[WrinkleModel, np.ndarray]:
    from gra_mi.render.atlas import UVAtlas
    from gra_mi.subject.sequence import load_sequence

    sequence = load_sequence(Path(folder) / "subject")
    cloth = read_exr(Path(folder) / "gt" / "cloth.exr")
    atlas = UVAtlas.build(sequence.faces, sequence.uvs, cloth.shape[0])
    return WrinkleModel(atlas, sequence.faces, sequence.vertices[0], cloth), sequence.vertices


def capture_wrinkles(folder: Path, frame: int) -> np.ndarray | None:
    """The wrinkle normal map of a synthetic capture's mesh frame (the one its images were rendered with); None when
    the capture has no cloth map. Models are cached per capture (the atlas takes a second to build)."""
    cloth, sequence = folder / "gt" / "cloth.exr", folder / "subject" / "sequence.npz"
    if not cloth.is_file():
        return None
    stamp = (cloth.stat().st_mtime_ns, sequence.stat().st_mtime_ns)
    model, vertices = _capture_model(str(folder.resolve()), stamp)
    return model.normal_map(vertices[frame])


def pose_capture_wrinkles(params, capture, frame: int) -> bool:
    """Pose a synthetic capture's ground-truth scene (``mi.traverse`` parameters) with the wrinkles of its mesh frame,
    as its images have them; False when the capture was made without wrinkles or its scene has no normal map."""
    if "wrinkles" in capture.ground_truth.get("without", []):
        return False
    wrinkles = capture_wrinkles(capture.folder, frame)
    return wrinkles is not None and pose_wrinkles(params, wrinkles)


def pose_wrinkles(params, normal_map: np.ndarray) -> bool:
    """Set a frame's wrinkle normal map on a ground-truth scene's ``normalmap`` BSDF (``mi.traverse`` parameters);
    False when the scene has none (a one-bounce ground truth)."""
    import mitsuba as mi

    from gra_mi.stage import scene_keys as keys

    key = next((k for k in params.keys() if k.endswith(keys.NORMALMAP_DATA_SUFFIX)), None)
    if key is None:
        return False
    params[key] = mi.TensorXf(normal_map)
    params.update()
    return True
