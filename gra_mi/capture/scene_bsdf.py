"""A set shape's own BSDF, carried from the user's scene file into the stage's ``scene.xml`` (``from-scene``, ``import
mitsuba``): Mitsuba cannot write a loaded BSDF back as XML, so the shape's element is taken from the file as the user
wrote it. A shape is found there by its id, or, without one, as the one id-less shape of the file that loads alone as
the same kind of shape in the same place. Its ``<ref>``s are inlined, its ``$names`` replaced by the file's
``<default>``s and the command's ``--define``s, and the files it reads (textures) found as Mitsuba finds them (beside
the scene file, or in its ``<path>`` folders), to be copied beside the stage. The files the scene ``<include>``s are
read in their places, as Mitsuba reads them. What
cannot be carried (id-less twins in one place with different BSDFs, a file that is missing) is said, and a diffuse
stand-in takes its place (:func:`gra_mi.capture.set_albedo.set_material`).
"""

from __future__ import annotations

import copy
import functools
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MAX_REF_DEPTH = 16  # <ref>s inside <ref>s: deeper is a cycle
MAX_INCLUDE_DEPTH = 15  # Mitsuba's own limit on <include>s inside included files
NOT_FOUND = "its element is not in the scene file or the files it includes"


@dataclass
class CarriedBSDF:
    """A BSDF element ready for the stage's scene.xml, and the files it reads (each written as ``set/<name>``)."""

    element: ET.Element
    files: dict[str, Path] = field(default_factory=dict)  # the name in the stage's set folder → the user's file

    def xml(self, where=None) -> str:
        """The element, each file named ``where(name)`` (a path relative to scene.xml; default: the user's own file)."""
        element = copy.deepcopy(self.element)
        for node in element.iter():
            if node.get("name") == "filename" and node.get("value") in self.files:
                node.set("value", str(where(node.get("value")) if where else self.files[node.get("value")]))
        return ET.tostring(element, encoding="unicode")

    def loads(self) -> str | None:
        """None where Mitsuba loads the element as it is; otherwise its error."""
        import mitsuba as mi

        element = ET.fromstring(self.xml())
        element.set("version", "3.0.0")
        try:
            mi.load_string(ET.tostring(element, encoding="unicode"))
        except Exception as error:  # Mitsuba raises RuntimeError, and others from its plugins
            return f"Mitsuba could not load it alone: {str(error).splitlines()[-1][:200]}"
        return None


def carried_bsdf(scene_file: Path, shape, defines: dict[str, str]) -> CarriedBSDF | str | None:
    """The BSDF the user's ``scene_file`` gives ``shape`` (a loaded Mitsuba shape, or the id of one); None where it
    gives none (Mitsuba's default diffuse, which the stand-in is exactly); otherwise why it cannot be carried."""
    try:
        stat = Path(scene_file).stat()
        key = (Path(scene_file).resolve(), stat.st_mtime_ns, stat.st_size, tuple(sorted(defines.items())))
        root, by_id, defaults, search = _read(key)
    except (OSError, ET.ParseError, ValueError) as error:
        return f"its scene file could not be read again ({error})"
    try:
        element = _shape_element(key, root, by_id, shape)
        bsdf = _own_bsdf(element, by_id)
        element = None if bsdf is None else _inlined(bsdf, by_id, 0)
    except ValueError as error:
        return str(error)
    if element is None:
        return None
    files: dict[str, Path] = {}
    for node in element.iter():
        node.attrib.pop("id", None)  # (two shapes may share it: ids must stay unique in scene.xml)
        for key, value in node.attrib.items():
            node.set(key, _substituted(value, defaults))
        unknown = re.findall(r"[$]\w+", "".join(node.attrib.values()))
        if unknown:
            return f"it uses a parameter without a default ({', '.join(unknown)})"
        if node.get("name") == "filename" and node.get("value"):
            found = _found(search, node.get("value"))
            if found is None:
                return f"it reads {node.get('value')}, which is not found beside the scene file or in its <path>s"
            name = f"{len(files):03d}_{found.name}"
            files[name] = found
            node.set("value", name)
    carried = CarriedBSDF(element, files)
    return carried.loads() or carried


def _read(key: tuple) -> tuple[ET.Element, dict[str, ET.Element], dict[str, str], tuple[Path, ...]]:
    """:func:`_parsed`, parsed again where a file it includes has changed since."""
    parsed = _parsed(*key)
    if any(_stat(path) != stat for path, stat in parsed[4].items()):
        _parsed.cache_clear()
        _id_less_places.cache_clear()
        parsed = _parsed(*key)
    return parsed[:4]


@functools.lru_cache(maxsize=4)
def _parsed(path: Path, mtime_ns: int, size: int, defines: tuple) -> tuple:
    """The scene file's elements with its ``<include>``s in their places, its objects by id, its parameters (the first
    ``<default>`` of each name, the command's ``--define``s over them), the folders its files are searched in (its
    ``<path>``s, the last first, then its own folder) and the included files' stats; parsed once for all its set
    shapes (never changed here: :func:`_inlined` copies what it takes)."""
    root = _upgraded(ET.parse(path).getroot())
    reading = _Reading(_defaults(root, dict(defines)), [path.parent], {})
    _expand(root, path, reading, 0)
    defaults = _defaults(root, dict(defines))  # (an included file's <default>s too)
    by_id = {node.get("id"): node for node in root.iter() if node.get("id") and node.tag != "ref"}
    return root, by_id, defaults, tuple(reading.search), reading.included


def _defaults(root: ET.Element, defines: dict[str, str]) -> dict[str, str]:
    found: dict[str, str] = {}
    for node in root.iter("default"):
        found.setdefault(node.get("name"), node.get("value", ""))  # (Mitsuba keeps the first)
    return found | defines


@dataclass
class _Reading:
    """What reading a scene file in Mitsuba's order gathers: its parameters, its file resolver's folders (searched in
    order) and the files it includes (their stats)."""

    defaults: dict[str, str]
    search: list[Path]
    included: dict[Path, tuple]


def _expand(node: ET.Element, file: Path, reading: _Reading, depth: int) -> None:
    """``node``'s elements in ``file``, in order, as Mitsuba's parser meets them: a ``<path>`` puts its folder first in
    the resolver (found beside ``file``, else through the resolver); an ``<include>``'s file (found through the
    resolver) takes its place, a ``<scene>``'s elements (another root element itself), in that file's own version's
    names."""
    children: list[ET.Element] = []
    for child in list(node):
        if child.tag == "path":
            value = _substituted(child.get("value", ""), reading.defaults)
            beside = file.parent / value
            folder = beside if beside.is_dir() else _found(reading.search, value, folder=True)
            if folder is None:
                raise ValueError(f"its <path> {value} is not a folder beside its file or in its other <path>s")
            reading.search.insert(0, folder.resolve())
        if child.tag != "include":
            _expand(child, file, reading, depth)
            children.append(child)
            continue
        if depth >= MAX_INCLUDE_DEPTH:
            raise ValueError(f"its <include>s nest deeper than {MAX_INCLUDE_DEPTH} files (one includes itself?)")
        name = _substituted(child.get("filename", ""), reading.defaults)
        found = _found(reading.search, name)
        if found is None:
            raise ValueError(f"it includes {name}, which is not found beside the scene file or in its <path>s")
        reading.included[found] = _stat(found)
        root = _upgraded(ET.parse(found).getroot())
        _expand(root, found, reading, depth + 1)
        children += list(root) if root.tag == "scene" else [root]
    node[:] = children


def _stat(path: Path) -> tuple[int, int]:
    stat = path.stat()
    return stat.st_mtime_ns, stat.st_size


def _upgraded(root: ET.Element) -> ET.Element:
    """A file of Mitsuba 0.x (``version`` before 2.0.0) in the names of the stage's 3.0.0, as Mitsuba upgrades it when
    it loads one: parameters in snake_case (``intIOR`` → ``int_ior``; a ``<default>``'s name is the file's own), and
    ``<lookAt>`` as ``<lookat>``."""
    version = tuple(int(v) if v.isdigit() else 0 for v in root.get("version", "3.0.0").split("."))
    if version >= (2, 0, 0):
        return root
    for node in root.iter():
        if node.tag == "lookAt":
            node.tag = "lookat"
        if node.get("name") and node.tag != "default":
            node.set("name", re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "_", node.get("name")).lower())
    return root


def _shape_element(key: tuple, root: ET.Element, by_id: dict, shape) -> ET.Element:
    """The element of ``shape`` in the file: by its id; without one, the file's one id-less top-level shape (not one of a
    shapegroup) that loads alone as the same kind of shape with the same bounds. Id-less twins (the same kind, the same
    place) do, where their BSDFs are written alike."""
    shape_id = shape if isinstance(shape, str) else shape.id()
    if shape_id:
        found = [s for s in root.iter("shape") if s.get("id") == shape_id]
        if len(found) != 1:
            raise ValueError(NOT_FOUND)
        return found[0]
    seen = (shape.class_name(), *shape.bbox().min, *shape.bbox().max)
    twins = [s for s, placed in _id_less_places(*key) if _same_place(placed, seen)]
    if not twins:
        raise ValueError(NOT_FOUND)
    written = {ET.tostring(_inlined(b, by_id, 0)) if (b := _own_bsdf(s, by_id)) is not None else b"" for s in twins}
    if len(written) > 1:
        raise ValueError(f"{len(twins)} shapes without an id in the scene file are of its kind in its place, with "
                         "different BSDFs: give each an id")  # fmt: skip
    return twins[0]


@functools.lru_cache(maxsize=4)
def _id_less_places(path: Path, mtime_ns: int, size: int, defines: tuple) -> list[tuple[ET.Element, tuple | None]]:
    """Each id-less top-level shape element of the file (its includes' too), and where it is (:func:`_placed`): loaded
    once per file."""
    root, _, defaults, search, _ = _parsed(path, mtime_ns, size, defines)
    return [(s, _placed(s, search, defaults)) for s in root.findall("shape") if not s.get("id")]


def _placed(element: ET.Element, search: tuple[Path, ...], defaults: dict) -> tuple | None:
    """(class name, bounds) of the shape ``element`` loaded alone (its own parameters, no BSDF); None where it does not
    load so."""
    import mitsuba as mi

    alone = ET.Element("shape", dict(element.attrib))
    for child in element:
        if child.tag not in ("bsdf", "ref", "emitter", "medium", "texture"):
            alone.append(copy.deepcopy(child))
    for node in alone.iter():
        for key, value in node.attrib.items():
            node.set(key, _substituted(value, defaults))
        if node.get("name") == "filename" and node.get("value"):
            node.set("value", str(_found(search, node.get("value")) or node.get("value")))
    try:
        loaded = mi.load_string(f'<scene version="3.0.0">{ET.tostring(alone, encoding="unicode")}</scene>').shapes()[0]
    except Exception:  # Mitsuba raises RuntimeError, and others from its plugins: this element is not the shape
        return None
    return (loaded.class_name(), *loaded.bbox().min, *loaded.bbox().max)


def _same_place(placed: tuple | None, seen: tuple) -> bool:
    if placed is None or placed[0] != seen[0]:
        return False
    a, b = np.array(placed[1:], np.float64), np.array(seen[1:], np.float64)
    return bool(np.allclose(a, b, rtol=1e-5, atol=1e-5 * max(1.0, float(np.abs(b).max()))))


def _own_bsdf(shape: ET.Element, by_id: dict[str, ET.Element]) -> ET.Element | None:
    """The shape's ``<bsdf>`` child, or the ``<bsdf>`` its ``<ref>`` names; None: it has none."""
    for child in shape:
        target = by_id.get(child.get("id", "")) if child.tag == "ref" else child
        if target is None:
            raise ValueError(f"it refers to '{child.get('id')}', which the scene file does not define")
        if target.tag == "bsdf":
            return target
    return None


def _inlined(node: ET.Element, by_id: dict[str, ET.Element], depth: int) -> ET.Element:
    """A copy of ``node`` with every ``<ref id=…>`` inside it replaced by a copy of the object it names (its ``name``
    kept)."""
    if depth > MAX_REF_DEPTH:
        raise ValueError("its <ref>s refer to each other in a cycle")
    out = ET.Element(node.tag, dict(node.attrib))
    for child in node:
        if child.tag == "ref":
            target = by_id.get(child.get("id", ""))
            if target is None:
                raise ValueError(f"it refers to '{child.get('id')}', which the scene file does not define")
            inlined = _inlined(target, by_id, depth + 1)
            if child.get("name"):
                inlined.set("name", child.get("name"))
            out.append(inlined)
        else:
            out.append(_inlined(child, by_id, depth))
    return out


def _substituted(value: str, defaults: dict[str, str]) -> str:
    for name in sorted(defaults, key=len, reverse=True):  # ($frame before $f)
        value = value.replace(f"${name}", defaults[name])
    return value


def _found(search: tuple[Path, ...] | list[Path], value: str, folder: bool = False) -> Path | None:
    """A file (or ``folder``) a scene names, as Mitsuba's file resolver finds it: as given where absolute, else in the
    first of the ``search`` folders that holds it."""
    exists = Path.is_dir if folder else Path.is_file
    candidates = [Path(value)] if Path(value).is_absolute() else [base / value for base in search]
    return next((c.resolve() for c in candidates if exists(c)), None)
