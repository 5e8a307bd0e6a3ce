"""Export the avatar as USD (.usda, .usdc or .usdz), written through usd-core, for VFX pipelines.

What a pipeline TD gets (docs/export.md):

- ``/Avatar`` (the default prim, kind ``component``: referencing the file brings only the avatar): the tracked mesh as
  a ``Mesh`` with time-sampled ``points``, ``normals`` and ``extent`` at the sequence's frame rate
  (``timeCodesPerSecond``; time code t is frame t), ``primvars:st`` per vertex, and ``Looks/Fitted``, a
  ``UsdPreviewSurface``: ``diffuseColor`` from the albedo (16-bit PNG, ``sourceColorSpace = sRGB``), ``roughness``
  from the roughness map (16-bit PNG, ``raw``; perceptual, α = r², as gra-mi's), ``metallic`` 0 and ``ior`` 1.5, the
  specular model's F0 = 0.04.
- ``/Set`` (optional, ``export --set``): a scene's set (a floor, walls, props) as static ``Mesh``\\ es under
  ``/Set/Geometry``, each bound to a constant ``UsdPreviewSurface`` under ``/Set/Looks`` (:mod:`gra_mi.apps.set_export`).
- ``/Capture`` (optional): the calibration's cameras as ``Camera`` prims (focal length and apertures in millimetres
  of a 36 mm wide film; the principal point as aperture offsets), an environment map as a ``DomeLight`` (lat-long,
  OpenEXR's convention = gra-mi's, with +Y up), the LEDs that are on under a pattern as ``SphereLight``\\ s, and a
  light path's moving lights as time-sampled ``SphereLight``\\ s (a spot with the ``ShapingAPI``).

Y is up and one unit is a metre (``upAxis``, ``metersPerUnit``), as gra-mi's world frame. USD's texture coordinates
start at the bottom-left of an image and gra-mi's row 0 is v = 0, so ``st = (u, 1 − v)`` with the same image.
"""

from __future__ import annotations

import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.color import srgb_encode
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.guard import scratch_directory
from gra_mi.core.io import atomic_path, write_exr
from gra_mi.stage.lightstage import Camera, Lightstage
from gra_mi.subject.interchange import USD_SUFFIXES
from gra_mi.subject.sequence import MeshSequence

FILM_WIDTH_MM = 36.0
LED_RADIUS_M = 0.01
"""A SphereLight's radius for a point LED: its radiance is the LED's intensity over the disc it shows, I / (π r²)."""
OPENCV_TO_USD_CAMERA = np.diag([1.0, -1.0, -1.0, 1.0])
"""OpenCV's camera looks along +Z with +Y down; USD's along −Z with +Y up."""


@dataclass
class UsdLighting:
    """The lighting to hand over with the avatar: an environment map and/or the rig's LEDs under one pattern."""

    envmap: np.ndarray | None = None  # (H, W, 3) linear radiance, gra-mi's lat-long convention
    stage: Lightstage | None = None
    led_intensities: np.ndarray | None = None  # (L, 3) W/sr
    tracks: list | None = None  # a light path's lights at each exported frame (gra_mi.apps.export_lights.LightTrack)


def prim_name(text: str, fallback: str, used: set[str]) -> str:
    """A name USD's prim paths take, not yet ``used`` (added to it): ``text`` (a user's id or name) in letters, digits
    and _, else ``fallback``; a second that reads the same gets _2, _3, …"""
    name = re.sub(r"\W", "_", text, flags=re.ASCII)
    name = name if name and not name[0].isdigit() else fallback
    unique, n = name, 1
    while unique in used:
        n += 1
        unique = f"{name}_{n}"
    used.add(unique)
    return unique


def _gf_matrix(m: np.ndarray):
    from pxr import Gf

    return Gf.Matrix4d(np.asarray(m, dtype=np.float64).T.tolist())  # USD's matrices act on row vectors


def _write_png16(path: Path, image: np.ndarray) -> None:
    import png

    image = np.clip(np.nan_to_num(np.asarray(image, np.float64)), 0.0, 1.0)
    height, width = image.shape[:2]
    rows = (image * 65535.0 + 0.5).astype(np.uint16).reshape(height, -1)
    with open(path, "wb") as fh:
        png.Writer(width, height, greyscale=image.ndim == 2, bitdepth=16).write(fh, rows)


def _texture_reader(stage, looks: str, name: str, file: str, color_space: str, st_reader):
    from pxr import Sdf, UsdShade

    tex = UsdShade.Shader.Define(stage, f"{looks}/{name}")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(file)
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
    tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_reader.ConnectableAPI(), "result")
    return tex


def _material(stage, root: str, textures: Path, albedo: np.ndarray, roughness: np.ndarray):
    from pxr import Sdf, UsdShade

    _write_png16(textures / "albedo.png", srgb_encode(np.clip(albedo[..., :3], 0.0, 1.0)))
    _write_png16(textures / "roughness.png", np.clip(roughness[..., 0], 0.0, 1.0))
    folder = textures.name
    looks = f"{root}/Looks/Fitted"
    material = UsdShade.Material.Define(stage, looks)
    surface = UsdShade.Shader.Define(stage, f"{looks}/PreviewSurface")
    surface.CreateIdAttr("UsdPreviewSurface")
    st = UsdShade.Shader.Define(stage, f"{looks}/stReader")
    st.CreateIdAttr("UsdPrimvarReader_float2")
    st.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    base = _texture_reader(stage, looks, "albedoTexture", f"{folder}/albedo.png", "sRGB", st)
    rough = _texture_reader(stage, looks, "roughnessTexture", f"{folder}/roughness.png", "raw", st)
    base.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    rough.CreateOutput("r", Sdf.ValueTypeNames.Float)
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(base.ConnectableAPI(), "rgb")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).ConnectToSource(rough.ConnectableAPI(), "r")
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    surface.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.5)  # F0 = ((1.5 − 1) / (1.5 + 1))² = 0.04
    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(0)
    surface.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    return material


def _mesh(stage, path: str, seq: MeshSequence, frames: list[int]):
    from pxr import Sdf, UsdGeom, Vt

    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr("none")
    mesh.CreateOrientationAttr("rightHanded")
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(seq.faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(seq.faces.astype(np.int32).ravel()))
    st = np.stack([seq.uvs[:, 0], 1.0 - seq.uvs[:, 1]], axis=1).astype(np.float32)
    primvar = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    primvar.Set(Vt.Vec2fArray.FromNumpy(st))
    points, normals, extent = mesh.CreatePointsAttr(), mesh.CreateNormalsAttr(), mesh.CreateExtentAttr()
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    source = mesh.GetPrim().CreateAttribute("gra_mi:sourceFrame", Sdf.ValueTypeNames.Int, custom=True)  # time → the sequence's frame
    for time, t in enumerate(frames):
        p = seq.vertices[t].astype(np.float32)
        points.Set(Vt.Vec3fArray.FromNumpy(p), float(time))
        normals.Set(Vt.Vec3fArray.FromNumpy(seq.normals[t].astype(np.float32)), float(time))
        extent.Set(Vt.Vec3fArray.FromNumpy(np.stack([p.min(axis=0), p.max(axis=0)])), float(time))
        source.Set(int(t), float(time))
    return mesh


def _set_prims(stage, parts: list) -> None:
    """The set's shapes as static meshes, each with its preview material (double-sided: a set shape's back may show)."""
    from pxr import Sdf, UsdGeom, UsdShade, Vt

    UsdGeom.Xform.Define(stage, "/Set")
    UsdGeom.Xform.Define(stage, "/Set/Geometry")  # (typed: a typeless parent breaks the hierarchy for importers)
    UsdGeom.Scope.Define(stage, "/Set/Looks")
    for part in parts:
        mesh = UsdGeom.Mesh.Define(stage, f"/Set/Geometry/{part.name}")
        mesh.CreateSubdivisionSchemeAttr("none")
        mesh.CreateOrientationAttr("rightHanded")
        mesh.CreateDoubleSidedAttr(True)
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(part.faces), 3, np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(part.faces.ravel()))
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(part.vertices))
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(part.normals))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([part.vertices.min(axis=0), part.vertices.max(axis=0)])))
        material = UsdShade.Material.Define(stage, f"/Set/Looks/{part.name}")
        surface = UsdShade.Shader.Define(stage, f"/Set/Looks/{part.name}/PreviewSurface")
        surface.CreateIdAttr("UsdPreviewSurface")
        surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(tuple(part.preview.base_color))
        surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(part.preview.roughness)
        surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(part.preview.metallic)
        surface.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(part.preview.ior)  # (1: no specular, a diffuse BSDF's)
        surface.CreateOutput("surface", Sdf.ValueTypeNames.Token)
        material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
        UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)


def usd_camera_parameters(camera: Camera) -> dict[str, float]:
    """USD ``Camera`` attributes for an OpenCV pinhole: a 36 mm wide film, so focal length = fx · 36 / W; the principal
    point as aperture offsets (USD's film y runs up, image rows down)."""
    focal = camera.fx * FILM_WIDTH_MM / camera.width
    vertical = camera.height * focal / camera.fy
    return {
        "focalLength": focal,
        "horizontalAperture": FILM_WIDTH_MM,
        "verticalAperture": vertical,
        "horizontalApertureOffset": (camera.width / 2.0 - camera.cx) * FILM_WIDTH_MM / camera.width,
        "verticalApertureOffset": (camera.cy - camera.height / 2.0) * vertical / camera.height,
    }


def _cameras(stage, root: str, cameras: list[Camera]) -> None:
    from pxr import Gf, UsdGeom

    for k, camera in enumerate(cameras):
        prim = UsdGeom.Camera.Define(stage, f"{root}/Cameras/cam{k:03d}")
        for name, value in usd_camera_parameters(camera).items():
            prim.GetPrim().GetAttribute(name).Set(float(value))
        prim.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100.0))
        prim.GetPrim().SetDisplayName(camera.name)
        UsdGeom.Xformable(prim).AddTransformOp().Set(_gf_matrix(camera.camera_to_world @ OPENCV_TO_USD_CAMERA))


def _lights(stage, root: str, textures: Path, lighting: UsdLighting) -> None:
    from pxr import Gf, UsdGeom, UsdLux

    if lighting.envmap is not None:
        write_exr(textures / "envmap.exr", lighting.envmap[..., :3])
        dome = UsdLux.DomeLight.Define(stage, f"{root}/Lights/Environment")
        dome.CreateTextureFileAttr(f"{textures.name}/envmap.exr")
        dome.CreateTextureFormatAttr(UsdLux.Tokens.latlong)
        dome.CreateIntensityAttr(1.0)
    if lighting.stage is not None and lighting.led_intensities is not None:
        intensities = np.asarray(lighting.led_intensities, np.float64)
        disc = math.pi * LED_RADIUS_M**2
        for led in np.flatnonzero(intensities.max(axis=1) > 0):  # LEDs that are off are not written
            peak = float(intensities[led].max())
            light = UsdLux.SphereLight.Define(stage, f"{root}/Lights/led{led:04d}")
            light.CreateRadiusAttr(LED_RADIUS_M)
            light.CreateIntensityAttr(peak / disc)
            light.CreateColorAttr(Gf.Vec3f(*(intensities[led] / peak).tolist()))
            UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*lighting.stage.led_positions[led].tolist()))


def _moving_lights(stage, root: str, tracks: list) -> None:
    """A light path's lights as ``SphereLight``\\ s (a spot with the ``ShapingAPI``: its cone angle the cutoff, its
    softness the share of the cone outside the full beam), time-sampled at each exported frame: transform, intensity,
    colour, cone. A light without a radius is a 1 cm sphere marked ``treatAsPoint``."""
    from pxr import Gf, UsdGeom, UsdLux

    from gra_mi.apps.export_lights import light_to_world

    used: set[str] = set()
    for track in tracks:
        light = UsdLux.SphereLight.Define(stage, f"{root}/PathLights/{prim_name(track.name, 'light', used)}")
        light.GetPrim().SetDisplayName(track.name)
        radius = track.states[0].radius or LED_RADIUS_M
        light.CreateRadiusAttr(radius)
        light.CreateTreatAsPointAttr(track.states[0].radius == 0)
        place, power, color = UsdGeom.Xformable(light).AddTransformOp(), light.CreateIntensityAttr(), light.CreateColorAttr()
        shaping = UsdLux.ShapingAPI.Apply(light.GetPrim()) if track.is_spot else None
        for time, state in enumerate(track.states):
            peak = float(state.intensity.max())
            place.Set(_gf_matrix(light_to_world(state)), float(time))
            power.Set(peak / (math.pi * radius**2), float(time))
            color.Set(Gf.Vec3f(*(state.intensity / peak if peak > 0 else np.ones(3)).tolist()), float(time))
            if shaping is not None:
                shaping.CreateShapingConeAngleAttr().Set(float(state.cutoff_angle), float(time))
                softness = 1.0 - state.beam_width / state.cutoff_angle
                shaping.CreateShapingConeSoftnessAttr().Set(float(softness), float(time))


def _write_stage(layer_path: Path, textures: Path, seq, albedo, roughness, frames, cameras, lighting, set_parts) -> None:
    from pxr import Kind, Usd, UsdGeom, UsdShade

    stage = Usd.Stage.CreateNew(str(layer_path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetTimeCodesPerSecond(seq.fps)
    stage.SetFramesPerSecond(seq.fps)
    stage.SetStartTimeCode(0.0)
    stage.SetEndTimeCode(float(len(frames) - 1))
    avatar = UsdGeom.Xform.Define(stage, "/Avatar")
    stage.SetDefaultPrim(avatar.GetPrim())
    Usd.ModelAPI(avatar).SetKind(Kind.Tokens.component)
    mesh = _mesh(stage, "/Avatar/Body", seq, frames)
    material = _material(stage, "/Avatar", textures, albedo, roughness)
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    if set_parts:
        _set_prims(stage, set_parts)
    if cameras or lighting is not None:
        UsdGeom.Scope.Define(stage, "/Capture")
        _cameras(stage, "/Capture", cameras or [])
        if lighting is not None:
            _lights(stage, "/Capture", textures, lighting)
            _moving_lights(stage, "/Capture", lighting.tracks or [])
    stage.GetRootLayer().Save()


def textures_beside(path: Path) -> Path:
    """Where an unpackaged layer's textures go: one folder per file, so that two exports side by side keep theirs."""
    return path.parent / f"{path.stem}_textures"


def export_usd(
    path: str | Path, seq: MeshSequence, albedo: np.ndarray, roughness: np.ndarray, frames: list[int] | None = None,
    cameras: list[Camera] | None = None, lighting: UsdLighting | None = None, set_parts: list | None = None,
) -> Path:  # fmt: skip
    """Write ``path`` (.usda / .usdc / .usd: the layer plus a ``<stem>_textures/`` folder beside it; .usdz: one package).
    ``frames``: the sequence's frames, in order, as time codes 0, 1, … (default: all); the mesh's ``gra_mi:sourceFrame``
    says which frame each time code shows. ``set_parts``: a scene's set (:func:`gra_mi.apps.set_export.read_set`)."""
    path = Path(path)
    if path.suffix.lower() not in USD_SUFFIXES:
        raise GraMiInputError(path, f"not a USD file name: expected one of {', '.join(USD_SUFFIXES)}")
    frames = list(range(seq.num_frames)) if frames is None else list(frames)
    with scratch_directory("gra-mi-usd-") as work:
        packaged = path.suffix.lower() == ".usdz"
        textures = work / ("textures" if packaged else f"{path.stem}_textures")  # unpackaged: one folder per file
        textures.mkdir()
        layer = work / ("avatar.usdc" if packaged else f"avatar{path.suffix.lower()}")
        _write_stage(layer, textures, seq, albedo, roughness, frames, cameras, lighting, set_parts)
        with atomic_path(path) as out:
            if packaged:  # the layer first, then its textures under their own names (USD's zip writer aligns them)
                from pxr import Sdf

                package = Sdf.ZipFileWriter.CreateNew(str(out))
                package.AddFile(str(layer), layer.name)
                for file in sorted(textures.iterdir()):
                    package.AddFile(str(file), f"{textures.name}/{file.name}")
                package.Save()
            else:
                shutil.copyfile(layer, out)
                beside = textures_beside(path)
                beside.mkdir(parents=True, exist_ok=True)
                for file in textures.iterdir():
                    with atomic_path(beside / file.name) as tex_out:
                        shutil.copyfile(file, tex_out)
    return path
