"""The set of a lightstage scene (its shapes besides the subject: a floor, walls, props) for ``gra-mi export --set``:
each shape as a static triangle mesh in world space, with a preview material (base colour, roughness, metallic) of
its Mitsuba BSDF, which USD's ``UsdPreviewSurface`` and glTF's metallic-roughness material both hold.

A BSDF is more than three numbers, so the preview is a summary, said in the export's notes:

- a ``principled`` BSDF: its own base colour, roughness and metallic (a texture's mean), which are the preview's model;
- otherwise the base colour is the mean diffuse albedo of its BSDF over its surface and the directions it is seen from
  (:func:`~gra_mi.capture.set_albedo.shape_albedos`: a texture's mean colour, a plastic's diffuse lobe under its coat);
  for a metal (no diffuse light, more than 5 % glossy), metallic 1 and the base colour (F0) for which glTF's metal BRDF
  of its roughness reflects as much as all its lobes do (:func:`metal_albedos`: the light its microfacets shadow
  from each other, and its Fresnel's rise toward grazing, are the renderer's to add; one brighter than such a metal can
  be, a Beckmann metal's often, at its own hue's brightest);
- roughness: the BSDF's own (``roughness``, perceptual; ``alpha``, ``alpha_u``/``alpha_v`` as √α; a texture's mean), 0
  for a smooth glossy BSDF, 1 for one without a glossy lobe, which also gets no specular (``ior`` 1: F0 = 0).

Rectangles, disks, spheres and cylinders, Mitsuba's analytic shapes, are tessellated (64 segments around; a sphere an
icosphere of 642 vertices); meshes are written as Mitsuba holds them (one of flat faces, a cube, with each triangle's
corners its own).
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.apps.usd import prim_name
from gra_mi.capture.scene_stage import ANALYTIC_SHAPES, GLOSSY_SAID, RawMesh, shape_label
from gra_mi.capture.set_albedo import shape_albedos

SEGMENTS = 64  # around a disk or a cylinder
METAL_DIFFUSE = 0.02  # a BSDF whose diffuse albedo stays below this, and whose glossy share is above GLOSSY_SAID, is a metal


@dataclass(frozen=True)
class Preview:
    """A BSDF in the terms of UsdPreviewSurface and glTF's metallic-roughness material."""

    base_color: tuple[float, float, float]
    roughness: float  # perceptual (α = r²)
    metallic: float
    ior: float = 1.5  # F0 = ((ior − 1) / (ior + 1))²: 0.04; 1 for a BSDF without a glossy lobe (no specular at all)

    def said(self) -> str:
        specular = "" if self.ior != 1.0 else ", no specular"
        return f"base colour {', '.join(f'{v:.3g}' for v in self.base_color)}, roughness {self.roughness:.3g}, metallic {self.metallic:g}{specular}"


@dataclass(frozen=True)
class SetPart:
    """One set shape: a triangle mesh in world space and its preview material."""

    name: str  # the shape's id in the scene (set_NNN for a gra-mi stage)
    vertices: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32, unit
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from the front
    preview: Preview


def read_set(scene_xml: Path) -> tuple[list[SetPart], list[str]]:
    """The set of the lightstage scene ``scene_xml`` (or the folder holding it as scene.xml; a variant chosen), and a
    note per shape: its preview, or why it is left out."""
    from gra_mi.stage import scene_keys as keys
    from gra_mi.stage.scene import LightstageScene, shape_order

    scene_xml = Path(scene_xml)
    ls = LightstageScene.load(scene_xml / "scene.xml" if scene_xml.is_dir() else scene_xml, every_frame=False)
    parts, notes, used = [], [], set()
    for k, shape in enumerate(sorted((s for s in ls.scene.shapes() if s.id() != keys.SUBJECT_ID), key=shape_order)):
        triangles = shape_triangles(shape)
        label = shape_label(shape)
        if triangles is None:
            notes.append(f"left out: {label}, a {shape.class_name()} (the set holds meshes, rectangles, disks, spheres, cylinders)")
            continue
        parts.append(SetPart(prim_name(shape.id(), f"set_{k:03d}", used), *triangles, preview_material(ls.scene, shape)))
        named = parts[-1].name if parts[-1].name == shape.id() else f"{parts[-1].name} ({label})"
        notes.append(f"{named}: its {shape.bsdf().class_name()} previewed as {parts[-1].preview.said()}")
        if shape.emitter() is not None:
            notes[-1] += "; its area light is not carried (the export's lights: --pattern's LEDs, --envmap)"
    return parts, notes or ["the scene holds no shape besides the subject: no set is written"]


def shape_triangles(shape) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(vertices, normals, faces) of a set shape in world space; None for a kind the set does not hold."""
    import mitsuba as mi

    params = mi.traverse(shape)
    if "faces" in params:
        mesh = RawMesh.of(shape)
        if mesh.normals is None:  # flat (face_normals, a cube): each triangle its own corners, facing its own way
            corners = mesh.vertices[mesh.faces].reshape(-1, 3)
            cross = np.cross(corners[1::3] - corners[0::3], corners[2::3] - corners[0::3])
            faces = np.arange(len(corners), dtype=np.int32).reshape(-1, 3)
            return corners.astype(np.float32), np.repeat(_unit(cross), 3, axis=0).astype(np.float32), faces
        return mesh.vertices.astype(np.float32), _unit(mesh.normals).astype(np.float32), mesh.faces.astype(np.int32)
    kind = ANALYTIC_SHAPES.get(shape.class_name())
    if kind is None or "to_world" not in params:
        return None
    vertices, normals, faces = UNIT_SHAPES[kind]()
    m = np.array(params["to_world"].matrix, np.float64).reshape(4, 4)
    if np.linalg.det(m[:3, :3]) < 0:  # a mirroring placement turns the winding around
        faces = faces[:, ::-1]
    normals = _unit(normals @ np.linalg.inv(m[:3, :3]))  # normals transform by the inverse transpose
    return (vertices @ m[:3, :3].T + m[:3, 3]).astype(np.float32), normals.astype(np.float32), faces.astype(np.int32)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def _rectangle():
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    return vertices, np.tile([0.0, 0.0, 1.0], (4, 1)), np.array([[0, 1, 2], [0, 2, 3]])


def _disk():
    a = np.linspace(0.0, 2.0 * np.pi, SEGMENTS, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    i = np.arange(SEGMENTS)
    faces = np.stack([np.zeros_like(i), 1 + i, 1 + (i + 1) % SEGMENTS], axis=1)
    return np.vstack([[0.0, 0.0, 0.0], ring]), np.tile([0.0, 0.0, 1.0], (SEGMENTS + 1, 1)), faces


def _sphere():
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=3)
    return np.asarray(ico.vertices, np.float64), _unit(np.asarray(ico.vertices, np.float64)), np.asarray(ico.faces)


def _cylinder():
    """Mitsuba's: radius 1 about the z axis from z = 0 to 1, open at both ends."""
    a = np.linspace(0.0, 2.0 * np.pi, SEGMENTS, endpoint=False)
    ring = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=1)
    i, j = np.arange(SEGMENTS), (np.arange(SEGMENTS) + 1) % SEGMENTS
    faces = np.concatenate([np.stack([i, j, SEGMENTS + j], 1), np.stack([i, SEGMENTS + j, SEGMENTS + i], 1)])
    return np.vstack([ring, ring + [0.0, 0.0, 1.0]]), np.vstack([ring, ring]), faces


UNIT_SHAPES = {"rectangle": _rectangle, "disk": _disk, "sphere": _sphere, "cylinder": _cylinder}


def preview_material(scene, shape) -> Preview:
    """The preview of a set shape's BSDF (the module's summary); a ``principled`` BSDF's own parameters, which are the
    preview's model."""
    own = principled_preview(shape.bsdf())
    if own is not None:
        return own
    diffuse, every = shape_albedos(scene, shape)
    diffuse = np.full(3, 0.5) if diffuse is None else np.maximum(diffuse, 0.0)
    every = diffuse if every is None else np.maximum(every, diffuse)
    glossy = float(np.mean(every - diffuse))
    rough = bsdf_roughness(shape.bsdf())
    if glossy <= GLOSSY_SAID:
        base, roughness, metallic, ior = diffuse, 1.0 if rough is None else rough, 0.0, 1.0
    elif diffuse.max() < METAL_DIFFUSE:
        roughness = 0.0 if rough is None else float(np.clip(rough, 0.0, 1.0))
        full, edge = metal_albedos(round(roughness, 3))
        base, metallic, ior = (every - edge) / (full - edge), 1.0, 1.5
        base = base / max(1.0, float(base.max()))  # (past 1, as bright as it goes in its own hue: gold stays gold)
    else:
        base, roughness, metallic, ior = diffuse, 0.0 if rough is None else rough, 0.0, 1.5
    return Preview(tuple(float(v) for v in np.clip(base, 0.0, 1.0)), float(np.clip(roughness, 0.0, 1.0)), metallic, ior)


@functools.lru_cache(maxsize=64)
def metal_albedos(roughness: float, steps: int = 64) -> tuple[float, float]:
    """(E1, E5): the mean albedo of glTF's metal BRDF (GGX, α = r², height-correlated Smith masking, Schlick's Fresnel
    F0 + (1 − F0)(1 − cos)⁵) of this perceptual roughness with F = 1 and with F = (1 − cos)⁵, over cosine-distributed
    view directions as :func:`shape_albedos` averages: one of base colour F0 reflects F0·E1 + (1 − F0)·E5. Midpoint
    quadrature over the views and the GGX distribution of half vectors."""
    alpha2 = max(roughness, 1e-3) ** 4
    grid = (np.arange(steps) + 0.5) / steps
    mu_o = np.sqrt(1.0 - grid)[:, None, None]  # (cosine-distributed views)
    cos2_h = ((1.0 - grid) / (1.0 + (alpha2 - 1.0) * grid))[None, :, None]  # (GGX's θ_h)
    cos_h, sin_h, phi = np.sqrt(cos2_h), np.sqrt(1.0 - cos2_h), 2.0 * np.pi * grid[None, None, :]
    wo = np.stack(np.broadcast_arrays(np.sqrt(1.0 - mu_o**2), 0.0 * mu_o, mu_o))
    h = np.stack(np.broadcast_arrays(sin_h * np.cos(phi), sin_h * np.sin(phi), cos_h))
    o_dot_h = np.einsum("i...,i...->...", wo, h)
    mu_i = 2.0 * o_dot_h * h[2] - wo[2]  # (the light direction: wo reflected about h)

    def smith_lambda(mu):
        return 0.5 * (np.sqrt(1.0 + alpha2 * (1.0 / np.maximum(mu, 1e-9) ** 2 - 1.0)) - 1.0)

    masking = np.where((mu_i > 0) & (o_dot_h > 0), 1.0 / (1.0 + smith_lambda(mu_o) + smith_lambda(mu_i)), 0.0)
    weight = masking * o_dot_h / (mu_o * h[2])  # f cosθ_i / pdf(h → ω_i)
    edge = (1.0 - np.clip(o_dot_h, 0.0, 1.0)) ** 5
    return float(weight.mean()), float((weight * edge).mean())


def principled_preview(bsdf) -> Preview | None:
    """A ``principled`` BSDF's (or one inside a ``twosided``'s) base colour, roughness and metallic, each a texture's
    mean where it is one; None for another BSDF."""
    found = _parameter_means(bsdf, ("base_color", "metallic"))
    if not found.get("base_color"):
        return None
    base = np.broadcast_to(found["base_color"][0], (3,))
    metallic = float(found["metallic"][0][0]) if found.get("metallic") else 0.0
    roughness = bsdf_roughness(bsdf)
    return Preview(
        tuple(float(v) for v in np.clip(base, 0.0, 1.0)),
        float(np.clip(0.5 if roughness is None else roughness, 0.0, 1.0)),
        float(np.clip(metallic, 0.0, 1.0)),
    )


def bsdf_roughness(bsdf) -> float | None:
    """The perceptual roughness a BSDF's parameters give (the mean over its lobes and texels); None where it has none."""
    found = _parameter_means(bsdf, ("alpha", "alpha_u", "alpha_v", "roughness"))
    values = [
        float(m.mean()) if name == "roughness" else np.sqrt(max(float(m.mean()), 0.0)) for name, means in found.items() for m in means
    ]
    return float(np.mean(values)) if values else None


def _parameter_means(bsdf, names: tuple[str, ...]) -> dict[str, list[np.ndarray]]:
    """Each of ``names`` among a BSDF's parameters (``mi.traverse``; nested lobes' too, by the last part of the key):
    the mean per channel of each occurrence over its finite texels (a texture's NaN texels say nothing of it)."""
    import mitsuba as mi

    params = mi.traverse(bsdf)
    found: dict[str, list[np.ndarray]] = {}
    for key in params.keys():
        last = re.sub(r"\.(value|data)$", "", key).rsplit(".", 1)[-1]
        if last in names:
            values = np.array(params[key], np.float64)
            values = values.reshape(-1, values.shape[-1]) if key.endswith(".data") else values.reshape(1, -1)  # (texels × channels)
            values = values[np.isfinite(values).all(axis=1)]
            if len(values):
                found.setdefault(last, []).append(values.mean(axis=0))
    return found
