"""Coarse relighting: frames × cameras × lighting → one-bounce renders through UV space (paper Sec. 3.1).

A :class:`Relighter` holds what never changes (the UV atlas, the material textures) and caches what changes only
with geometry (texel positions and visibility per frame). Rendering a view is then: LED intensities from the
lighting → :func:`gra_mi.uvspace.shade_texels` → :func:`gra_mi.uvspace.rasterize_to_camera`.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import read_exr
from gra_mi.render import bounce
from gra_mi.render.atlas import TexelGeometry, UVAtlas
from gra_mi.render.bounce import BounceOperator, SetGlossyLobe, SetHits, glossy_surfaces, light_along_rays
from gra_mi.render.leds import LedLayout
from gra_mi.render.point_light import PointLight, as_light_list, point_light_visibility, shade_point_light
from gra_mi.render.rasterize import RASTER_SAMPLES, rasterize_to_camera
from gra_mi.render.shading import ALONG_NORMAL, TexelLedLoop, TexelShading, led_cell_roughness, shade_texels
from gra_mi.render.transport import BOUNCE_LEDS, LightTransport
from gra_mi.render.visibility import VisibilityCache, texels_seen_by
from gra_mi.stage.scene import LightstageScene

logger = logging.getLogger(__name__)

DEFAULT_ROUGHNESS = 0.5


def load_texture(path: str | Path, channels: int, name: str) -> np.ndarray:
    """A square UV texture from EXR with the given channel count (RGB albedo, single-channel roughness)."""
    image = read_exr(path)
    if image.shape[0] != image.shape[1]:
        raise GraMiInputError(path, f"a UV texture must be square, got {image.shape[1]}x{image.shape[0]}", field=name)
    if channels == 1:
        image = image[..., :1] if image.shape[2] in (1, 3, 4) else image
    else:
        if image.shape[2] == 1:
            image = np.repeat(image, 3, axis=2)
        image = image[..., :3]
    if not np.isfinite(image).all() or image.min() < 0 or image.max() > 1:
        raise GraMiInputError(path, "values must be finite and in [0, 1]", field=name)
    return image.astype(np.float32)


@dataclass
class ViewRender:
    image: np.ndarray  # (H, W, 4) linear RGB + alpha
    shading: TexelShading  # per valid texel: radiance, view direction, facing mask
    geometry: TexelGeometry


CULL_AT_MOST = 0.8  # trace a subset of texels only when the job's cameras see at most this fraction of them


class Relighter:
    def __init__(
        self,
        ls: LightstageScene,
        resolution: int = 512,
        albedo: np.ndarray | None = None,
        roughness: np.ndarray | None = None,
        far_field: bool = False,
        cache_dir: str | Path | None = None,
        visibility_keep: int | None = None,
        transport: LightTransport | None = None,
    ):
        self.transport = transport or LightTransport()
        self.transport.validate()
        self.ls = ls
        given = albedo if albedo is not None else roughness  # a map's resolution is the atlas's (the default albedo's too)
        resolution = given.shape[0] if given is not None else resolution
        self.atlas = UVAtlas.build(ls.sequence.faces, ls.sequence.uvs, resolution)
        if self.atlas.num_texels == 0:
            name = "albedo" if albedo is not None else "roughness" if roughness is not None else "uv_resolution"
            raise GraMiParameterError(
                name, f"a {resolution}² UV texture has no texel centre inside the subject's UV layout: give a larger one"
            )
        if albedo is None:
            colors = (
                ls.sequence.vertex_colors
                if ls.sequence.vertex_colors is not None
                else np.full((ls.sequence.num_vertices, 3), 0.5, np.float32)
            )
            albedo = self.atlas.bake_vertex_attribute(colors, fill=0.5)
        if roughness is None:
            roughness = np.full((resolution, resolution, 1), DEFAULT_ROUGHNESS, np.float32)
        if roughness.shape[:2] != albedo.shape[:2]:
            raise GraMiParameterError("roughness", f"roughness {roughness.shape[:2]} and albedo {albedo.shape[:2]} resolutions differ")
        self.albedo_tex, self.roughness_tex = albedo, roughness
        self.albedo = self.atlas.gather(albedo)
        self.roughness = self.atlas.gather(roughness)[:, 0]
        self.far_field = far_field
        self.cache = VisibilityCache(cache_dir, keep=visibility_keep)
        self.set_cache = VisibilityCache(cache_dir, keep=visibility_keep)  # of the points where bounce rays hit the set
        self._geometry: dict[int, TexelGeometry] = {}
        self._point_light_vis: dict[tuple, object] = {}
        self._operators: dict[str, BounceOperator] = {}  # the last frames' bounce operators (bounces > 1)
        self._indirect: tuple | None = None  # (key, indirect light) of the last lighting: a frame's cameras share it
        self._job_operator: tuple | None = None  # (key, the operator reduced to what the job's cameras need)
        self._job_texels: tuple | None = None  # (key, the texels whose light the job's cameras need)
        self.job_cameras = None  # :meth:`only_for`

    def with_maps(self, albedo: np.ndarray, roughness: np.ndarray) -> Relighter:
        """The same subject, atlas, transport and caches (geometry, visibility, bounce operators) with other maps of
        this atlas's resolution: a fit's estimates, rendered without tracing anything again."""
        other = copy.copy(self)
        other.albedo_tex, other.roughness_tex = albedo, roughness
        other.albedo, other.roughness = self.atlas.gather(albedo), self.atlas.gather(roughness)[:, 0]
        other._indirect = None
        return other

    def leds(self, far_field: bool | None = None) -> LedLayout:
        """The rig's LEDs, lit near or far field (None: the relighter's own setting)."""
        return LedLayout.of(self.ls.stage, self.far_field if far_field is None else far_field)

    def geometry(self, frame: int) -> TexelGeometry:
        if frame not in self._geometry:
            seq = self.ls.sequence
            self._geometry = {frame: TexelGeometry.from_frame(self.atlas, seq.vertices[frame], seq.normals[frame], self.ls.set_digest)}
        return self._geometry[frame]

    def visibility(self, frame: int, far_field: bool | None = None, led_intensities: np.ndarray | None = None):
        """The frame's per-LED visibility: of every texel, or (after :meth:`only_for`) of those the job's cameras see;
        of every LED, or of those ``led_intensities`` lights (an OLAT traces one LED, not the rig).
        The scene's mesh is moved to the frame only when the bits must be traced: moving it rebuilds the BVH (25-50 ms
        on a body), for nothing when they are cached (a streamed fit's steps visit their views' frames in any order)."""

        def scene_at_frame():
            self.ls.set_frame(frame)
            return self.ls.scene

        lit = None if led_intensities is None else np.flatnonzero(np.reshape(led_intensities, (self.ls.stage.num_leds, -1)).max(axis=1) > 0)
        return self.cache.get(scene_at_frame, self.geometry(frame), self.leds(far_field), self.job_texels(frame), lit)

    def job_texels(self, frame: int) -> np.ndarray | None:
        """The texels whose light the job's cameras need (None: all): those they see and, with more than one
        bounce, every texel whose light reaches those within the extra bounces."""
        if self.job_cameras is None:
            return None
        t = self.transport
        key = (frame, t.bounces, t.bounce_rays, t.bounce_smoothing, self._job_key())
        if self._job_texels is None or self._job_texels[0] != key:
            geom = self.geometry(frame)
            texels = texels_seen_by(geom, self.job_cameras)
            if t.bounces > 1:
                texels = self.bounce_operator(frame).closure(self.atlas.dilated(texels, t.bounce_smoothing), t.bounces)
            if len(texels) > CULL_AT_MOST * dr.width(geom.position):
                texels = None  # cameras around the body see most of it: the full trace is as fast, and serves every job
            self._job_texels = (key, texels)
        return self._job_texels[1]

    def _job_key(self) -> tuple:
        return tuple((c.name, *c.camera_to_world.ravel()) for c in self.job_cameras)

    def bounce_operator(self, frame: int) -> BounceOperator:
        """The frame's texel-to-texel bounce operator: from memory, the cache folder, or traced (and kept in both)."""
        geom = self.geometry(frame)
        key = bounce.operator_key(geom, self.transport.bounce_rays, 0, self._set_materials())
        if key not in self._operators:
            folder = self.cache.folder
            path = None if folder is None else folder / f"bounce_{key}.npz"
            op = None if path is None else BounceOperator.load(path, dr.width(geom.position), self.transport.bounce_rays)
            if op is None:
                self.ls.set_frame(frame)
                seq, subject = self.ls.sequence, self.ls.subject_shape()
                reachable = np.concatenate([seq.vertices[frame], bounce.set_corners(self.ls.scene, subject)])
                texels = bounce.texels_that_see_the_body(geom, reachable)
                rays = self.transport.bounce_rays
                leds = self.ls.stage.led_positions
                op = bounce.trace_operator(self.ls.scene, subject, geom, self.atlas, seq.uvs, seq.faces, texels, rays, 0, leds)
                if path is not None:
                    op.save(path)
            self._operators = {k: v for k, v in list(self._operators.items())[-1:]}  # this frame and the one before
            self._operators[key] = op
        return self._operators[key]

    def _set_materials(self) -> str:
        if not hasattr(self, "_set_materials_digest"):  # the set stays still: one hash per relighter
            key = ""
            if self.ls.set_digest:  # the set's materials, and the LEDs that size its cells
                key = bounce.set_materials_digest(self.ls.scene, self.ls.subject_shape()) + "_" + self.leds(False).digest
            self._set_materials_digest = key
        return self._set_materials_digest

    def job_operator(self, frame: int) -> BounceOperator:
        """The frame's bounce operator, reduced (after :meth:`only_for`) to the rays whose light can reach what the job's
        cameras see: the rays of the texels they see (and of their neighbours the smoothing averages in) and, with more
        bounces, of the texels those rays hit."""
        op = self.bounce_operator(frame)
        if self.job_cameras is None:
            return op
        t = self.transport
        key = (frame, op.rays, t.bounces, t.bounce_smoothing, self._job_key())
        if self._job_operator is None or self._job_operator[0] != key:
            # The texels they see and their neighbours within the smoothing radius, whose received light is averaged in.
            receivers = self.atlas.dilated(texels_seen_by(self.geometry(frame), self.job_cameras), t.bounce_smoothing)
            self._job_operator = (key, op.restricted(op.closure(receivers, t.bounces - 1)))
        return self._job_operator[1]

    def indirect(self, frame: int, led_intensities: np.ndarray, lights: list[PointLight], fractions: list, far_field: bool):
        """The light after the first bounce for this lighting, as (the operator it was computed on, the light along
        each of its rays, (M, 3) what each texel's diffuse layer takes in per unit albedo and T(ω_view)); the cameras
        of one frame and lighting share it."""
        digest = hashlib.sha1(np.ascontiguousarray(led_intensities, np.float32).tobytes())
        digest.update(np.ascontiguousarray(self.albedo, np.float32).tobytes())
        digest.update(np.ascontiguousarray(self.roughness, np.float32).tobytes())
        for light in lights:
            digest.update(repr(light).encode())
        key = (frame, far_field, self.transport.bounces, self.transport.bounce_smoothing, digest.hexdigest(), id(self.job_operator(frame)))
        if self._indirect is None or self._indirect[0] != key:
            op, geom = self.job_operator(frame), self.geometry(frame)
            first = self.light_toward_receivers(frame, op, led_intensities, lights, fractions, far_field)
            from_set = self.set_light(frame, op.set_hits, led_intensities, lights, far_field)
            albedo = mi.Color3f(*self.albedo.T.astype(np.float32))
            light = light_along_rays(op, geom, albedo, first, self.transport.bounces, from_set)
            diffuse = op.smoothed(self.atlas, geom, op.gather_diffuse(geom, light), self.transport.bounce_smoothing)
            dr.eval(light, diffuse)
            self._indirect = (key, (op, light, np.array(diffuse).T.reshape(-1, 3)))
        return self._indirect[1]

    def light_toward_receivers(self, frame, op: BounceOperator, led_intensities, lights, fractions, far_field) -> tuple:
        """Per ray of ``op``: (diffuse per unit albedo, specular) that its source texel sends back toward the receiver
        under the LEDs and the near lights: the same LED loop as a camera's view, one lane per ray."""
        geom = self.geometry(frame)
        sources, toward = op.sources, op.toward_receivers()
        diffuse, spec = dr.zeros(mi.Color3f, op.entries), dr.zeros(mi.Color3f, op.entries)
        if op.entries == 0:
            return diffuse, spec
        if np.max(led_intensities) > 0:
            leds = self.leds(far_field)
            fewer = leds.brightest(led_intensities, BOUNCE_LEDS)
            # Fewer LEDs stand for the lighting: a lobe narrower than their spacing would reflect points, not it.
            reduced = not np.array_equal(fewer, led_intensities)
            rough = led_cell_roughness(self.roughness, BOUNCE_LEDS) if reduced else self.roughness
            vis = self.visibility(frame, far_field, fewer)
            lanes, toward_lanes, distinct, where = op.by_source()
            loop = TexelLedLoop.build(geom, vis, lanes, leds, fewer, toward_lanes, distinct=distinct, hold=False)
            texels, index = distinct
            diffuse, spec = loop.run(dr.gather(mi.Float, dr.gather(mi.Float, mi.Float(np.asarray(rough, np.float32)), texels), index))
            diffuse, spec = dr.gather(mi.Color3f, diffuse, where), dr.gather(mi.Color3f, spec, where)  # back in the entries' order
        if lights:
            s = mi.UInt32(sources)
            at_sources = TexelGeometry(*(dr.gather(type(a), a, s) for a in (geom.position, geom.normal, geom.geo_normal)), "")
            for light, fraction in zip(lights, fractions, strict=True):
                d, sp = shade_point_light(at_sources, dr.gather(mi.Float, fraction, s), light, self.roughness[sources], toward)
                diffuse, spec = diffuse + mi.Color3f(*d.T), spec + mi.Color3f(*sp.T)
        return diffuse, spec

    def set_light(self, frame: int, hits: SetHits, led_intensities, lights: list[PointLight], far_field: bool) -> mi.Color3f:
        """Per ray that hits the set: the radiance the set sends back along it, Lambertian with its diffuse albedo,
        under every LED that is on (fewer standing for them would light a floor from below its horizon) and the near
        lights, each where the set sees it (the body shadows the floor); once per cell of the set (:meth:`SetHits.grouped`).
        A BSDF's glossy lobes add their light per hit, toward each light (:meth:`_set_glossy_light`)."""
        if hits.count == 0:
            return dr.zeros(mi.Color3f, 0)
        leds = self.leds(far_field)
        geom, cell = hits.geometry
        light = dr.zeros(mi.Color3f, dr.width(geom.position))
        vis, fractions = None, []
        if np.max(led_intensities) > 0:
            vis = self.set_cache.get(lambda: self._scene_at(frame), geom, leds, None, np.flatnonzero(np.max(led_intensities, axis=1) > 0))
            count = dr.width(geom.position)
            light, _ = TexelLedLoop.build(geom, vis, np.arange(count), leds, led_intensities, ALONG_NORMAL, hold=False).run(None)
        for near in lights:
            fractions.append(point_light_visibility(self._scene_at(frame), geom, near))
            diffuse, _ = shade_point_light(geom, fractions[-1], near, None, ALONG_NORMAL)
            light += mi.Color3f(*diffuse.T)
        per_hit = dr.gather(mi.Color3f, light, cell) * mi.Color3f(*hits.reflectance.T)
        if hits.glossy.any():
            per_hit += self._set_glossy_light(frame, hits, (vis, leds, led_intensities), list(zip(lights, fractions, strict=True)))
        return per_hit

    def _scene_at(self, frame: int) -> mi.Scene:
        self.ls.set_frame(frame)
        return self.ls.scene

    def _set_glossy_light(self, frame: int, hits: SetHits, led_light: tuple, near: list) -> mi.Color3f:
        """Per hit, the light the set's glossy lobes send back along the rays that hit a glossy BSDF (0 along the others):
        Mitsuba's own ``eval`` of the BSDF at the hit, toward each LED that is on and each near light, through its
        cell's visibility (the same as its diffuse light's)."""
        geom, _ = hits.geometry
        index, si = glossy_surfaces(self._scene_at(frame), hits, self.geometry(frame), geom)
        lobe, cells = SetGlossyLobe(si), hits.cell[index]
        glossy = dr.zeros(mi.Color3f, len(index))
        vis, leds, led_intensities = led_light
        # Each light seen from the hit itself (a lobe is sharper than a cell is small, under a near light), through the
        # visibility of its cell.
        if vis is not None:
            loop = TexelLedLoop.build(geom, vis, cells, leds, led_intensities, ALONG_NORMAL, hold=False)
            glossy = dataclasses.replace(loop, position=si.p).run(None, material=lobe)[1]
        c = mi.UInt32(cells)
        at_hits = TexelGeometry(si.p, *(dr.gather(mi.Vector3f, a, c) for a in (geom.normal, geom.geo_normal)), "")
        for light, fraction in near:
            _, spec = shade_point_light(at_hits, dr.gather(mi.Float, fraction, c), light, None, ALONG_NORMAL, material=lobe)
            glossy += mi.Color3f(*spec.T)
        per_hit = dr.zeros(mi.Color3f, hits.count)
        dr.scatter(per_hit, glossy, mi.UInt32(index.astype(np.uint32)))
        return per_hit

    def only_for(self, cameras) -> None:
        """Render only from these cameras from now on (a batch relight, an evaluation): a new frame's visibility is
        traced for the texels they can see, not all (the same images; about half the rays on a body). None: all."""
        self.job_cameras = None if cameras is None else [self.ls.stage.camera(c) for c in cameras]

    def render(
        self,
        frame: int,
        camera: int | str,
        led_intensities: np.ndarray,
        near_lights: PointLight | list[PointLight] | None = None,
        far_field: bool | None = None,
    ) -> ViewRender:
        """One-bounce render of ``camera`` at ``frame``: LEDs of radiant intensity (L, 3), plus near-field point or
        spot lights (one or a list). ``far_field`` None: the relighter's own setting (docs/accuracy.md, lighting models)."""
        shading, geom = self.shade(frame, camera, led_intensities, near_lights, far_field)
        return ViewRender(self.rasterize(frame, camera, self.atlas.scatter(shading.radiance)), shading, geom)

    def rasterize(self, frame: int, camera: int | str, texture: np.ndarray, samples: int = RASTER_SAMPLES) -> np.ndarray:
        """A UV texture (R, R, C) seen by ``camera`` at ``frame``: (H, W, C + 1) with alpha, from ``samples``² sub-samples
        per pixel (a live viewer takes fewer)."""
        self.ls.set_frame(frame)
        return rasterize_to_camera(self.ls, self.ls.stage.camera(camera), texture, self.atlas.mask, samples)

    def shade(
        self,
        frame: int,
        camera: int | str,
        led_intensities: np.ndarray,
        near_lights: PointLight | list[PointLight] | None = None,
        far_field: bool | None = None,
    ) -> tuple[TexelShading, TexelGeometry]:
        """The UV-space part of :meth:`render`: per-texel radiance toward the camera (no rasterisation)."""
        cam = self.ls.stage.camera(camera)
        far_field = self.far_field if far_field is None else far_field
        # No LED on (e.g. a point light alone): nothing to trace for them.
        vis = self.visibility(frame, far_field, led_intensities) if np.max(led_intensities) > 0 else None
        geom = self.geometry(frame)
        stage = self.ls.stage
        # Far field: the LEDs sample an environment, so each lobe is widened to the LEDs' spacing (no sparkles).
        roughness = led_cell_roughness(self.roughness, stage.num_leds) if far_field else self.roughness
        lights = as_light_list(near_lights)
        fractions = self._near_light_visibility(frame, geom, lights)
        indirect = self.indirect(frame, led_intensities, lights, fractions, far_field) if self.transport.bounces > 1 else None
        diffuse_in = None if indirect is None else indirect[2]
        shading = shade_texels(geom, vis, self.leds(far_field), led_intensities, self.albedo, roughness, cam.position, diffuse_in)
        if indirect is not None:
            op, along_rays = indirect[0], indirect[1]
            spec = op.specular_response(geom, cam.position, mi.Float(np.asarray(roughness, np.float32)), along_rays)
            shading.specular = shading.specular + np.array(spec).T.reshape(-1, 3)
            shading.radiance = self.albedo * shading.diffuse_unit + shading.specular
        for light, fraction in zip(lights, fractions, strict=True):
            diffuse, spec = shade_point_light(geom, fraction, light, self.roughness, cam.position)
            shading.diffuse_unit = shading.diffuse_unit + diffuse
            shading.specular = shading.specular + spec
        if lights:
            shading.radiance = self.albedo * shading.diffuse_unit + shading.specular
        return shading, geom

    def _near_light_visibility(self, frame: int, geom: TexelGeometry, lights: list[PointLight]) -> list:
        """Each near light's visible fraction per texel: traced once per (frame, placement), the next camera of the
        same frame reuses it."""
        self.ls.set_frame(frame)
        visible = {}
        for light in lights:
            key = (frame, tuple(light.position), light.radius)  # depends on geometry and light placement only
            visible[key] = self._point_light_vis.get(key)
            if visible[key] is None:
                visible[key] = point_light_visibility(self.ls.scene, geom, light)
        if lights:
            self._point_light_vis = visible
        return [visible[(frame, tuple(light.position), light.radius)] for light in lights]

    def texel_inputs(self, view: ViewRender) -> dict[str, np.ndarray]:
        """The later RelightNet inputs as (R, R, C) textures: normal, position, view direction, mask."""
        g = view.geometry
        return {
            "normal": self.atlas.scatter(np.array(g.normal).T),
            "position": self.atlas.scatter(np.array(g.position).T),
            "view_dir": self.atlas.scatter(view.shading.view_dir),
            "mask": self.atlas.mask[..., None].astype(np.float32),
        }
