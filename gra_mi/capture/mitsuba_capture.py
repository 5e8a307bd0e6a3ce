"""A capture whose rig is a Mitsuba scene (``gra-mi import mitsuba``), into gra-mi's capture layout through the import
every source shares (:func:`gra_mi.capture.importer.import_capture`).

The stage a user describes as a Mitsuba scene — its ``perspective`` sensors the calibrated cameras, its ``point``
emitters the LEDs, the shape ``id="subject"`` the tracked mesh — with the photographs taken on it::

    DIR/scene.xml                                          the stage (or --scene FILE); lengths in metres
    DIR/images/<sensor id>/<frame, 6 digits>.{exr,png,jpg,avif}   the photographs (masked, or with alpha, or masks below)
    DIR/mask/<sensor id>/<frame, 6 digits>.png             optional masks

Each photograph's lighting comes from ``--lighting``, EasyMocap's file (:func:`gra_mi.capture.easymocap.lighting_frames`:
``led`` numbers the scene's point emitters in their order). The scene is read as Mitsuba loads it
(:mod:`gra_mi.capture.scene_stage`): a camera is what its sensor renders, scaled to its photographs' size (same
aspect). Point emitters whose intensities differ state the LEDs' gains (normalised to their mean); equal ones, or all 0,
state none; their mean intensity is the LEDs' (``--led-intensity`` unless given): photographs in the scene's units
(a radiometric calibration, or renders of the scene) give albedos in absolute terms. A static subject (a scene without ``--frame-parameter``) is in every photograph. A moving one: a photograph
shows the mesh frame of its number, or its lighting entry's ``mesh_frame``; mesh frame k loads the scene with the
parameter set to k (zero-padded as its default is), its mesh's triangles the first's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.capture.easymocap import camera_images, lighting_frames
from gra_mi.capture.importer import import_capture
from gra_mi.capture.scene_stage import RawMesh, load_frame, scene_rig, scene_set, subject_shape
from gra_mi.capture.source import ImportConfig, Source
from gra_mi.capture.source_files import CalibCamera, ObjMesh, image_size, write_mask
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.guard import scene_references
from gra_mi.core.io import write_exr
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.scene_file import load_scene_file, scene_parameters, sensor_name, subject_pixels
from gra_mi.render.scene_lights import set_point_lights
from gra_mi.stage.lightstage import Camera
from gra_mi.stage.scene import scene_defaults

logger = logging.getLogger(__name__)


@dataclass(kw_only=True)
class MitsubaOptions:
    """What a capture on a Mitsuba stage needs besides its images and --lighting (:func:`import_mitsuba`)."""

    scene: Path | None = None
    """mitsuba: the stage's scene file (perspective sensors, point-emitter LEDs, the shape id="subject"). Default:
    FOLDER/scene.xml."""
    frame_parameter: str = "frame"
    """mitsuba: the scene parameter that selects the subject's mesh frame (a lighting entry's mesh_frame; e.g. in
    <string name="filename" value="body_$frame.ply"/>)."""


class SceneMeshes:
    """The subject of a scene at each mesh frame, as :class:`~gra_mi.capture.mesh_frames.MeshFrames` gives a file's:
    ``first`` whole, every frame's positions on demand (the scene loaded at that frame, its topology checked)."""

    def __init__(self, path: Path, parameter: str, count: int, moving: bool, rig: tuple):
        self.path, self.parameter, self.count, self.moving, self.rig = path, parameter, count, moving, rig
        default = scene_defaults(path).get(parameter, "")
        self.width = len(default) if default.isdigit() else 0
        if count > 1 and not moving:
            raise GraMiInputError(path, f"the lighting names {count} mesh frames, but the scene has no parameter '{parameter}' to "
                                  "select them (--frame-parameter; e.g. <string name=\"filename\" value=\"body_$frame.ply\"/>)")  # fmt: skip
        self._first, self._last = self._load(0), None
        mesh = self._first
        uvs = mesh.texcoords if mesh.texcoords is not None else np.zeros((0, 2))
        self.first = ObjMesh(mesh.vertices, uvs, mesh.faces, mesh.faces if mesh.texcoords is not None else None)

    def __len__(self) -> int:
        return self.count

    def positions(self, k: int) -> np.ndarray:
        return self._mesh(k).vertices

    def normals(self, k: int) -> np.ndarray | None:
        """Mitsuba's vertex normals of mesh frame ``k`` (its own, or those it computed: angle-weighted, not gra-mi's
        area weighting), so that the capture shades as the scene renders; None where the subject has face normals (gra-mi
        computes smooth ones when it writes the subject)."""
        return self._mesh(k).normals

    def _mesh(self, k: int) -> RawMesh:
        """Mesh frame ``k``, its rig and topology checked; the last one read is kept (positions, then normals)."""
        if k == 0:
            return self._first
        if self._last is None or self._last[0] != k:
            self._last = (k, self._load(k, self._first))
        return self._last[1]

    def _value(self, k: int) -> str:
        return f"{k:0{self.width}d}"

    def _load(self, k: int, first: RawMesh | None = None) -> RawMesh:
        """The calibration is the scene's at its defaults: the rig at every mesh frame is checked against it."""
        defines = {self.parameter: self._value(k)} if self.moving else {}
        return load_frame(self.path, defines, f"{self.parameter}={self._value(k)}", self.rig, "its defaults", first)


def read_mitsuba(folder: Path, options: MitsubaOptions, lighting: Path) -> Source:
    path = options.scene or folder / "scene.xml"
    ensure_mitsuba()
    scene = load_scene_file(path)
    rig = scene_rig(scene, path)
    cameras, leds, intensities, _ = rig
    set_shapes, notes = scene_set(scene, subject_shape(scene, path)[1], (path, {}))
    for note in notes:
        logger.info("%s: %s", path, note)
    names = [c.name for c in cameras]
    images = [camera_images(folder, n) for n in names]
    frame_masks = [camera_images(folder, n, "mask", required=False) for n in names]
    if set_shapes and not all(frame_masks):
        logger.warning("%s: the scene holds shapes besides the subject (%s): where they are in view, the photographs' alpha "
                       "covers them too; give the subject's masks as mask/<sensor id>/<frame>.png", path,
                       ", ".join(shape.label for shape in set_shapes))  # fmt: skip
    calib, sizes = zip(*(_calib(c, found, path) for c, found in zip(cameras, images, strict=True)), strict=True)
    moving = options.frame_parameter in scene_parameters(path)
    frames = lighting_frames(lighting, len(leds), None if moving else 0)  # a static subject: every image shows its one mesh
    meshes = SceneMeshes(path, options.frame_parameter, max(f.mesh_frame for _, f, _ in frames) + 1, moving, rig)
    stated = None if np.ptp(intensities) == 0 else intensities  # equal (or all off): no gains stated
    return Source(
        folder, "mitsuba", path, names, list(calib), list(sizes), images, 1.0, leds, meshes, [None] * len(names), frames,
        mesh_units=1.0, frame_masks=frame_masks, leds_path=path, set_shapes=set_shapes,
        mesh_files=[path, *scene_references(path)], stated_gains=stated, gains_field="point emitters' intensities",
        stated_intensity=float(intensities.mean()) if intensities.max() > 0 else None,
    )  # fmt: skip


def _calib(camera: Camera, images: dict[int, Path], path: Path) -> tuple[CalibCamera, tuple[int, int]]:
    """The sensor as the calibration of its photographs: K over the image width (a film of another size, same aspect,
    scales it exactly), the camera-to-world."""
    width, height = image_size(next(iter(images.values())))
    if abs(width / height - camera.width / camera.height) * height > 1.0:
        raise GraMiInputError(path, f"sensor '{camera.name}' renders {camera.width}x{camera.height}, its photographs are "
                              f"{width}x{height}: another aspect ratio (give the film the photographs' size)")  # fmt: skip
    k = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, camera.width]]) / camera.width
    return CalibCamera(k, camera.camera_to_world[:3, :4].copy(), [0.0] * 5), (width, height)


def import_mitsuba(
    folder: str | Path, out: str | Path, config: ImportConfig, options: MitsubaOptions, lighting: Path, overwrite: bool = False,
    shard=None, estimate_gains=None,
):  # fmt: skip
    config.validate()
    source = read_mitsuba(Path(folder), options, lighting)
    said = {"scene": str(source.calib_path), "frame_parameter": options.frame_parameter}
    return import_capture(source, Path(out), config, said, overwrite, options, shard, estimate_gains)


def write_photographs(scene, folder: Path, number: int, emitted: np.ndarray, integrator, spp: int, seed: int | None = None) -> None:
    """Photographs as ``import mitsuba`` reads them, rendered from a loaded stage: ``scene`` lit by its point emitters
    at ``emitted`` (L, 3) W/sr, every sensor rendered by ``integrator`` at ``spp`` (``seed``, default ``number``) into
    ``folder/images/<sensor id>/<number, 6 digits>.exr`` (RGBA where the film has alpha: the subject's mask, where the
    scene holds the subject alone). With other shapes (a set), whose pixels the alpha covers too, the subject's masks go
    to ``folder/mask/<sensor id>/<number>.png`` (where Mitsuba's sensor rays meet it first). A writer for tests and
    benchmarks of the importer: what a calibrated capture on the stage would hold."""
    import mitsuba as mi

    set_point_lights(scene, emitted)
    for index, sensor in enumerate(scene.sensors()):
        image = np.array(mi.render(scene, sensor=index, integrator=integrator, spp=spp, seed=number if seed is None else seed))
        name = sensor_name(index, sensor, folder)
        write_exr(folder / "images" / name / f"{number:06d}.exr", image)
        if len(scene.shapes()) > 1:
            write_mask(folder / "mask" / name / f"{number:06d}.png", subject_pixels(scene, index))
