"""Which of a Mitsuba scene's emitters gra-mi's one-bounce integrator computes, how, and which it refuses by name.

A light that reaches a point from one position or one direction (a *delta* light: ``point``, ``spot``,
``projector``, ``directional``) is computed exactly with one shadow ray: its emitter's own ``sample_direction`` gives
the incident radiance. An environment (``envmap``, ``constant``, ``sunsky``) is computed as a lightstage computes
one: a dome of far-field lights, each carrying its cell of the sphere (:mod:`gra_mi.render.dome`). An ``area`` light
is sampled on its surface as Mitsuba's ``direct`` samples it (noise that falls with samples, no bias): the
``area_samples`` points per pixel sample are shared among the area lights in proportion to their weights
(:func:`area_weights`: power × Mitsuba's ``sampling_weight``), at least one each. A ``directionalarea`` light cannot
be reached from a point (its light leaves its surface in one direction); rather than render it black, gra-mi refuses
the scene when it is loaded, naming the emitter and what to use instead; so it does a participating medium
(:func:`refuse_volumes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.render.dome import DEFAULT_LIGHTS, LIGHTS_RANGE, cell_light, light_directions

# Mitsuba class name → the plugin name a scene file uses.
PLUGIN_NAMES = {
    "PointLight": "point",
    "SpotLight": "spot",
    "Projector": "projector",
    "DirectionalEmitter": "directional",
    "AreaLight": "area",
    "EnvironmentMapEmitter": "envmap",
    "ConstantBackgroundEmitter": "constant",
    "SunskyEmitter": "sunsky",
    "DirectionalArea": "directionalarea",
}
EXACT = ("point", "spot", "projector", "directional")
DOME = ("envmap", "constant", "sunsky")  # environments integrated onto a dome of far-field lights
SAMPLED = ("area",)  # sampled on their surface
OTHER_INTEGRATORS = "Mitsuba's own integrators (`gra-mi render SCENE --integrator direct` or `path`)"
ADVICE = {  # Mitsuba's direct and path render a directionalarea light black, as gra_onebounce would
    "directionalarea": "its light leaves its surface in one direction, so no shading point can sample it and only a light "
    'tracer reaches it: give the scene <integrator type="ptracer"/> and render it with its own integrator, or stand a '
    "directional emitter in for it",
}
DEFAULT_AREA_SAMPLES = 16
DEFAULT_BSDF_SAMPLES = 4
OPTIONS = {
    "dome_lights": (LIGHTS_RANGE, DEFAULT_LIGHTS),
    "area_samples": ((1, 4096), DEFAULT_AREA_SAMPLES),
    "bsdf_samples": ((0, 4096), DEFAULT_BSDF_SAMPLES),
}
"""gra_onebounce's sample counts: (range, default). ``area_samples``: points per pixel sample on the area lights
(shared among them by :func:`area_weights`, at least one each); ``bsdf_samples``: directions drawn from the BSDF per
pixel sample that may reach an area light."""
POWER_POINTS = 256  # points per area light over which its mean radiance is estimated


def checked_option(name: str, value, flag: str | None = None) -> int:
    """``value`` of one of :data:`OPTIONS`, refused (named ``flag`` or ``name``) unless an integer in its range."""
    (low, high), _ = OPTIONS[name]
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise GraMiParameterError(flag or name, f"expected an integer in [{low}, {high}], got {value!r}")
    return value


def plugin_name(emitter) -> str:
    return PLUGIN_NAMES.get(emitter.class_name(), emitter.class_name())


def emitter_label(index: int, emitter) -> str:
    """How an error names an emitter: its id, its type, and its place among the scene's emitters."""
    name = emitter.id()
    shape = emitter.get_shape() if plugin_name(emitter) in ("area", "directionalarea") else None
    where = f" on shape '{shape.id()}'" if shape is not None and shape.id() else ""
    return (f"emitter '{name}'" if name else f"emitter #{index}") + where


@dataclass
class SceneLights:
    """The scene's delta lights: point emitters (the LEDs of a lightstage: one array, one loop) and the others; its
    environments as one dome of far-field lights; its area lights that are on."""

    points: list
    others: list
    positions: np.ndarray  # (P, 3) of the point emitters
    intensities: np.ndarray  # (P, 3) W/sr
    dome_directions: np.ndarray  # (D, 3) unit vectors towards each dome light (its cell's mean light direction)
    dome_irradiance: np.ndarray  # (D, 3) W/m² of each; zeros without an environment
    environments: list
    areas: list
    area_weights: np.ndarray  # (A,) > 0: each area light's share of the points (:func:`area_weights`)
    objects: dict  # every object of the scene's graph → its parent (:func:`scene_objects`), walked once

    @property
    def count(self) -> int:
        return len(self.points) + len(self.others) + len(self.environments) + len(self.areas)


def point_lights(emitters: list) -> tuple[np.ndarray, np.ndarray]:
    """Positions (P, 3) and radiant intensities (P, 3) of point emitters, in order."""
    import drjit as dr
    import mitsuba as mi

    if not emitters:
        return np.zeros((0, 3)), np.zeros((0, 3))
    n = len(emitters)
    # Vectorised calls over all LEDs: a point light's sample_direction gives its position, then, seen from 1 m
    # beside it, I / 1² (its intensity).
    lights = mi.EmitterPtr(emitters)
    ds, _ = lights.sample_direction(dr.zeros(mi.Interaction3f, n), dr.full(mi.Point2f, 0.5, n), True)
    positions = np.array(ds.p, dtype=np.float64).T.reshape(n, 3)
    beside = dr.zeros(mi.Interaction3f, n)
    beside.p = ds.p + mi.Vector3f(1.0, 0.0, 0.0)
    _, weight = lights.sample_direction(beside, dr.full(mi.Point2f, 0.5, n), True)
    intensities = np.array(weight, dtype=np.float64).T.reshape(n, 3)
    return positions, intensities


def set_point_lights(scene, intensities: np.ndarray) -> None:
    """Drive a scene's point emitters (``scene.emitters()``'s order, as :func:`point_lights` reads them) at
    ``intensities`` (P, 3) W/sr, each sampled in proportion to its power: a path tracer picks an OLAT's one lit LED,
    not the dark ones."""
    import mitsuba as mi

    from gra_mi.stage.scene import led_sampling_weights

    params = mi.traverse(scene)
    owner = {
        id(params.properties[key][2]): key[: -len("sampling_weight")] for key in params.keys() if key.split(".")[-1] == "sampling_weight"
    }
    emitters = list(scene.emitters())
    if others := [emitter_label(i, e) for i, e in enumerate(emitters) if plugin_name(e) != "point"]:
        raise GraMiParameterError("scene", f"only point emitters are driven; {others[0]} is not one")
    if len(emitters) != len(intensities):
        raise GraMiParameterError("intensities", f"expected one per point emitter of the scene, got {len(intensities)} for {len(emitters)}")
    for emitter, value, weight in zip(emitters, intensities, led_sampling_weights(intensities), strict=True):
        prefix = owner[id(emitter)]
        params[prefix + "intensity.value"] = mi.Color3f(*(float(x) for x in value))
        params[prefix + "sampling_weight"] = float(weight)
    params.update()


def scene_lights(scene, source: str | None = None, dome_lights: int = DEFAULT_LIGHTS) -> SceneLights:
    """Classify and check the emitters of a loaded scene; ``source`` names the scene file in errors; environments are
    integrated onto a dome of ``dome_lights`` lights.

    Refuses (:class:`GraMiInputError`, naming the emitter): a scene with no emitter, an emitter gra-mi cannot compute,
    a negative or non-finite intensity or radiance, a spot cone outside (0°, 180°); and a participating medium
    (:func:`refuse_volumes`). Area lights that emit nothing are left out (no samples spent on them).
    """
    import mitsuba as mi

    objects = scene_objects(scene)
    refuse_volumes(objects, source)
    emitters = list(scene.emitters())
    if not emitters:
        raise GraMiInputError(source or "scene", "the scene has no emitter, so every render would be black: add a point, spot or "
                              "directional emitter, or an envmap")  # fmt: skip
    points, others, point_index, environments, areas = [], [], [], [], []
    dome, moments = np.zeros((dome_lights, 3)), np.zeros((dome_lights, 3))
    for index, emitter in enumerate(emitters):
        kind, label = plugin_name(emitter), emitter_label(index, emitter)
        if kind in DOME:
            irradiance, moment = _environment(emitter, label, dome_lights, source)
            dome, moments = dome + irradiance, moments + moment
            environments.append(emitter)
            continue
        if kind not in EXACT + SAMPLED:
            raise GraMiInputError(
                source or "scene", f"{label} is of type '{kind}', which gra_onebounce does not compute (it computes "
                f"{', '.join(EXACT)} lights exactly, {', '.join(DOME)} environments on a dome of lights and "
                f"{', '.join(SAMPLED)} lights by sampling their surface): {_advice(kind)}"
            )  # fmt: skip
        if kind == "point":  # hundreds on a lightstage: read and checked at once below
            points.append(emitter)
            point_index.append(index)
        elif _check_values(mi.traverse(emitter), label, kind, source):
            (areas if kind in SAMPLED else others).append(_checked_weight(emitter, label, source) if kind in SAMPLED else emitter)
    positions, intensities = point_lights(points)
    bad = np.flatnonzero(~np.all(np.isfinite(intensities) & (intensities >= 0), axis=1))
    if bad.size:
        k = int(bad[0])
        raise GraMiInputError(source or "scene", f"{emitter_label(point_index[k], points[k])} (point): 'intensity' must be finite and "
                              f">= 0, got {np.round(intensities[k], 6).tolist()} ({bad.size} such point lights)")  # fmt: skip
    directions = light_directions(moments)
    return SceneLights(points, others, positions, intensities, directions, dome, environments, areas, area_weights(areas), objects)


def area_weights(emitters: list) -> np.ndarray:
    """Each area light's weight in sharing gra_onebounce's points: its power (mean radiance over a lattice of points on
    its surface × its area) times its Mitsuba ``sampling_weight`` (raise it for a dim light close to the subject,
    whose power alone undersells its light there)."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.lattice import lattice_point

    if not emitters:
        return np.zeros(0)
    points = lattice_point(dr.arange(mi.Float, POWER_POINTS), POWER_POINTS)
    radiances = []
    for emitter in emitters:  # each its own shape (a call through a pointer array would trace every shape, groups too)
        where = mi.SurfaceInteraction3f(emitter.get_shape().sample_position(0.0, points), dr.zeros(mi.Color0f))
        where.wi = mi.Vector3f(0.0, 0.0, 1.0)  # seen from the front
        radiances.append(dr.mean(emitter.eval(where), axis=None))
    dr.eval(radiances)
    radiance = np.array([r[0] for r in radiances], dtype=np.float64)
    power = radiance * np.array([e.get_shape().surface_area()[0] for e in emitters], dtype=np.float64)
    return power * np.array([e.sampling_weight() for e in emitters], dtype=np.float64)


def _checked_weight(emitter, label: str, source: str | None):
    """The area light, refused unless its ``sampling_weight`` is finite and > 0 (0 would leave it unsampled)."""
    weight = emitter.sampling_weight()
    if not (np.isfinite(weight) and weight > 0):
        raise GraMiInputError(source or "scene", f"{label} (area): 'sampling_weight' must be finite and > 0 (gra_onebounce shares "
                              f"its points among area lights in proportion to power × sampling_weight), got {weight:g}")  # fmt: skip
    return emitter


def scene_objects(scene) -> dict:
    """Every object of the scene's graph (shapes inside shape groups, nested materials, media) → its parent."""
    import mitsuba as mi

    return {node: parent for node, (parent, _) in mi.traverse(scene).hierarchy.items()}


def owner_label(node, parents: dict) -> str:
    """The shape, sensor or emitter ``node`` belongs to (itself, or the nearest above it), as an error names it."""
    import mitsuba as mi

    while node is not None and not isinstance(node, (mi.Shape, mi.Sensor, mi.Emitter)):
        node = parents.get(node)
    kind = {mi.Shape: "shape", mi.Sensor: "sensor", mi.Emitter: "emitter"}
    found = next((name for cls, name in kind.items() if isinstance(node, cls)), None)
    if found is None:
        return "the scene"
    return f"{found} '{node.id()}'" if node.id() else f"a {found} without an id ({node.class_name()})"


def object_name(node) -> str:
    """`` 'ID'`` of a scene object, or nothing where it has no id (for a sentence that already says its type)."""
    return f" '{node.id()}'" if node.id() else ""


def refuse_volumes(parents: dict, source: str | None = None) -> None:
    """Refuse, by name, a participating medium (a shape's interior or exterior, a sensor's, an emitter's; inside shape
    groups too), which gra_onebounce (a surface integrator, as Mitsuba's ``direct`` and ``path``) would render as if it
    were not there; Mitsuba's ``volpath`` computes media. ``parents``: the scene's :func:`scene_objects`."""
    import mitsuba as mi

    for node in parents:
        if isinstance(node, mi.Medium):
            raise GraMiInputError(source or "scene", f"{owner_label(node, parents)} has a participating medium "
                                  f"'{node.id()}' ({node.class_name()}), which gra_onebounce does not compute (it shades "
                                  'surfaces): give the scene <integrator type="volpath"/> and render it with its own '
                                  "integrator, or remove the medium")  # fmt: skip


def _environment(emitter, label: str, count: int, source: str | None) -> tuple[np.ndarray, np.ndarray]:
    """The emitter's light on the dome's cells (:func:`~gra_mi.render.dome.cell_light`), refused if any is negative or
    not finite."""
    irradiance, moment = cell_light(emitter, count)
    if not np.all(np.isfinite(irradiance)) or np.any(irradiance < 0):
        bad = int(np.sum(~np.all(np.isfinite(irradiance) & (irradiance >= 0), axis=1)))
        raise GraMiInputError(source or "scene", f"{label} ({plugin_name(emitter)}): its radiance must be finite and >= 0, "
                              f"but {bad} of {count} directions' cells are not (NaN, Inf or negative pixels?)")  # fmt: skip
    return irradiance, moment


def _advice(kind: str) -> str:
    return ADVICE.get(kind, f"gra-mi cannot compute it: use {OTHER_INTEGRATORS}")


def _check_values(params, label: str, kind: str, source: str | None) -> bool:
    """Refuse a negative or non-finite intensity, irradiance or radiance (a constant or a bitmap's pixels) or a bad spot
    cone; False for a light whose every such value is 0 (it is off)."""
    values = []
    for key in params.keys():
        if key.startswith(("intensity", "irradiance", "radiance")) and key.endswith((".value", ".data")):
            value = np.asarray(params[key], np.float64)
            values.append(value)
            if not np.all(np.isfinite(value)) or np.any(value < 0):
                bad = value[~(np.isfinite(value) & (value >= 0))]
                raise GraMiInputError(source or "scene", f"{label} ({kind}): '{key.split('.')[0]}' must be finite and >= 0, got "
                                      f"{np.round(bad.ravel()[:6], 6).tolist()} ({bad.size} such values)")  # fmt: skip
    if kind == "spot":
        cutoff, beam = float(np.ravel(params["cutoff_angle"])[0]), float(np.ravel(params["beam_width"])[0])
        if not 0 < cutoff < 180:
            raise GraMiInputError(source or "scene", f"{label} (spot): cutoff_angle must lie in (0°, 180°), got {cutoff:g}°")
        if not 0 <= beam <= cutoff:
            raise GraMiInputError(
                source or "scene", f"{label} (spot): beam_width must lie in [0°, cutoff_angle = {cutoff:g}°], got {beam:g}°"
            )
    return not values or any(np.any(v > 0) for v in values)
