"""UV-space one-bounce rendering (paper Sec. 3.1 and Supp. "Details about Microfacet Rendering").

The paper shades in the 512² UV space of the tracked mesh. Pieces, in the order they are used:

- :class:`UVAtlas` — once per topology: which triangle and barycentrics each texel centre falls in (Mitsuba's
  ``eval_parameterization``), and a validity mask. UVs never change across frames, so this is never redone.
- :class:`TexelGeometry` — per frame: texel positions, shading normals and geometric normals, interpolated from the
  frame's vertices with the cached barycentrics (~1 ms).
- :class:`VisibilityCache` — per frame and LED layout: one bit per (texel, LED), "the LED is above the texel's
  horizon and nothing blocks the segment". It depends only on geometry, so it is reused across envmaps, cameras,
  materials and fitting iterations, in memory and on disk.
- :func:`shade_texels` — per view: Σ over LEDs that are on of bit · I/d² · f(ωi, ωk) cosθk, in one Dr.Jit loop
  over LED arrays. Changing the envmap only changes the intensities: nothing is re-traced.
- :func:`rasterize_to_camera` — the texture seen by a camera, with alpha: the image-space coarse render.

Texel (row i, column j) of an R×R texture sits at uv = ((j + ½)/R, (i + ½)/R); row 0 is v ≈ 0, as Mitsuba's
bitmap textures read it (docs/conventions.md).
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi import brdf
from gra_mi.imageio import atomic_path

logger = logging.getLogger(__name__)

# Shadow rays start this far (metres) off the surface along the geometric normal, and stop this far short of the
# LED: enough to clear float32 self-intersection on a 2 m stage, far below a texel's size (~3 mm at 512²).
RAY_EPSILON = 1e-4


def texel_uvs(resolution: int) -> np.ndarray:
    """Texel-centre UVs, (R·R, 2), row-major (row i = v index)."""
    c = (np.arange(resolution) + 0.5) / resolution
    u, v = np.meshgrid(c, c, indexing="xy")
    return np.stack([u.ravel(), v.ravel()], axis=1)


@dataclass
class UVAtlas:
    """Texel → (triangle, barycentrics) for the texels the mesh's UV atlas covers."""

    resolution: int
    texel_index: np.ndarray  # (M,) flat index (row * R + col) of each valid texel
    faces: np.ndarray  # (M, 3) vertex indices of its triangle
    barycentrics: np.ndarray  # (M, 3)

    @property
    def num_texels(self) -> int:
        return int(self.texel_index.size)

    @property
    def mask(self) -> np.ndarray:
        m = np.zeros(self.resolution * self.resolution, bool)
        m[self.texel_index] = True
        return m.reshape(self.resolution, self.resolution)

    @classmethod
    def build(cls, faces: np.ndarray, uvs: np.ndarray, resolution: int = 512) -> UVAtlas:
        """Rasterise the atlas with Mitsuba's UV-space point location (needs a variant set)."""
        mesh = mi.Mesh("atlas", uvs.shape[0], faces.shape[0], has_vertex_texcoords=True)
        params = mi.traverse(mesh)
        # Geometry is irrelevant for the UV look-up; put the UVs in the plane so the mesh is valid.
        params["vertex_positions"] = mi.Float(np.concatenate([uvs, np.zeros((uvs.shape[0], 1))], axis=1).ravel().astype(np.float32))
        params["faces"] = mi.UInt32(faces.ravel().astype(np.uint32))
        params["vertex_texcoords"] = mi.Float(uvs.ravel().astype(np.float32))
        params.update()
        query = texel_uvs(resolution)
        si = mesh.eval_parameterization(mi.Point2f(*query.T.astype(np.float32)))
        valid = np.array(si.is_valid())
        prim = np.array(si.prim_index)[valid]
        tri = faces[prim]
        # Barycentrics of the texel centre in the UV triangle (float64: tiny triangles are common).
        a, b, c = (uvs[tri[:, k]].astype(np.float64) for k in range(3))
        p = query[valid]
        v0, v1, v2 = b - a, c - a, p - a
        d00, d01, d11 = np.sum(v0 * v0, 1), np.sum(v0 * v1, 1), np.sum(v1 * v1, 1)
        d20, d21 = np.sum(v2 * v0, 1), np.sum(v2 * v1, 1)
        denom = d00 * d11 - d01 * d01
        ok = np.abs(denom) > 1e-30  # degenerate UV triangles cannot hold a texel
        denom = np.where(ok, denom, 1.0)
        w1 = (d11 * d20 - d01 * d21) / denom
        w2 = (d00 * d21 - d01 * d20) / denom
        bary = np.clip(np.stack([1 - w1 - w2, w1, w2], axis=1), 0.0, 1.0)
        bary /= bary.sum(axis=1, keepdims=True)
        index = np.flatnonzero(valid)[ok]
        return cls(resolution, index, tri[ok].astype(np.int64), bary[ok])

    def bake_vertex_attribute(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Interpolate a per-vertex attribute (V, C) into an (R, R, C) texture (``fill`` outside the atlas)."""
        out = np.full((self.resolution * self.resolution, values.shape[1]), fill, dtype=np.float32)
        out[self.texel_index] = np.einsum("mk,mkc->mc", self.barycentrics, values[self.faces])
        return out.reshape(self.resolution, self.resolution, values.shape[1])

    def scatter(self, texel_values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """(M, C) values of the valid texels → (R, R, C) texture."""
        out = np.full((self.resolution * self.resolution, texel_values.shape[1]), fill, dtype=np.float32)
        out[self.texel_index] = texel_values
        return out.reshape(self.resolution, self.resolution, texel_values.shape[1])

    def gather(self, texture: np.ndarray) -> np.ndarray:
        """(R, R, C) texture → (M, C) values at the valid texels."""
        return texture.reshape(self.resolution * self.resolution, -1)[self.texel_index]

    def on_device(self) -> tuple[list[mi.UInt32], list[mi.Float]]:
        """The three vertex-index columns of ``faces`` and of ``barycentrics`` as Dr.Jit arrays, uploaded once per variant."""
        cache = self.__dict__.setdefault("_on_device", {})
        if mi.variant() not in cache:
            cache[mi.variant()] = (
                [mi.UInt32(np.ascontiguousarray(self.faces[:, k], np.uint32)) for k in range(3)],
                [mi.Float(np.ascontiguousarray(self.barycentrics[:, k], np.float32)) for k in range(3)],
            )
        return cache[mi.variant()]


@dataclass
class TexelGeometry:
    """Per-frame surface at the valid texels (float32 Dr.Jit arrays)."""

    position: mi.Point3f
    normal: mi.Vector3f  # interpolated shading normal
    geo_normal: mi.Vector3f  # the triangle's normal
    digest: str  # hash of the frame's vertices (keys the visibility cache)

    @classmethod
    def from_frame(cls, atlas: UVAtlas, vertices: np.ndarray, normals: np.ndarray) -> TexelGeometry:
        """Interpolate the frame's mesh at the texels, on the Dr.Jit device (on a GPU the NumPy version of this cost
        more than tracing the frame's visibility)."""
        vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        faces, bary = atlas.on_device()
        verts = mi.Point3f(*vertices.T)
        norms = mi.Vector3f(*np.asarray(normals, np.float32).T)
        v0, v1, v2 = (dr.gather(mi.Point3f, verts, f) for f in faces)
        p = bary[0] * v0 + bary[1] * v1 + bary[2] * v2
        n = bary[0] * dr.gather(mi.Vector3f, norms, faces[0])
        n += bary[1] * dr.gather(mi.Vector3f, norms, faces[1]) + bary[2] * dr.gather(mi.Vector3f, norms, faces[2])
        n /= dr.maximum(dr.norm(n), 1e-12)
        ng = dr.cross(v1 - v0, v2 - v0)
        length = dr.norm(ng)
        # Sliver triangles have no reliable geometric normal: fall back to the shading normal.
        ng = dr.select(length > 1e-20, ng / dr.maximum(length, 1e-20), n)
        dr.eval(p, n, ng)
        digest = hashlib.sha1(vertices.tobytes()).hexdigest()[:16]
        return cls(mi.Point3f(p), mi.Vector3f(n), mi.Vector3f(ng), digest)


# --------------------------------------------------------------------------------------------------------------
# Visibility
# --------------------------------------------------------------------------------------------------------------


def led_layout_digest(led_positions: np.ndarray, far_field: bool) -> str:
    return hashlib.sha1(np.ascontiguousarray(led_positions, np.float32).tobytes() + bytes([far_field])).hexdigest()[:16]


def compute_visibility(
    scene: mi.Scene, geom: TexelGeometry, led_positions: np.ndarray, far_field: bool = False, stage_center: np.ndarray | None = None
) -> mi.UInt32:
    """Bit-packed visibility, word-major: bit (k % 32) of word ``(k // 32) * M + t`` is LED k at texel t.

    Rays are traced LED-major (all texels for one LED, then the next) in groups of 32 LEDs per kernel, which keeps
    them coherent; pairs below the texel's horizon (shading or geometric) trace nothing.
    """
    m = dr.width(geom.position)
    num_leds = led_positions.shape[0]
    words = (num_leds + 31) // 32
    bits = dr.zeros(mi.UInt32, words * m)
    if far_field:
        center = np.zeros(3) if stage_center is None else stage_center
        targets = led_positions - center
        targets /= np.linalg.norm(targets, axis=1, keepdims=True)
    else:
        targets = led_positions
    target_arr = mi.Point3f(*targets.T.astype(np.float32))
    for w in range(words):
        group = min(32, num_leds - 32 * w)
        i = dr.arange(mi.UInt32, group * m)
        j = i // m  # LED within the group (m > 0: no division by zero in the masked tail)
        t = i - j * m
        k = j + 32 * w
        target = dr.gather(mi.Point3f, target_arr, k)
        p = dr.gather(mi.Point3f, geom.position, t)
        n = dr.gather(mi.Vector3f, geom.normal, t)
        ng = dr.gather(mi.Vector3f, geom.geo_normal, t)
        if far_field:
            d = mi.Vector3f(target)
            dist = mi.Float(dr.inf)
        else:
            offset = target - p
            dist = dr.norm(offset)
            d = offset / dist
        facing = (dr.dot(n, d) > 0) & (dr.dot(ng, d) > 0)
        origin = p + ng * RAY_EPSILON
        maxt = dist if far_field else dist * (1.0 - RAY_EPSILON) - RAY_EPSILON
        ray = mi.Ray3f(origin, d, maxt)
        blocked = scene.ray_test(ray, coherent=True, active=facing)
        word = dr.select(facing & ~blocked, mi.UInt32(1) << j, mi.UInt32(0))
        dr.scatter_reduce(dr.ReduceOp.Add, bits, word, t + w * m)
        dr.eval(bits)
    return bits


class VisibilityCache:
    """Visibility bits per (frame geometry, LED layout): in memory, and on disk under ``folder`` if given."""

    def __init__(self, folder: str | Path | None = None):
        self.folder = None if folder is None else Path(folder)
        self._memory: dict[str, mi.UInt32] = {}
        self.hits = 0
        self.misses = 0

    def get(
        self,
        scene: mi.Scene,
        geom: TexelGeometry,
        led_positions: np.ndarray,
        far_field: bool = False,
        stage_center: np.ndarray | None = None,
    ) -> mi.UInt32:
        key = f"{geom.digest}_{led_layout_digest(led_positions, far_field)}"
        if key in self._memory:
            self.hits += 1
            return self._memory[key]
        path = None if self.folder is None else self.folder / f"vis_{key}.npy"
        if path is not None and path.is_file():
            bits = mi.UInt32(np.load(path))
            self.hits += 1
        else:
            bits = compute_visibility(scene, geom, led_positions, far_field, stage_center)
            self.misses += 1
            if path is not None:
                with atomic_path(path) as tmp:
                    with open(tmp, "wb") as fh:
                        np.save(fh, np.array(bits, dtype=np.uint32))
        self._memory[key] = bits
        return bits


# --------------------------------------------------------------------------------------------------------------
# Shading
# --------------------------------------------------------------------------------------------------------------


@dataclass
class TexelShading:
    radiance: np.ndarray  # (M, 3) outgoing radiance toward the camera
    view_dir: np.ndarray  # (M, 3) unit direction from texel to camera (world)
    facing_camera: np.ndarray  # (M,) the camera is above the texel's horizon
    diffuse_unit: np.ndarray  # (M, 3) the diffuse part for albedo 1: radiance = albedo ⊙ diffuse_unit + specular
    specular: np.ndarray  # (M, 3)


def shade_texels(
    geom: TexelGeometry,
    visibility: mi.UInt32 | None,
    led_positions: np.ndarray,
    led_intensities: np.ndarray,
    albedo: np.ndarray,
    roughness: np.ndarray,
    camera_position: np.ndarray,
    far_field: bool = False,
    stage_center: np.ndarray | None = None,
) -> TexelShading:
    """Outgoing radiance of every valid texel toward ``camera_position`` (paper Eq. 1, one bounce).

    ``albedo`` (M, 3) and ``roughness`` (M,) are per valid texel. LEDs that are off are dropped before the loop;
    ``visibility`` may be None when every LED is off.
    """
    m = dr.width(geom.position)
    num_leds = led_positions.shape[0]
    on = np.max(led_intensities, axis=1) > 0
    pos, inten = np.asarray(led_positions, np.float64), np.asarray(led_intensities, np.float64)
    if far_field:
        center = np.zeros(3) if stage_center is None else stage_center
        offset = pos - center
        r2 = np.sum(offset**2, axis=1, keepdims=True)
        pos, inten = offset / np.sqrt(r2), inten / r2
    # One bit per LED that is on, in the same word layout as the visibility: off LEDs are masked out of every
    # texel's word before the loop, so they cost nothing.
    words = (num_leds + 31) // 32
    on_bits = np.zeros(words * 32, bool)
    on_bits[:num_leds] = on
    on_words = (on_bits.reshape(words, 32) * (1 << np.arange(32, dtype=np.uint64))).sum(axis=1).astype(np.uint32)

    p, n = geom.position, geom.normal
    frame = mi.Frame3f(n)
    view = dr.normalize(mi.Point3f(*(float(x) for x in camera_position)) - p)
    wi = frame.to_local(view)
    if on.any():
        diffuse, spec = _led_sum(
            m, words, visibility, mi.UInt32(on_words), mi.Point3f(*pos.T.astype(np.float32)), mi.Color3f(*inten.T.astype(np.float32)),
            p, frame, wi, mi.Float(np.asarray(roughness, np.float32)), far_field,
        )  # fmt: skip
    else:  # every LED off: nothing to do
        diffuse, spec = dr.zeros(mi.Color3f, m), dr.zeros(mi.Color3f, m)
    dr.eval(diffuse, spec, view, wi)
    diffuse, spec = np.array(diffuse).T.reshape(m, 3), np.array(spec).T.reshape(m, 3)
    radiance = np.asarray(albedo, np.float32) * diffuse + spec
    return TexelShading(radiance, np.array(view).T.reshape(m, 3), np.array(wi.z > 0), diffuse, spec)


@dr.syntax
def _led_sum(m, words, visibility, on_words, led_pos, led_int, p, frame, wi, roughness, far_field):
    """Σ over the LEDs that are on *and* visible from each texel, walking the set bits of its visibility words.

    Each lane loops over its own visible LEDs only (about a fifth of them on a body), instead of all LEDs masked.
    """
    t = dr.arange(mi.UInt32, m)  # texel index
    material = brdf.PreparedBRDF(mi.Color3f(1.0), roughness, wi)  # per-texel terms hoisted out of the loop
    diffuse = mi.Color3f(0.0)  # Σ diffuse part per unit albedo (the model is linear in albedo)
    spec = mi.Color3f(0.0)  # Σ specular part
    w = mi.UInt32(0)  # current visibility word
    bits = dr.gather(mi.UInt32, visibility, t) & dr.gather(mi.UInt32, on_words, mi.UInt32(0))  # its remaining set bits
    n_words = mi.UInt32(words)
    while w < n_words:
        if bits == 0:
            w += 1
            bits = dr.gather(mi.UInt32, visibility, w * m + t, w < n_words) & dr.gather(mi.UInt32, on_words, w, w < n_words)
        else:
            led = w * 32 + dr.tzcnt(bits)
            bits = bits & (bits - 1)  # clear the lowest set bit
            lp = dr.gather(mi.Point3f, led_pos, led)
            intensity = dr.gather(mi.Color3f, led_int, led)
            if dr.hint(far_field, mode="scalar"):
                wo_world = mi.Vector3f(lp)
                inv_d2 = mi.Float(1.0)
            else:
                offset = lp - p
                inv_d = dr.rsqrt(dr.squared_norm(offset))
                inv_d2 = dr.square(inv_d)
                wo_world = offset * inv_d
            wo = frame.to_local(wo_world)
            d_part, s_part = material.eval_parts(wo)
            weight = intensity * inv_d2
            diffuse += d_part * weight
            spec += s_part * weight
    return diffuse, spec


# --------------------------------------------------------------------------------------------------------------
# Texture → camera
# --------------------------------------------------------------------------------------------------------------


_CAMERA_RAYS: dict[bytes, mi.Ray3f] = {}


def camera_rays(camera) -> mi.Ray3f:
    """The rays through the pixel centres of ``camera``, row-major, built once per camera and kept on the device:
    only the scene changes from frame to frame, and on a GPU the host-side ray set-up cost more than the tracing."""
    key = np.array([camera.width, camera.height, camera.fx, camera.fy, camera.cx, camera.cy], np.float64).tobytes()
    key += np.asarray(camera.position, np.float64).tobytes() + np.asarray(camera.rotation, np.float64).tobytes()
    key += mi.variant().encode()  # the arrays belong to one backend (tests switch variants in one process)
    ray = _CAMERA_RAYS.get(key)
    if ray is None:
        origin, directions = camera.pixel_rays()
        d = directions.reshape(-1, 3).astype(np.float32)
        ray = mi.Ray3f(mi.Point3f(*np.tile(origin.astype(np.float32), (d.shape[0], 1)).T), mi.Vector3f(*d.T))
        dr.eval(ray)
        if len(_CAMERA_RAYS) >= 64:  # a rig has tens of cameras; bound the memory all the same
            _CAMERA_RAYS.pop(next(iter(_CAMERA_RAYS)))
        _CAMERA_RAYS[key] = ray
    return ray


def rasterize_to_camera(scene: mi.Scene, camera, texture: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Look the UV texture up through each pixel centre of ``camera``: (H, W, C + 1) with alpha = coverage.

    Bilinear in UV; texels outside ``mask`` do not bleed in (normalised by the mask's own interpolation).
    """
    h, w = camera.height, camera.width
    si = scene.ray_intersect(camera_rays(camera), ray_flags=mi.RayFlags.UV, coherent=True)
    valid = si.is_valid()
    channels = texture.shape[2]
    weight = np.ones(texture.shape[:2] + (1,), np.float32) if mask is None else mask[..., None].astype(np.float32)
    tex = mi.Texture2f(
        mi.TensorXf(np.concatenate([texture * weight, weight], axis=2).astype(np.float32)), use_accel=False, wrap_mode=dr.WrapMode.Clamp
    )
    values = tex.eval(si.uv, valid)
    # Normalise by the interpolated mask and pack (H, W, C + 1) on the device: one transfer back.
    cov = values[channels]
    alpha = dr.select(valid, 1.0, 0.0)
    scale = dr.select(cov > 1e-6, alpha / dr.maximum(cov, 1e-6), 0.0)
    out = dr.zeros(mi.Float, h * w * (channels + 1))
    pixel = dr.arange(mi.UInt32, h * w) * (channels + 1)
    for c in range(channels):
        dr.scatter(out, values[c] * scale, pixel + c)
    dr.scatter(out, alpha, pixel + channels)
    return np.array(out, dtype=np.float32).reshape(h, w, channels + 1)
