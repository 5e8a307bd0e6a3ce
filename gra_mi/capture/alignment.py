"""A calibration moved into the LEDs' frame by where some of its cameras are known to be there (``--align-cameras``).

A rig calibrated on its own (COLMAP's reconstruction frame, EasyMocap's chessboard, a transforms.json from either) is
in a frame of its own, at a scale of its own; the LEDs and the mesh are in the stage's. Given the stage positions of
at least three of the cameras (not on one line), the similarity (scale, rotation, translation) that puts the
calibration's camera centres nearest them in the least-squares sense (Umeyama 1991, as COLMAP's ``model_aligner``
fits it) moves every camera there. The file is COLMAP's ``--ref_images_path``: a line ``NAME X Y Z`` per camera, ``#``
comments; NAME is a camera's name, or an image path whose folder (else whose stem) is one (COLMAP's image names).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from gra_mi.capture.source_files import image_camera
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_text
from gra_mi.core.schema import Record, matrix, parse

ALIGN_MAX_SHARE = 0.02  # a camera this far (a share of the known cameras' extent) from its stated place: refused
ON_ONE_LINE = 0.05  # placed cameras whose second principal extent is below this share of the first are nearly in a line:
# the turn about it is as uncertain as their places over that small extent (3 neighbours on a ring of 40: 8° per 3 mm)


class CameraPlace(Record):
    """One line of the file: a camera's name and where it is in the LEDs' frame."""

    name: str
    position: matrix(3)


def read_places(path: Path) -> list[CameraPlace]:
    """The file's lines (``NAME X Y Z``; the name may hold spaces, as COLMAP's image names may), each name once."""
    places: dict[str, CameraPlace] = {}
    for number, line in enumerate(read_text(path, "lines 'NAME X Y Z' (COLMAP's ref_images)").splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.strip().rsplit(maxsplit=3)
        if len(fields) < 4:
            raise GraMiInputError(path, "expected NAME X Y Z", field=f"line {number}")
        place = parse(CameraPlace, {"name": fields[0], "position": fields[1:]}, path, line=number)
        if place.name in places:
            raise GraMiInputError(path, f"{place.name!r} is placed twice", field=f"line {number}")
        places[place.name] = place
    return list(places.values())


def camera_named(path: Path, name: str, cameras: list[str], aliases: dict[str, str] | None = None) -> str:
    """The camera a line names: a camera's name, or another name the source gives it (``aliases``: EasyMocap's own
    camera names, transforms.json's image paths), or an image path whose folder, else whose stem, is one of those."""
    known = {camera: camera for camera in cameras} | (aliases or {})
    for candidate in (name, *image_camera(name)):
        if candidate in known:
            return known[candidate]
    shown = ", ".join(cameras[:6]) + (" …" if len(cameras) > 6 else "")
    raise GraMiInputError(path, f"{name!r} names no camera of the calibration (its cameras: {shown})", field=name)


def similarity(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(s, R, t) minimising Σ |s R source + t − target|² over rotations R (Umeyama 1991; det R = +1)."""
    mean_s, mean_t = source.mean(axis=0), target.mean(axis=0)
    a, b = source - mean_s, target - mean_t
    u, sigma, vt = np.linalg.svd(b.T @ a / len(a))
    flip = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt)) or 1.0])
    rotation = u @ flip @ vt
    scale = float(np.trace(np.diag(sigma) @ flip) / (a**2).sum(axis=1).mean())
    return scale, rotation, mean_t - scale * rotation @ mean_s


def _spread(path: Path, points: np.ndarray, what: str) -> float:
    """The diagonal of the points' bounding box; refused where they are fewer than 3 or on one line."""
    extents = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) if len(points) >= 3 else np.zeros(2)
    if len(points) < 3 or not extents[1] > ON_ONE_LINE * extents[0]:
        raise GraMiInputError(
            path, f"{what} are {len(points)}, in a line or nearly: place 3 cameras or more, spread over the rig, not along a line"
        )
    return float(np.linalg.norm(np.ptp(points, axis=0)))


def align_cameras(path: Path, names: list[str], calib: list, aliases: dict[str, str] | None = None) -> tuple[list, tuple, dict]:
    """Each CalibCamera of ``calib`` (camera-to-world, OpenCV axes) moved by the similarity that puts the named cameras'
    centres at their places in ``path`` (names as :func:`camera_named` reads them), that similarity (scale, rotation,
    translation) and what the import report says of it."""
    places = read_places(path)
    index = {}
    for place in places:
        camera = camera_named(path, place.name, names, aliases)
        if camera in index:
            raise GraMiInputError(path, f"{place.name!r} and {index[camera][0]!r} both place camera {camera}", field=place.name)
        index[camera] = (place.name, place.position)
    known = sorted(index)
    centres = np.array([calib[names.index(c)].extrinsic[:, 3] for c in known])
    target = np.array([index[c][1] for c in known])
    extent = _spread(path, target, "the cameras placed")
    _spread(path, centres, "the placed cameras' calibrated centres")
    scale, rotation, shift = similarity(centres, target)
    off = np.linalg.norm(centres @ (scale * rotation).T + shift - target, axis=1)
    if off.max() > ALIGN_MAX_SHARE * extent:
        worst = int(np.argmax(off))
        raise GraMiInputError(path, f"camera {known[worst]} lands {off[worst]:.4g} from where {index[known[worst]][0]!r} places it "
                              f"({100 * off[worst] / extent:.1f} % of the cameras' extent; at most {100 * ALIGN_MAX_SHARE:g} %): "
                              "a camera named for another, or a place mis-measured?", field=index[known[worst]][0])  # fmt: skip
    moved = [replace(c, extrinsic=np.column_stack([rotation @ c.extrinsic[:, :3], scale * rotation @ c.extrinsic[:, 3] + shift]))
             for c in calib]  # fmt: skip
    turned = float(np.degrees(np.arccos(np.clip((np.trace(rotation) - 1) / 2, -1.0, 1.0))))
    return moved, (scale, rotation, shift), {"file": str(path), "cameras": known, "scale": scale, "rotation_deg": turned, "translation": shift.tolist(),
            "rms": float(np.sqrt(np.mean(off**2))), "max": float(off.max())}  # fmt: skip


def aligned(options, names: list[str], calib: list, aliases: dict[str, str]) -> tuple[list, dict]:
    """The cameras moved into the LEDs' frame where ``options`` (a rig's TransformsOptions) --align-cameras places some
    of them (:func:`align_cameras`; ``aliases``: the source's other names of its cameras), and the Source fields that
    say it: the alignment, and the meshes' move where they are in the calibration's frame (--mesh-frame calibration)."""
    if options.align_cameras is None:
        return calib, {}
    moved, move, said = align_cameras(Path(options.align_cameras), names, calib, aliases)
    with_mesh = options.mesh_frame == "calibration"
    return moved, {"alignment": said | {"mesh_moved": with_mesh}, "alignment_move": move}
