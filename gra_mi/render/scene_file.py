"""Any Mitsuba 3 scene file, rendered as Mitsuba's own tool would render it (``gra-mi render SCENE.xml``).

A scene gra-mi did not write is loaded as it is, with ``-D name=value`` parameters checked against the
``<default>`` parameters the file declares, and rendered with its own integrator or one named on the command line
(``direct``, ``path``, or ``gra_onebounce``, whose emitters are checked when the scene loads). Each sensor becomes
``SENSOR.exr`` (linear: RGB or RGBA as the film develops it; with AOVs, every channel named as Mitsuba names them) and ``SENSOR.png``. A lightstage scene (gra-mi's LEDs, rig and
tracked subject) is the special case :class:`gra_mi.stage.scene.LightstageScene` handles.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.guard import path_component
from gra_mi.core.io import atomic_path, write_exr, write_png
from gra_mi.core.limits import require_memory_for
from gra_mi.core.progress import progress
from gra_mi.stage import scene_keys as keys
from gra_mi.stage.scene import make_integrator, mitsuba_load_error, render_in_passes, scene_defaults

logger = logging.getLogger(__name__)
NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
FILM_BYTES_PER_PIXEL = 4 * 4 * 4  # RGBA float32 in the film, its developed image, the NumPy copy and the PNG's


def is_lightstage_scene(path: Path) -> bool:
    """Whether ``path`` declares a gra-mi lightstage's parameters (a subject sequence and a rig calibration)."""
    defaults = scene_defaults(path)
    return keys.PARAM_SUBJECT in defaults and keys.PARAM_CALIBRATION in defaults


def parse_defines(items: list[str]) -> dict[str, str]:
    """``-D name=value`` items as a dict (a name given twice: the last wins, as in Mitsuba's own tool)."""
    defines = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not NAME.match(name):
            raise GraMiParameterError("define", f"expected NAME=VALUE with NAME a scene parameter, got '{item}'")
        defines[name] = value
    return defines


def scene_parameters(path: Path) -> set[str]:
    """The parameters a scene file declares (``<default name=…>``) or uses (``$name``)."""
    return set(scene_defaults(path)) | set(re.findall(r"\$([A-Za-z_][A-Za-z0-9_]*)", path.read_text(errors="replace")))


def check_defines(path: Path, defines: dict[str, str]) -> None:
    """Every ``-D`` parameter must be one the scene declares (``<default name=…>``) or uses (``$name``): a misspelt
    name would otherwise be dropped without a word."""
    declared = scene_parameters(path)
    unknown = sorted(set(defines) - declared)
    if unknown:
        said = ", ".join(sorted(declared)) or "none"
        raise GraMiInputError(path, f"-D {unknown[0]}=…: the scene declares no parameter '{unknown[0]}' (it has: {said})")


def load_scene_file(path: str | Path, defines: dict[str, str] | None = None):
    """``mi.load_file`` with the parameters checked and Mitsuba's errors turned into one line naming the file.
    ``parallel=False``: scenes may use gra-mi's Python plugins."""
    import mitsuba as mi

    path = Path(path)
    if not path.is_file():
        raise GraMiInputError(path, "scene file not found")
    defines = defines or {}
    check_defines(path, defines)
    try:
        return mi.load_file(str(path), parallel=False, **defines)
    except Exception as exc:  # Mitsuba reports parse and plugin errors as RuntimeError with its own location
        raise GraMiInputError(path, mitsuba_load_error(exc)) from None


def sensor_name(index: int, sensor, source: Path | None = None) -> str:
    """The sensor's id (its output files' name), or ``sensorN`` for a sensor without one; an id that is not a plain
    file name (``../x``, ``/abs``) is refused, naming the scene."""
    return path_component(sensor.id() or f"sensor{index}", source, f"sensor {index} id")


def subject_pixels(scene, sensor: int = 0, subject_id: str = keys.SUBJECT_ID) -> np.ndarray:
    """(H, W) bool: the pixels of the scene's ``sensor`` whose centre ray, as Mitsuba's own sensor makes it, meets the
    shape ``subject_id`` before anything else (a scene with a set: the subject's mask, the pixels it is scored on)."""
    import mitsuba as mi

    subject = next(s for s in scene.shapes() if s.id() == subject_id)
    camera = scene.sensors()[sensor]
    w, h = camera.film().crop_size()
    y, x = np.mgrid[0:h, 0:w]
    film = mi.Point2f(((x.ravel() + 0.5) / w).astype(np.float32), ((y.ravel() + 0.5) / h).astype(np.float32))
    ray, _ = camera.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    si = scene.ray_intersect(ray)
    return np.array(si.is_valid() & (si.shape == mi.ShapePtr(subject))).reshape(h, w)


def select_sensors(path: Path, scene, wanted: list[str]) -> list[int]:
    """Indices of the sensors named (by id or index) in ``wanted``; all of them when it is empty."""
    sensors = list(scene.sensors())
    if not sensors:
        raise GraMiInputError(path, "the scene has no sensor to render from")
    names = [sensor_name(i, s, path) for i, s in enumerate(sensors)]
    for i, name in enumerate(names):
        if name in names[:i]:
            raise GraMiInputError(
                path, f"sensors {names.index(name)} and {i} are both named '{name}': their images would overwrite each other"
            )
    if not wanted:
        return list(range(len(sensors)))
    chosen = []
    for item in wanted:
        if item in names:
            chosen.append(names.index(item))
        elif item.isdigit() and int(item) < len(sensors):
            chosen.append(int(item))
        else:
            raise GraMiParameterError("sensor", f"{path} has no sensor '{item}' (its sensors: {', '.join(names)}, or an index)")
    return list(dict.fromkeys(chosen))  # a sensor named twice (by id and by index) is rendered once


@dataclass
class SceneRender:
    sensor: str
    image: np.ndarray  # (H, W, C) linear, as the film develops it
    path: Path  # the EXR


def render_scene_file(
    path: str | Path,
    out: str | Path,
    *,
    sensors: list[str] | None = None,
    integrator: str | None = None,
    spp: int | None = None,
    seed: int = 0,
    defines: dict[str, str] | None = None,
    options: dict | None = None,
) -> list[SceneRender]:
    """Render the named sensors (all by default) of a scene file into ``out/SENSOR.{exr,png}``.

    ``integrator`` None and ``spp`` None: the scene's own (a scene without an integrator: ``path``); ``options``:
    gra_onebounce's sample counts (:data:`gra_mi.render.scene_lights.OPTIONS`; one the scene has nothing for is warned
    about). With
    ``gra_onebounce`` the scene's emitters are checked first (:func:`gra_mi.render.scene_lights.scene_lights`): one
    it cannot compute stops the run by name.
    """
    import mitsuba as mi

    from gra_mi.render.plugins.onebounce import GraOneBounce
    from gra_mi.render.scene_lights import scene_lights

    path, out = Path(path), Path(out)
    scene = load_scene_file(path, defines)
    check_bump_maps(scene, path)
    chosen = select_sensors(path, scene, list(sensors or []))
    for index in chosen:  # a film too large for memory is named before a render allocates it
        width, height = scene.sensors()[index].film().size()
        require_memory_for(path, f"sensor {index} film", float(width) * height * FILM_BYTES_PER_PIXEL, f"a {width} × {height} film")
    chosen_integrator = make_integrator(integrator, onebounce=options)
    if chosen_integrator is None and scene.integrator() is None:
        logger.info("%s has no <integrator>: rendering with Mitsuba's path tracer (--integrator chooses another)", path)
        chosen_integrator = make_integrator("path")
    onebounce = chosen_integrator or scene.integrator()
    if isinstance(onebounce, GraOneBounce):  # refuse what it cannot compute, by name, now
        _warn_unused_counts(path, scene_lights(scene, str(path), onebounce.dome_lights), options or {})
    renders = []
    for index in progress(chosen, description=f"render {path.name}"):
        name = sensor_name(index, scene.sensors()[index], path)
        image, film, channels = render_in_passes(scene, index, chosen_integrator, spp, seed, path, name)
        if len(channels) > 4:  # AOVs: every channel of the film, named and ordered as Mitsuba's own writer does
            with atomic_path(out / f"{name}.exr") as tmp:
                mi.Bitmap(film, channel_names=channels).write(str(tmp))
        else:
            write_exr(out / f"{name}.exr", image)
        write_png(out / f"{name}.png", image[..., :3], exposure=None)
        renders.append(SceneRender(name, image, out / f"{name}.exr"))
    return renders


def check_bump_maps(scene, path: Path) -> None:
    """Refuse, by name, a ``bumpmap`` whose height texture has no gradient (Mitsuba's ``checkerboard`` and
    ``mesh_attribute`` have none): every integrator would stop in the middle of its render with Mitsuba's
    "eval_1_grad(): not implemented". Asked of the texture itself, so a texture that gains one passes."""
    import mitsuba as mi

    from gra_mi.render.scene_lights import object_name, owner_label, scene_objects

    objects = scene_objects(scene)
    for texture, parent in objects.items():
        if not (isinstance(texture, mi.Texture) and isinstance(parent, mi.BSDF) and parent.class_name() == "BumpMap"):
            continue
        try:
            texture.eval_1_grad(mi.SurfaceInteraction3f())
        except RuntimeError:
            raise GraMiInputError(path, f"{owner_label(parent, objects)} has a bumpmap{object_name(parent)} over a "
                                  f"{texture.class_name()} texture{object_name(texture)}, which has no gradient (a bumpmap "
                                  "needs one): give it a bitmap height texture") from None  # fmt: skip


def _warn_unused_counts(path: Path, lights, options: dict) -> None:
    """Say which of the sample counts asked for the scene has nothing to spend on (they change nothing there)."""
    sampled = {"dome_lights": (lights.environments, "environment emitter"), "area_samples": (lights.areas, "area light"),
               "bsdf_samples": (lights.areas, "area light")}  # fmt: skip
    for name in options:
        emitters, kind = sampled[name]
        if not emitters:
            logger.warning("%s has no %s that emits: --%s changes nothing", path, kind, name.replace("_", "-"))
