"""Near-field lights inside the stage (paper "Near-field relighting", Supp. "Details of Near-field Relighting").

A light is a small sphere (``radius``) of radiant intensity ``intensity`` (W/sr, RGB) at ``position``; with a
``direction`` it is a spot, whose intensity falls off with the angle θ from its axis as Mitsuba's ``spot`` emitter's
does (full within ``beam_width``, linear in θ to zero at ``cutoff_angle``). Texels see it with inverse-square falloff
from its centre and a *fraction* of its sphere visible (soft shadows: the body, e.g. an arm, occludes it). Several
lights add. Its envmap conditioning follows the paper: a ray from the stage centre toward each LED;
the LED is lit if its ray meets the light's sphere (of ``conditioning_radius``) and subsequently not the subject,
with an intensity corrected by the squared distance between the point light and that LED.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.limits import MAX_INTENSITY
from gra_mi.core.runtime import opaque, segment
from gra_mi.render import brdf
from gra_mi.render.atlas import TexelGeometry
from gra_mi.render.shading import local_view
from gra_mi.render.visibility import RAY_EPSILON
from gra_mi.stage.envmap import leds_to_envmap

logger = logging.getLogger(__name__)


MIN_CONDITIONING_DISTANCE = 1e-3  # metres: a light closer to an LED than this (or its radius) counts as that far


@dataclass
class PointLight:
    position: np.ndarray  # (3,) metres, world
    intensity: np.ndarray  # (3,) W/sr
    radius: float = 0.03  # physical size: soft shadow edges
    conditioning_radius: float = 0.25  # sphere the stage-centre rays must meet for the envmap conditioning
    direction: np.ndarray | None = None  # a spot's axis (world); None: a point light, the same in every direction
    cutoff_angle: float = 180.0  # degrees: a spot gives no light beyond this angle from its axis
    beam_width: float | None = None  # degrees: full intensity within this angle (default ¾ of the cutoff, as Mitsuba's)

    def __post_init__(self):
        self.position = np.asarray(self.position, np.float64).reshape(3)
        self.intensity = np.broadcast_to(np.asarray(self.intensity, np.float64), (3,)).copy()
        if not np.all(np.isfinite(self.position)):
            raise GraMiParameterError("point_light", f"position must be three finite numbers, got {self.position.tolist()}")
        if not np.all(np.isfinite(self.intensity)) or np.any(self.intensity < 0) or np.any(self.intensity > MAX_INTENSITY):
            raise GraMiParameterError("point_light_intensity", f"must be in [0, {MAX_INTENSITY:g}] W/sr, got {self.intensity.tolist()}")
        if not (np.isfinite(self.radius) and self.radius >= 0) or not self.conditioning_radius > 0:
            raise GraMiParameterError("point_light_radius", f"must be a finite number >= 0 (metres), got {self.radius}")
        if self.direction is not None:
            self._check_cone()

    def _check_cone(self) -> None:
        direction = np.asarray(self.direction, np.float64).reshape(3)
        norm = float(np.linalg.norm(direction))
        if not (np.isfinite(norm) and norm > 0):
            raise GraMiParameterError("direction", f"a spot's direction must be a finite non-zero vector, got {direction.tolist()}")
        self.direction = direction / norm
        if not 0 < self.cutoff_angle < 180:
            raise GraMiParameterError("cutoff_angle", f"must lie in (0°, 180°), got {self.cutoff_angle}°")
        if self.beam_width is None:
            self.beam_width = 0.75 * self.cutoff_angle
        if not 0 <= self.beam_width <= self.cutoff_angle:
            raise GraMiParameterError("beam_width", f"must lie in [0°, cutoff_angle = {self.cutoff_angle}°], got {self.beam_width}°")

    @property
    def is_spot(self) -> bool:
        return self.direction is not None

    def falloff(self, toward: np.ndarray) -> np.ndarray:
        """The spot's falloff (1 for a point light) toward world directions ``toward`` (N, 3), away from the light."""
        toward = np.asarray(toward, np.float64).reshape(-1, 3)
        if not self.is_spot:
            return np.ones(len(toward))
        cos = toward @ self.direction / np.maximum(np.linalg.norm(toward, axis=1), 1e-12)
        theta = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
        ramp = (self.cutoff_angle - theta) / max(self.cutoff_angle - self.beam_width, 1e-12)
        return np.where(theta <= self.beam_width, 1.0, np.where(theta < self.cutoff_angle, ramp, 0.0))


def parse_point_light(text: str, intensity: float, radius: float) -> PointLight:
    try:
        xyz = [float(v) for v in text.split(",")]
    except ValueError:
        xyz = []
    if len(xyz) != 3:
        raise GraMiParameterError("point_light", f"expected X,Y,Z in metres, got '{text}'")
    return PointLight(np.array(xyz), np.full(3, intensity), radius)


def light_samples(light: PointLight, count: int) -> np.ndarray:
    """Points spread evenly over the light's sphere (the centre alone for a zero radius)."""
    if light.radius == 0 or count <= 1:
        return light.position[None]
    i = np.arange(count) + 0.5
    y = 1 - 2 * i / count
    r = np.sqrt(1 - y * y)
    phi = i * math.pi * (3 - math.sqrt(5))
    return light.position + light.radius * np.stack([r * np.cos(phi), y, r * np.sin(phi)], axis=1)


def point_light_visibility(scene: mi.Scene, geom: TexelGeometry, light: PointLight, samples: int = 16) -> mi.Float:
    """Fraction of the light's sphere each texel sees, above its horizon and unoccluded by the subject."""
    m = dr.width(geom.position)
    points = light_samples(light, samples)
    seen = dr.zeros(mi.Float, m)
    usable = dr.zeros(mi.Float, m)
    for q in points:
        target = opaque(mi.Point3f, q)
        offset = target - geom.position
        dist = dr.norm(offset)
        d = offset / dist
        above = (dr.dot(geom.normal, d) > 0) & (dr.dot(geom.geo_normal, d) > 0)
        # Sample points on the far side of the light's sphere are hidden by the light itself.
        front = dr.dot(d, opaque(mi.Vector3f, q - light.position)) <= 0 if light.radius > 0 else mi.Bool(True)
        ray = segment(geom.position + geom.geo_normal * RAY_EPSILON, d, dist * (1 - RAY_EPSILON) - RAY_EPSILON)
        blocked = scene.ray_test(ray, active=above & front)
        usable += dr.select(front, 1.0, 0.0)
        seen += dr.select(above & front & ~blocked, 1.0, 0.0)
    fraction = dr.select(usable > 0, seen / dr.maximum(usable, 1.0), 0.0)
    dr.eval(fraction)
    return fraction


def shade_point_light(
    geom: TexelGeometry, fraction: mi.Float, light: PointLight, roughness: np.ndarray, camera_position, material=None
) -> tuple[np.ndarray, np.ndarray]:
    """(diffuse per unit albedo, specular) of every texel lit by the point light: I/d² · f cos · visible fraction.
    ``roughness`` None: a Lambertian surface (the set). ``camera_position``: any viewer :func:`~gra_mi.render.shading.local_view` takes (a camera, along each normal,
    per-lane directions). ``material``: another material per texel (as :meth:`TexelLedLoop.run` takes one)."""
    frame = mi.Frame3f(geom.normal)
    wi = local_view(frame, geom.position, camera_position)
    material = material or (
        brdf.PreparedLambert(wi)
        if roughness is None
        else brdf.PreparedBRDF(mi.Color3f(1.0), mi.Float(np.asarray(roughness, np.float32)), wi)
    )
    offset = opaque(mi.Point3f, light.position) - geom.position
    inv_d2 = dr.rcp(dr.maximum(dr.squared_norm(offset), 1e-8))
    wo = frame.to_local(offset * dr.sqrt(inv_d2))
    d_part, s_part = material.eval_parts(wo)
    weight = opaque(mi.Color3f, light.intensity) * inv_d2 * fraction * _spot_falloff(light, -offset * dr.sqrt(inv_d2))
    diffuse, spec = d_part * weight, s_part * weight
    dr.eval(diffuse, spec)
    m = dr.width(geom.position)
    return np.array(diffuse).T.reshape(m, 3), np.array(spec).T.reshape(m, 3)


def _spot_falloff(light: PointLight, toward: mi.Vector3f) -> mi.Float:
    """:meth:`PointLight.falloff` on the device, for unit directions ``toward`` pointing away from the light."""
    if not light.is_spot:
        return mi.Float(1.0)
    cos = dr.clip(dr.dot(toward, opaque(mi.Vector3f, light.direction)), -1.0, 1.0)
    theta = dr.acos(cos) * (180.0 / math.pi)
    cutoff, beam = opaque(mi.Float, light.cutoff_angle), opaque(mi.Float, light.beam_width)
    ramp = (cutoff - theta) / dr.maximum(cutoff - beam, 1e-12)
    return dr.select(theta <= beam, 1.0, dr.select(theta < cutoff, ramp, 0.0))


def conditioning_pattern(stage, scene: mi.Scene, light: PointLight) -> np.ndarray:
    """LED intensities (L, 3) standing for the point light in the envmap conditioning (the paper's recipe).

    An LED is lit when the ray from the stage centre toward it meets the light's sphere of ``conditioning_radius``
    and, after the light, not the subject; its value is I / |LED − light|². If no ray meets the sphere, the LED nearest to the light's
    direction stands for it (subject to the same occlusion test). A spot counts with the falloff it has toward the stage
    centre (the subject): a spot turned away from the subject stands for no light.
    """
    c = stage.center
    d = stage.led_directions()
    oc = c - light.position
    b = d @ oc
    disc = b * b - (oc @ oc - light.conditioning_radius**2)
    t_hit = np.where(disc >= 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    hits = np.isfinite(t_hit) & (t_hit > 0)
    if not hits.any():  # the sphere falls between LED directions: its nearest LED stands for it
        to_light = light.position - c
        distance = max(float(np.linalg.norm(to_light)), 1e-9)
        nearest = int(np.argmax(d @ (to_light / distance)))
        hits[nearest], t_hit[nearest] = True, distance
    idx = np.flatnonzero(hits)
    # "If a ray intersects the light and subsequently does not intersect the subject": the stretch from the light
    # onward to the LED must be free (the stage centre itself lies inside the subject).
    start = c + t_hit[idx, None] * d[idx]
    remaining = np.linalg.norm(stage.led_positions[idx] - start, axis=1)
    ray = segment(
        mi.Point3f(*start.T.astype(np.float32)), mi.Vector3f(*d[idx].T.astype(np.float32)), mi.Float(remaining.astype(np.float32))
    )
    hits[idx] = ~np.array(scene.ray_test(ray))
    # I/d² at the LED, with d no less than the light's own radius (a light at an LED would give +inf)
    floor = max(light.radius, MIN_CONDITIONING_DISTANCE) ** 2
    dist2 = np.maximum(np.sum((stage.led_positions - light.position) ** 2, axis=1), floor)
    intensity = light.intensity * light.falloff(c - light.position)[0]
    return np.where(hits[:, None], intensity[None] / dist2[:, None], 0.0)


def conditioning_of(stage, scene: mi.Scene, lights) -> np.ndarray:
    """The conditioning of several lights: light adds, so their patterns add."""
    total = np.zeros((stage.num_leds, 3))
    for light in lights:
        total += conditioning_pattern(stage, scene, light)
    return total


def as_light_list(lights) -> list[PointLight]:
    """None, one :class:`PointLight` or several, as a list."""
    if lights is None:
        return []
    return [lights] if isinstance(lights, PointLight) else list(lights)


def conditioning_envmap(stage, pattern: np.ndarray, height: int = 64) -> np.ndarray:
    """The conditioning as a lat-long envmap: every pixel takes its LED cell's value (``pattern`` is irradiance-like,
    I/d², so it is spread over the cell's solid angle directly)."""

    return leds_to_envmap(stage, pattern * stage.led_distances()[:, None] ** 2, height)
