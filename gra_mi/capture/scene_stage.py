"""A gra-mi lightstage from a Mitsuba scene a user wrote (``gra-mi from-scene``).

gra-mi's UV-space stages (``relight``, ``view``, ``export``, RelightNet) need a rig calibration and a tracked mesh
sequence beside the scene file. A user's own scene holds the same things in Mitsuba's words: its ``perspective``
sensors are the rig's cameras, its ``point`` emitters the LEDs (their intensities the scene's own lighting, kept as
an LED pattern), its subject a mesh with texture coordinates, and the subject's material may hold the albedo and
roughness maps gra-mi relights with. Everything is read from the scene as Mitsuba loaded it (world-space vertices,
the sensors' fields of view and principal points, the emitters' own ``sample_direction``), so whatever way the file
spells a transform or a field of view, the stage is what Mitsuba renders. What the stage cannot hold is refused by
name (a ``thinlens`` sensor's depth of field, an area or environment light), or, where it only leaves something out
(a shape the set cannot hold: a curve, an SDF grid), said in the notes the command prints and writes. The scene's other
shapes (a floor, a wall, props) are kept as the stage's set: they shadow the subject and hide it from cameras, as in
the user's scene.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.placement import generate_atlas
from gra_mi.capture.scene_bsdf import CarriedBSDF, carried_bsdf
from gra_mi.capture.set_albedo import set_material
from gra_mi.capture.source import ImportConfig
from gra_mi.capture.source_files import one_uv_tile
from gra_mi.core.config import comma_list
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.io import atomic_write_text, write_exr
from gra_mi.core.limits import MAX_INTENSITY
from gra_mi.render.scene_file import load_scene_file, scene_parameters, select_sensors, sensor_name
from gra_mi.render.scene_lights import emitter_label, plugin_name, point_lights
from gra_mi.stage import scene_keys as keys
from gra_mi.stage.lightstage import Camera, Lightstage, lightstage_from_dict, lightstage_to_dict
from gra_mi.stage.scene import scene_defaults, shape_order, subject_scene_xml, write_rig
from gra_mi.subject.geometry import split_uv_seams, vertex_normals
from gra_mi.subject.sequence import MeshSequence, SequenceLayout, validate_sequence, write_ply, write_sequence

# Mitsuba class → the parameters holding (albedo, roughness) in gra-mi's sense (roughness r: GGX α = r², as gra-mi's)
MATERIAL_MAPS = {
    "SmoothDiffuse": ("reflectance", None),
    "GraMicrofacet": ("albedo", "roughness"),
    "Principled": ("base_color", "roughness"),
}
WRAPPERS = {"TwoSidedBRDF": "brdf_0"}  # a material around the one that holds the maps
DEFAULT_MAP_RESOLUTION = 256  # maps of constants and procedural textures; a bitmap keeps its own size
MAX_MAP_RESOLUTION = 4096
RIGID_TOLERANCE = 1e-4
MAX_FRAMES = 1_000_000


ANALYTIC_SHAPES = {"Rectangle": "rectangle", "Disk": "disk", "Sphere": "sphere", "Cylinder": "cylinder"}  # class → XML type
GLOSSY_SAID = 0.05  # a set shape whose BSDF reflects more than this share of light glossily is named in the notes


@dataclass
class SetShape:
    """A shape of the set: a mesh (world space) or one of Mitsuba's analytic shapes placed by its ``to_world``."""

    label: str  # as the user's scene names it
    kind: str  # "ply" (a mesh) or the analytic shape's XML type
    mesh: RawMesh | None = None
    to_world: np.ndarray | None = None  # (4, 4)
    reflectance: tuple = (0.5, 0.5, 0.5)  # its BSDF's diffuse albedo, the mean over its surface and directions (set_material)
    two_sided: bool = False  # whether its BSDF reflects from both sides
    glossy: float = 0.0  # the mean albedo of its BSDF's other lobes
    carried: CarriedBSDF | None = None  # its own BSDF from the scene file; None: the diffuse stand-in above

    def bsdf_xml(self, files_at: str = "") -> str:
        """Its own BSDF (its files named ``files_at`` + their name), or a diffuse stand-in of its mean diffuse albedo."""
        if self.carried is not None:
            return self.carried.xml(lambda name: f"{files_at}{name}")
        rgb = ", ".join(f"{v:.6g}" for v in self.reflectance)
        diffuse = f'<bsdf type="diffuse"><rgb name="reflectance" value="{rgb}"/></bsdf>'
        return f'<bsdf type="twosided">{diffuse}</bsdf>' if self.two_sided else diffuse


@dataclass
class SceneStage:
    """What a user's scene gives gra-mi: the rig, the subject (its first frame), the scene's LED intensities, its
    material's maps, and the subject's later frames (read as they are written)."""

    stage: Lightstage
    sequence: MeshSequence  # the first frame
    intensities: np.ndarray  # (L, 3) the scene's own LED intensities (W/sr): a pattern, as gra-mi's pattern files hold them
    maps: dict[str, np.ndarray] = field(default_factory=dict)  # "albedo" (R, R, 3), "roughness" (R, R, 1)
    notes: list[str] = field(default_factory=list)  # what the stage leaves out of the scene, said
    later: LaterFrames | None = None
    set_shapes: list[SetShape] = field(default_factory=list)  # the scene's other shapes: shadows and occluders

    @property
    def num_frames(self) -> int:
        return 1 + (len(self.later.values) if self.later else 0)

    def frames(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(vertices, normals) of every frame, the later ones loaded one at a time."""
        yield self.sequence.vertices[0], self.sequence.normals[0]
        if self.later:
            yield from self.later


@dataclass
class RawMesh:
    """The subject as one load of the scene holds it: world space, split at UV seams by Mitsuba."""

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 3) int32
    normals: np.ndarray | None  # Mitsuba's vertex normals; None with face_normals
    texcoords: np.ndarray | None

    @classmethod
    def of(cls, shape) -> RawMesh:
        import mitsuba as mi

        params = mi.traverse(shape)
        get = {name: np.array(params[key], np.float64) for name, key in (("v", "vertex_positions"), ("n", "vertex_normals"),
               ("t", "vertex_texcoords")) if key in params and np.array(params[key]).size}  # fmt: skip
        faces = np.array(params["faces"], np.int64).reshape(-1, 3).astype(np.int32)
        return cls(
            get["v"].reshape(-1, 3), faces, get["n"].reshape(-1, 3) if "n" in get else None, get["t"].reshape(-1, 2) if "t" in get else None
        )

    def shading_normals(self) -> np.ndarray:
        """Mitsuba's normals, or smooth ones across the UV seams (of the mesh welded by position)."""
        if self.normals is not None:
            return self.normals
        _, weld = np.unique(self.vertices, axis=0, return_inverse=True)
        welded = np.zeros((weld.max() + 1, 3))
        welded[weld.reshape(-1)] = self.vertices
        return vertex_normals(welded, weld.reshape(-1)[self.faces])[weld.reshape(-1)]


def stage_from_scene(
    path: str | Path, defines: dict[str, str] | None = None, frames: list[str] | None = None, parameter: str = "frame", fps: float = 24.0
) -> SceneStage:
    """Read the lightstage in the Mitsuba scene file ``path`` (``defines``: its ``-D`` parameters). ``frames``: values
    of the scene's ``parameter`` to load it at, one per frame of a moving subject (the first now, the later ones as
    :meth:`SceneStage.frames` reads them)."""
    path, frames = Path(path), frames or []
    scene = load_scene_file(path, {**(defines or {}), **({parameter: frames[0]} if frames else {})})
    rig = scene_rig(scene, path)
    cameras, positions, intensities, _ = rig
    shape, others = subject_shape(scene, path)
    set_shapes, notes = scene_set(scene, others, (path, {**(defines or {}), **({parameter: frames[0]} if frames else {})}))
    mesh = RawMesh.of(shape)
    faces, uvs, position_of = _layout(mesh, path, notes)
    if mesh.normals is None:
        notes.append("the subject has no vertex normals (face_normals): gra-mi shades it with smooth ones")
    vertices, normals = mesh.vertices[position_of], mesh.shading_normals()[position_of]
    labels = frames[:1] or [""]
    sequence = MeshSequence(
        faces, uvs.astype(np.float32), vertices[None].astype(np.float32), normals[None].astype(np.float32), fps, labels, origin=str(path)
    )
    validate_sequence(sequence, str(path))
    center = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0  # where an environment is seen from: the subject's middle
    top = float(intensities.max())
    data = lightstage_to_dict(Lightstage(positions, cameras, center, float(np.median(np.linalg.norm(positions - center, axis=1)))))
    data["stage"]["max_led_intensity"] = top if top > 0 else 1.0
    stage = lightstage_from_dict(data, source=str(path))  # the calibration's own checks: two LEDs at one place, ...
    maps = material_maps(shape, path, notes)
    if top <= 0:
        notes.append("every LED is off in the scene (intensity 0): lighting.json drives none; relight with --envmap or --olat")
    later = LaterFrames(path, defines or {}, parameter, frames, mesh, position_of, rig) if frames[1:] else None
    return SceneStage(stage, sequence, intensities, maps, notes, later, set_shapes)


def frame_values(text: str, path: Path, parameter: str) -> list[str]:
    """``--frames``: 'A:B' (B excluded), each value zero-padded to the width of the parameter's default
    (``<default name="frame" value="0000"/>``: 0000, 0001, …), or a comma list of values as the scene takes them."""
    if parameter not in (known := scene_parameters(path)):
        raise GraMiParameterError("frame_parameter", f"{path} has no parameter '{parameter}' to set per frame (it has: "
                                  f"{', '.join(sorted(known)) or 'none'}; e.g. <string name=\"filename\" value=\"body_${parameter}.ply\"/>)")  # fmt: skip
    if ":" not in text:
        values = comma_list(text)
        if not values or len(set(values)) != len(values):
            return _refuse_frames(text, "selects no frame" if not values else "gives a frame twice")
        return values
    a, _, b = text.partition(":")
    if not (a.strip().isdigit() and b.strip().isdigit()) or int(b) <= int(a):
        return _refuse_frames(text, "expected A:B with integers A < B (B excluded), or a comma list of values")
    if int(b) - int(a) > MAX_FRAMES:
        return _refuse_frames(text, f"selects more than {MAX_FRAMES:,} frames")
    default = scene_defaults(path).get(parameter, "")
    width = len(default) if default.isdigit() else 0
    return [f"{i:0{width}d}" for i in range(int(a), int(b))]


def _refuse_frames(text: str, problem: str) -> list[str]:
    raise GraMiParameterError("frames", f"'{text}' {problem}")


@dataclass
class LaterFrames:
    """The subject's frames after the first: the scene loaded at each value of its frame parameter, the rig and the
    mesh's topology checked against the first's (a rig stays fixed; only the subject moves)."""

    path: Path
    defines: dict[str, str]
    parameter: str
    all_values: list[str]
    first: RawMesh
    position_of: np.ndarray
    rig: tuple

    @property
    def values(self) -> list[str]:
        return self.all_values[1:]

    def __iter__(self) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        for value in self.values:
            defines, at_first = {**self.defines, self.parameter: value}, f"{self.parameter}={self.all_values[0]}"
            mesh = load_frame(self.path, defines, f"{self.parameter}={value}", self.rig, at_first, self.first)
            yield mesh.vertices[self.position_of].astype(np.float32), mesh.shading_normals()[self.position_of].astype(np.float32)


def load_frame(path: Path, defines: dict[str, str], where: str, rig: tuple, at_first: str, first: RawMesh | None = None) -> RawMesh:
    """The subject of the scene ``path`` loaded with ``defines`` (``where`` says them in errors), the scene's rig
    checked against ``rig`` (read ``at_first``) and, given the ``first`` frame's mesh, its topology against that: a
    rig stays fixed, a tracked mesh keeps its vertices, triangles and UVs; only positions move."""
    try:
        scene = load_scene_file(path, defines)
    except GraMiInputError as exc:  # a later frame's file: the frames before it may be written already
        raise GraMiInputError(exc.source, f"with {where}: {exc.problem}") from None
    same_rig(rig, scene_rig(scene, path), path, where, at_first)
    mesh = RawMesh.of(subject_shape(scene, path)[0])
    if first is None:
        return mesh
    for name, exact in (("faces", True), ("texcoords", True), ("vertices", False)):  # positions move, the rest stays
        ours, theirs = getattr(mesh, name), getattr(first, name)
        if (ours is None) != (theirs is None) or (
            ours is not None and (ours.shape != theirs.shape or (exact and not np.array_equal(ours, theirs)))
        ):
            raise GraMiInputError(path, f"with {where} the subject's {name} differ from the first frame's: a tracked mesh "
                                  "keeps its vertices, triangles and UVs, only its positions move")  # fmt: skip
    return mesh


def scene_rig(scene, path: Path) -> tuple[list[Camera], np.ndarray, np.ndarray, np.ndarray]:
    """What stays fixed while the subject moves: the cameras, the LEDs' positions and intensities, and the set (the
    bounds of every other shape, (N, 6))."""
    sensors = scene.sensors()
    cameras = [camera_of(sensors[i], sensor_name(i, sensors[i], path), path) for i in select_sensors(path, scene, [])]
    others = subject_shape(scene, path)[1]
    bounds = np.array([[*s.bbox().min, *s.bbox().max] for s in others], np.float64).reshape(-1, 6)
    return (cameras, *_leds(scene, path), bounds)


def same_rig(first: tuple, now: tuple, path: Path, where: str, at_first: str) -> None:
    """Refuse a rig (:func:`scene_rig`'s cameras, LED positions, intensities, set) that is not the one read ``at_first``."""
    (cams_a, pos_a, int_a, set_a), (cams_b, pos_b, int_b, set_b) = first, now
    if [c.name for c in cams_a] != [c.name for c in cams_b]:
        raise GraMiInputError(path, f"with {where} the scene's sensors are not the ones at {at_first}: a rig stays fixed")
    for a, b in zip(cams_a, cams_b, strict=True):
        if not np.allclose(np.r_[a.camera_to_world.ravel(), a.fx, a.cx, a.cy, a.width, a.height],
                           np.r_[b.camera_to_world.ravel(), b.fx, b.cx, b.cy, b.width, b.height], rtol=0, atol=1e-6):  # fmt: skip
            raise GraMiInputError(path, f"with {where} sensor '{a.name}' is not where or what it is at {at_first}: a rig stays fixed")
    if pos_a.shape != pos_b.shape or not (np.allclose(pos_a, pos_b, rtol=0, atol=1e-6) and np.allclose(int_a, int_b, rtol=1e-6)):
        raise GraMiInputError(path, f"with {where} the LEDs are not the ones at {at_first}: a rig stays fixed (light the "
                              "subject per frame with `gra-mi relight --lights`)")  # fmt: skip
    if set_a.shape != set_b.shape or not np.allclose(set_a, set_b, rtol=0, atol=1e-6):
        raise GraMiInputError(path, f"with {where} the shapes besides the subject (the set) are not where they are at {at_first}: "
                              "the set stays still; only the subject moves")  # fmt: skip


def camera_of(sensor, name: str, path: Path) -> Camera:
    """A ``perspective`` sensor as a pinhole camera in OpenCV's convention (its film's crop window is the image)."""
    import mitsuba as mi

    kind = sensor.class_name()
    if kind != "PerspectiveCamera":
        raise GraMiInputError(path, f"sensor '{name}' is a {kind}: gra-mi's cameras are pinholes, a <sensor type=\"perspective\"> "
                              "(a thinlens's depth of field, an orthographic or spherical projection would be lost)")  # fmt: skip
    params = mi.traverse(sensor)
    width, height = (int(x) for x in sensor.film().size())
    (crop_w, crop_h), (crop_x, crop_y) = sensor.film().crop_size(), sensor.film().crop_offset()
    fx = 0.5 * width / np.tan(np.radians(0.5 * float(params["x_fov"][0])))
    cx = width / 2.0 - float(params["principal_point_offset_x"][0]) * width - int(crop_x)
    cy = height / 2.0 - float(params["principal_point_offset_y"][0]) * height - int(crop_y)
    to_world = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    rotation = to_world[:3, :3]
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=RIGID_TOLERANCE) or np.linalg.det(rotation) < 0:
        raise GraMiInputError(path, f"sensor '{name}': its to_world scales, shears or mirrors the camera; give it a rotation "
                              "and a translation only (a <lookat>)")  # fmt: skip
    return Camera(name, int(crop_w), int(crop_h), fx, fx, cx, cy, to_world @ np.diag([-1.0, -1.0, 1.0, 1.0]))


def _leds(scene, path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Positions and intensities (L, 3) of the scene's point emitters; any other emitter is refused, naming it."""
    emitters = list(scene.emitters())
    for i, emitter in enumerate(emitters):
        if (kind := plugin_name(emitter)) != "point":
            raise GraMiInputError(path, f"{emitter_label(i, emitter)} is a '{kind}' emitter: a gra-mi lightstage's LEDs are "
                                  "point emitters (render this scene as it is with `gra-mi render`)")  # fmt: skip
    if not emitters:
        raise GraMiInputError(path, 'the scene has no emitter: a lightstage\'s LEDs are <emitter type="point"> in it')
    positions, intensities = point_lights(emitters)
    bad = ~(np.isfinite(intensities) & (intensities >= 0) & (intensities <= MAX_INTENSITY)).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise GraMiInputError(
            path, f"{emitter_label(i, emitters[i])}: intensity {intensities[i].tolist()} must be finite, >= 0 and <= {MAX_INTENSITY:g} W/sr"
        )
    return positions, intensities


def subject_shape(scene, path: Path) -> tuple[object, list]:
    """The shape with id ``subject``, or the scene's only shape, and the scene's other shapes (in :func:`shape_order`)."""
    shapes = list(scene.shapes())
    chosen = [s for s in shapes if s.id() == keys.SUBJECT_ID]
    if not chosen and len(shapes) == 1:
        chosen = shapes
    if not chosen:  # (Mitsuba itself refuses two objects with one id)
        ids = ", ".join(f"'{s.id()}'" if s.id() else s.class_name() for s in shapes) or "none"
        raise GraMiInputError(path, f"no shape has id '{keys.SUBJECT_ID}' among the scene's shapes ({ids}): give the body's "
                              f'shape id="{keys.SUBJECT_ID}"')  # fmt: skip
    subject = chosen[0]
    label = f"shape '{subject.id()}'" if subject.id() else f"the {subject.class_name()} shape"
    if not subject.is_mesh():
        raise GraMiInputError(path, f"{label} is a {subject.class_name()}, not a mesh: the subject is a mesh with texture "
                              "coordinates (obj, ply, serialized)")  # fmt: skip
    return subject, sorted((s for s in shapes if s is not subject), key=shape_order)


def shape_label(shape) -> str:
    return f"shape '{shape.id()}'" if shape.id() else f"a {shape.class_name()} shape"


def scene_set(scene, others: list, source: tuple[Path, dict] | None = None) -> tuple[list[SetShape], list[str]]:
    """The scene's other shapes as the stage's set, as they stand at the first frame (the set stays still; a later
    frame's is checked against it), and what is said about them: kept, or left out (a kind the set cannot hold).
    ``source``: (the scene file, its defines), whose elements give each shape its own BSDF where they can be carried
    (:func:`~gra_mi.capture.scene_bsdf.carried_bsdf`); a diffuse stand-in otherwise."""
    import mitsuba as mi

    kept, notes = [], []
    for shape in others:
        params = mi.traverse(shape)
        kind = ANALYTIC_SHAPES.get(shape.class_name())
        if "faces" in params:
            placed = ("ply", RawMesh.of(shape), None)
        elif kind and "to_world" in params:  # exact: Mitsuba's own shape, its whole placement in one matrix
            placed = (kind, None, np.array(params["to_world"].matrix, np.float64).reshape(4, 4))
        else:
            notes.append(f"left out: {shape_label(shape)}, a {shape.class_name()} (the set holds meshes, rectangles, disks, spheres "
                         "and cylinders), so its shadows are not in gra-mi's renders")  # fmt: skip
            continue
        rgb, two_sided, glossy = set_material(scene, shape)
        carried = carried_bsdf(source[0], shape, source[1]) if source else "no scene file was given"
        own = carried if isinstance(carried, CarriedBSDF) else None
        kept.append(SetShape(shape_label(shape), *placed, tuple(min(v, 1.0) for v in rgb), two_sided, glossy, own))
        with_bsdf = ", with its own BSDF" if own else ""
        notes.append(f"kept as the set: {shape_label(shape)} ({set_name(len(kept) - 1)} in scene.xml{with_bsdf})")
        notes += material_notes(shape, rgb, glossy, carried)
    if kept:
        notes.append("the set shadows the subject and hides it from the cameras, and reflects light onto it with two bounces "
                     "(a BSDF's diffuse lobes, and its glossy lobes toward each light)")  # fmt: skip
    return kept, notes


def material_notes(shape, rgb: tuple, glossy: float, carried) -> list[str]:
    """What the stage's set shape leaves out of the user's, said: light it lets through (opaque in the stage); where its
    own BSDF is not ``carried`` (a reason), the diffuse stand-in's loss: its glossy light (more than
    :data:`GLOSSY_SAID`), its texture's light over 1 (kept at 1)."""
    import mitsuba as mi

    label, notes = shape_label(shape), []
    if mi.has_flag(shape.bsdf().flags(), mi.BSDFFlags.Null | mi.BSDFFlags.Transmission):
        notes.append(f"{label} lets light through in your scene (an opacity mask, glass); in the stage it is opaque: it "
                     "shadows the subject fully and hides it from the cameras")  # fmt: skip
    if isinstance(carried, CarriedBSDF):
        return notes
    if isinstance(carried, str):
        notes.append(f"the BSDF of {label} is not carried into scene.xml ({carried}): a diffuse of its mean diffuse "
                     f"albedo {', '.join(f'{min(v, 1.0):.3g}' for v in rgb)} stands in")  # fmt: skip
    if glossy > GLOSSY_SAID:
        notes.append(f"the BSDF of {label} reflects {glossy:.0%} of the light it receives glossily (a metal, a coat), which "
                     "the stand-in does not: the subject renders darker near it than in your scene; put the BSDF in "
                     "scene.xml to have that light (docs/guides/scene-files.md)")  # fmt: skip
    if max(rgb) > 1.0:
        notes.append(f"the BSDF of {label} reflects more light than it receives (diffuse albedo {max(rgb):.3g} > 1, not a "
                     "physical material): the stand-in keeps 1")  # fmt: skip
    return notes


def _layout(mesh: RawMesh, path: Path, notes: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(faces, UVs, the raw vertex of each vertex): the mesh's own UVs, or a layout generated for a mesh without (as an
    import generates one), split at its seams."""
    if mesh.texcoords is not None:
        return mesh.faces, one_uv_tile(path, mesh.texcoords), np.arange(len(mesh.vertices))
    atlas_uvs, face_uvs, said = generate_atlas(mesh.vertices, mesh.faces, ImportConfig().uv_resolution)
    faces, position_of, uv_of = split_uv_seams(mesh.faces, face_uvs)
    notes.append(f"the subject has no texture coordinates: its UV layout is {said}")
    return faces, atlas_uvs[uv_of], position_of


def children(node) -> dict:
    """A scene object's parameters that are objects themselves (textures, nested materials), by name."""
    import mitsuba as mi

    class Collect(mi.TraversalCallback):
        def __init__(self):
            super().__init__()
            self.found = {}

        def put(self, name, value, *flags):
            if isinstance(value, mi.Object):
                self.found[name] = value

    collect = Collect()
    node.traverse(collect)
    return collect.found


def material_maps(shape, path: Path, notes: list[str]) -> dict[str, np.ndarray]:
    """The subject material's albedo and roughness as square UV maps (a bitmap at its own size), where gra-mi reads its
    kind (:data:`MATERIAL_MAPS`); otherwise none, said."""
    if not shape.has_vertex_texcoords():
        notes.append("its material's textures are not baked (on a mesh without texture coordinates they had none to follow)")
        return {}
    bsdf = shape.bsdf()
    while _kind(bsdf) in WRAPPERS:
        bsdf = children(bsdf)[WRAPPERS[_kind(bsdf)]]
    kind = _kind(bsdf)
    if kind not in MATERIAL_MAPS:
        notes.append(f"the subject's material is a {kind}: no albedo or roughness taken from it (give "
                     "`gra-mi relight --albedo/--roughness`)")  # fmt: skip
        return {}
    found = children(bsdf)
    textures = {name: found[param] for name, param in zip(("albedo", "roughness"), MATERIAL_MAPS[kind], strict=True) if param in found}
    largest = max((_bitmap_side(t) for t in textures.values()), default=0)
    resolution = min(MAX_MAP_RESOLUTION, largest or DEFAULT_MAP_RESOLUTION)
    if largest > MAX_MAP_RESOLUTION:
        notes.append(f"the subject's maps are baked at {MAX_MAP_RESOLUTION}² (its largest bitmap has {largest} texels a side)")
    maps = {name: bake_texture(texture, resolution, 3 if name == "albedo" else 1, shape) for name, texture in textures.items()}
    if kind == "Principled":
        notes.append("the subject's principled material gives its base colour and roughness; its metallic, specular, sheen, "
                     "clearcoat and transmission are not gra-mi's model (Lambert + GGX, F0 = 0.04)")  # fmt: skip
    if "roughness" not in maps:
        notes.append(f"the subject's {kind} has no roughness: relight uses gra-mi's default")
    for name, image in maps.items():
        if not np.isfinite(image).all() or image.min() < 0 or image.max() > 1:
            notes.append(f"the subject's {name} holds values outside [0, 1]: clamped into it")
            maps[name] = np.clip(np.nan_to_num(image, nan=0.0), 0.0, 1.0)
    return maps


def _kind(bsdf) -> str:
    """Mitsuba's class name of a material; a Python plugin's (``gra_microfacet``) is its Python class's."""
    return type(bsdf).__name__ if bsdf.class_name() == "BSDF" else bsdf.class_name()


def _bitmap_side(texture) -> int:
    import mitsuba as mi

    params = mi.traverse(texture)
    return max(np.array(params["data"]).shape[:2]) if "data" in params else 0


def bake_texture(texture, resolution: int, channels: int, shape=None) -> np.ndarray:
    """A Mitsuba texture evaluated at the texel centres of a ``resolution``² UV map (row r at v = (r + ½) / R, as
    gra-mi's maps and Mitsuba's bitmaps lie), (R, R, ``channels``) float32. With the ``shape`` it lies on, a texel
    inside the mesh's UV layout is evaluated at the surface point there (``eval_parameterization``: a texture of
    vertex attributes, or of positions, needs it); one outside, at its UV alone."""
    import drjit as dr
    import mitsuba as mi

    u, v = np.meshgrid((np.arange(resolution) + 0.5) / resolution, (np.arange(resolution) + 0.5) / resolution)
    uv = mi.Point2f(u.ravel().astype(np.float32), v.ravel().astype(np.float32))
    si = dr.zeros(mi.SurfaceInteraction3f, resolution * resolution)
    si.uv = uv
    if shape is not None:
        on = shape.eval_parameterization(uv)
        si = dr.select(on.is_valid(), on, si)
    values = np.array(texture.eval(si) if channels == 3 else texture.eval_1(si), np.float32).reshape(channels, -1)
    # a constant evaluates once for all lanes
    return np.ascontiguousarray(np.broadcast_to(values, (channels, resolution * resolution)).T).reshape(resolution, resolution, channels)


def write_scene_stage(stage: SceneStage, folder: Path, spp: int = 64) -> list[Path]:
    """``folder``: scene.xml (a gra-mi lightstage scene), rig/, subject/, lighting.json (the scene's own LED intensities),
    albedo.exr / roughness.exr (where the material held them), notes.md. Returns what it wrote. scene.xml is written
    last and removed first: a folder with one holds a whole stage (a rerun stopped at a bad frame leaves none)."""
    (folder / "scene.xml").unlink(missing_ok=True)
    write_rig(stage.stage, folder / "rig")
    seq = stage.sequence
    labels = stage.later.all_values if stage.later else seq.frame_labels
    layout = SequenceLayout(seq.faces, seq.uvs, stage.num_frames, seq.fps, labels, _vertex_colours(stage))
    write_sequence(folder / "subject", layout, stage.frames(), source=seq.origin)
    atomic_write_text(folder / "lighting.json", json.dumps({"intensities": np.round(stage.intensities, 9).tolist()}) + "\n")
    written = [folder / name for name in ("rig", "subject", "lighting.json")]
    for name, image in stage.maps.items():
        write_exr(folder / f"{name}.exr", image)
        written.append(folder / f"{name}.exr")
    lines = ["# What gra-mi took from the scene", "", f"- {len(stage.stage.cameras)} cameras, {stage.stage.num_leds} LEDs"]
    lines += [f"- {note}" for note in stage.notes]
    atomic_write_text(folder / "notes.md", "\n".join(lines) + "\n")
    set_xml = write_set(stage.set_shapes, folder / "set")
    atomic_write_text(folder / "scene.xml", subject_scene_xml("rig", "subject", spp=spp, set_xml=set_xml))
    return [
        folder / "scene.xml",
        *written,
        *([folder / "set"] if any(s.mesh is not None for s in stage.set_shapes) else []),
        folder / "notes.md",
    ]


def write_set(shapes: list[SetShape], folder: Path, to_stage: np.ndarray | None = None) -> str:
    """The scene.xml elements of the set ``shapes`` (ids of gra-mi's own: a user's id may be any text), its meshes
    written as ``folder``/set_NNN.ply (a rerun's old ones removed). ``to_stage``: a 4 × 4 rigid transform (and scale)
    from the shapes' world to the stage's (an import's world frame); None: as they are."""
    for old in folder.glob("set_*"):  # (meshes and the files of carried BSDFs)
        old.unlink()
    m = np.eye(4) if to_stage is None else np.asarray(to_stage, np.float64)
    elements = []
    for i, shape in enumerate(shapes):
        name = set_name(i)
        for file_name, source in (shape.carried.files if shape.carried else {}).items():
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, folder / f"{name}_{file_name}")
        if shape.mesh is None:
            matrix = " ".join(f"{v:.9g}" for v in (m @ shape.to_world).ravel())
            elements.append(f'<shape type="{shape.kind}" id="{name}"><transform name="to_world"><matrix value="{matrix}"/></transform>'
                            f'{shape.bsdf_xml(f"{folder.name}/{name}_")}</shape>')  # fmt: skip
            continue
        mesh = shape.mesh
        folder.mkdir(parents=True, exist_ok=True)
        uvs = mesh.texcoords if mesh.texcoords is not None else np.zeros((len(mesh.vertices), 2))
        normals = mesh.shading_normals() @ np.linalg.inv(m[:3, :3])  # normals transform by the inverse transpose
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        write_ply(folder / f"{name}.ply", mesh.vertices @ m[:3, :3].T + m[:3, 3], normals, uvs, mesh.faces)
        flat = "true" if mesh.normals is None else "false"  # a cube's faces stay flat
        elements.append(f'<shape type="ply" id="{name}"><string name="filename" value="{folder.name}/{name}.ply"/>'
                        f'<boolean name="face_normals" value="{flat}"/>{shape.bsdf_xml(f"{folder.name}/{name}_")}</shape>')  # fmt: skip
    return "\n    ".join(elements)


def set_name(index: int) -> str:
    return f"set_{index:03d}"


def _vertex_colours(stage: SceneStage) -> np.ndarray:
    """The albedo at each vertex's UV (nearest texel): what a stock Mitsuba render of the stage's scene shows."""
    albedo = stage.maps.get("albedo")
    if albedo is None:
        return np.full((stage.sequence.num_vertices, 3), 0.5, np.float32)
    side = albedo.shape[0]
    ij = np.clip((stage.sequence.uvs * side).astype(int), 0, side - 1)
    return albedo[ij[:, 1], ij[:, 0]].astype(np.float32)
