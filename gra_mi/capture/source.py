"""What an import reads, as one record whatever the source format: :class:`Source` (filled by each format's reader,
checked by :meth:`Source.check` before anything is written) and the options every import shares
(:class:`ImportConfig`). One floor below the import that drives them (:mod:`gra_mi.capture.importer`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.lens import held_fraction
from gra_mi.capture.mesh_frames import MeshFrames
from gra_mi.capture.source_files import normalised_gains, read_led_gains
from gra_mi.core.config import name_list, option
from gra_mi.core.errors import GraMiInputError, GraMiParameterError, require_positive
from gra_mi.core.guard import path_component
from gra_mi.core.limits import require_memory
from gra_mi.core.schema import rigid_rotation
from gra_mi.render.atlas import MIN_RESOLUTION

TEXEL_BYTES = 64  # per texel of an imported capture's atlas: positions, normals, masks, the maps (a lower bound)
MIN_HELD = 0.5  # of a camera's pinhole view that its distorted image must hold (an ordinary lens loses its corners at most)
UP_AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}


@dataclass(kw_only=True)
class ImportConfig:
    """What every import route shares (:func:`import_capture`)."""

    cameras: list[str] | None = field(default=None, metadata=option(parse=name_list))
    """Cameras to import, comma-separated (Cam01,Cam05,...). Default: all."""
    eval_cameras: list[str] | None = field(default=None, metadata=option(parse=name_list))
    """Cameras held out for novel-view evaluation, comma-separated. Default: two, spread over the rig."""
    scale: float = 1.0
    """Image scale after the pixels are made square (0.25: a quarter of the size; a full HumanOLAT pose is ~13,700
    images)."""
    up: str = field(default="auto", metadata=option(choices=("auto", *UP_AXES)))
    """The source frame's up axis; auto: level to every camera's image x axis, signed by their image up (reported)."""
    led_intensity: float = 4.0
    """Radiant intensity (W/sr) of a fully driven LED (the mean LED's), in the images' units: it sets the albedo's
    scale only (too low, and `gra-mi fit` warns that the albedo reaches past 1, naming the intensity that holds it).
    Default: 4, or what the source states (mitsuba: the mean intensity of the scene's point emitters)."""
    uv_resolution: int = 256
    """UV resolution of the maps fitted to the capture."""
    min_iou: float = 0.5
    """Stop when the mesh reprojected over a camera's mask overlaps it less than this (intersection over union)."""
    led_gains: Path | None = None
    """A text file of the LEDs' measured gains (a calibration of the stage): line k is LED k's, in the source's LED
    numbering (HumanOLAT's light positions file, --leds, or transforms.json's light_idx), one number or `r g b`
    (linear; `#` comments). Normalised to a mean of 1, so --led-intensity is the mean LED's. An OLAT frame is lit by
    its LED's gain; environment-map frames are taken to have been driven with the gains undone (the emitted light is
    the map's). Default: equal gains."""
    estimate_led_gains: bool = False
    """Measure the LEDs' gains from the capture's own OLAT frames (where the stage states none): each LED's light
    against the albedo that every LED's images share, on the training cameras (docs/data-format.md). Written into the
    rig, and as import/led_gains.txt, a --led-gains file for the stage's other captures. An LED without an OLAT, or
    whose light no training camera sees on texels other LEDs light too, keeps 1 (listed in the report)."""
    missing_images: str = field(default="refuse", metadata=option(choices=("refuse", "skip")))
    """A camera without an image of a frame: refuse (name it and stop), or skip (import the rest; capture.json and the
    report list the gaps, the fit and RelightNet leave them out, the evaluation and the refiner refuse a camera with a
    gap in what they need)."""

    def validate(self) -> None:
        require_positive({"scale": self.scale, "led_intensity": self.led_intensity})
        if self.uv_resolution < MIN_RESOLUTION:
            raise GraMiParameterError("uv_resolution", f"must be >= {MIN_RESOLUTION}, got {self.uv_resolution}")
        if not 0 <= self.min_iou <= 1:
            raise GraMiParameterError("min_iou", f"must be in [0, 1], got {self.min_iou}")
        if self.up not in ("auto", *UP_AXES):
            raise GraMiParameterError("up", f"expected auto or one of {', '.join(UP_AXES)}, got {self.up!r}")
        # the atlas, the maps and their per-texel checks of the import, and later the fit, at this resolution
        require_memory("uv_resolution", self.uv_resolution**2 * TEXEL_BYTES, f"a {self.uv_resolution}² UV atlas")


@dataclass
class Source:
    """A capture as read, before anything is written: everything in the source's own frame and units. Each format's
    reader (:func:`gra_mi.capture.humanolat.read_humanolat`, :func:`gra_mi.capture.transforms.read_transforms`,
    :func:`gra_mi.capture.easymocap.read_easymocap`, :func:`gra_mi.capture.colmap.read_colmap`, …) fills it; the rest
    of the import is the same for every source."""

    folder: Path
    format: str  # "humanolat", "transforms", "easymocap", "colmap", "mitsuba"
    calib_path: Path  # what a camera error names
    names: list[str]  # camera names
    calib: list  # CalibCamera per camera: K / width, camera-to-world (OpenCV axes) in the source's units
    sizes: list[tuple[int, int]]  # (width, height) of each camera's images
    images: list[dict[int, Path]]  # per camera: frame key → image file
    units: float  # metres per source unit of the calibration (0.001: millimetres)
    leds: np.ndarray  # (L, 3) metres, the source's frame
    meshes: MeshFrames  # one file per mesh frame (one topology), source units; each checked when read
    masks: list[Path | None]  # per camera: a mask file, else the images' alpha or non-black pixels
    frames: list = field(default_factory=list)  # (frame key, FrameLighting, drive): an LED, "white", an envmap file, …
    left_out: list[int] = field(default_factory=list)  # LEDs whose OLATs were not imported
    white: int | None = None  # the frame key of an all-LEDs frame (the linearity check)
    olat_keys: list[int] | None = None  # the frame keys of every LED's OLAT, imported or not (the linearity check)
    steady_keys: list[int] | None = None  # frames lit alike all through the OLATs (HumanOLAT's full-bright): the stillness check
    order: np.ndarray | None = None  # the OLAT firing order (HumanOLAT)
    mesh_units: float | None = None  # metres per unit of the meshes (None: as the calibration)
    frame_masks: list[dict[int, Path]] | None = None  # per camera: frame key → its own mask file (a moving subject)
    mask_cache: dict[int, np.ndarray] = field(default_factory=dict, repr=False)  # per camera: a mask every frame shares
    subtracted: dict[int, list] = field(default_factory=dict)  # frame key → [(OLAT key, RGB weight)] taken off its images

    leds_path: Path | None = None  # what an LED error names (None: the calibration)
    led_numbers: list[int] | None = None  # the source's number of each LED in ``leds`` (None: 0, 1, …), for --led-gains
    stated_gains: np.ndarray | None = None  # (L, 3) gains the source itself states (transforms.json's pl_intensity)
    gains_field: str = "pl_intensity"  # where the source states them, as an error names it
    stated_intensity: float | None = None  # the LEDs' mean W/sr at full drive, where the source states it (a Mitsuba scene)
    mesh_files: list[Path] = field(default_factory=list)  # the mesh file(s) or folder read (for provenance)
    calib_files: list[Path] = field(default_factory=list)  # the calibration's files besides calib_path (for provenance)
    alignment: dict | None = None  # how --align-cameras moved the calibration into the LEDs' frame (the report says it)
    alignment_move: tuple | None = None  # (scale, rotation, translation in calibration units): what it moved them by
    set_shapes: list = field(default_factory=list)  # a Mitsuba scene's other shapes (scene_stage.SetShape), in the meshes' frame

    def check(self) -> None:
        """What every source must satisfy before anything is written, whichever reader filled it: the checks gra-mi's
        own loaders make of a capture, stated here against the source's files (each reader checks its format).
        :func:`import_capture` calls it first."""
        self._check_cameras()
        self._check_leds()
        self._check_frames()

    def _check_cameras(self) -> None:
        # Camera names become folder names in the capture (and in every later command's output): plain and unique.
        seen: dict[tuple, str] = {}
        for i, (name, cam) in enumerate(zip(self.names, self.calib, strict=True)):
            path_component(name, self.calib_path, f"camera {i} name")
            if name in self.names[:i]:
                raise GraMiInputError(self.calib_path, f"cameras {self.names.index(name)} and {i} are both named '{name}'", field="cameras")
            if not (np.isfinite(cam.extrinsic).all() and np.isfinite(cam.intrinsic).all()):
                raise GraMiInputError(self.calib_path, "non-finite calibration values", field=f"camera {name}")
            try:
                rigid_rotation(np.asarray(cam.extrinsic)[:3, :3], "camera-to-world rotation")
            except ValueError as exc:
                raise GraMiInputError(self.calib_path, str(exc), field=f"camera {name}") from None
            key = tuple(np.round(np.concatenate([np.ravel(cam.extrinsic), np.ravel(cam.intrinsic)]), 6))
            if key in seen:
                raise GraMiInputError(
                    self.calib_path, f"cameras {seen[key]} and {name} have one pose and intrinsics: a camera listed twice", field="cameras"
                )
            seen[key] = name
            self._check_lens(name, cam, self.sizes[i])
        if not (np.isfinite(self.units) and self.units > 0):
            raise GraMiInputError(self.calib_path, f"units must be a positive length in metres, got {self.units}")

    def _check_lens(self, name: str, cam, size: tuple[int, int]) -> None:
        """A lens model must map the pinhole view onto every pixel of its image: one that folds back short of the
        image's corners is a calibration that does not hold there (its images cannot be undistorted)."""
        if cam.lens is None:
            return
        k = cam.k_matrix(size[0])
        corners = np.array([[0, 0], [size[0], 0], [0, size[1]], [size[0], size[1]]], float)
        farthest = float(np.hypot((corners[:, 0] - k[0, 2]) / k[0, 0], (corners[:, 1] - k[1, 2]) / k[1, 1]).max())
        if cam.lens.reach() < farthest:
            raise GraMiInputError(
                cam.lens.origin[0],
                f"camera {name}: the lens distortion {cam.lens.describe()} folds back at {cam.lens.reach():.3f} (normalized), "
                f"inside its image (corners at {farthest:.3f}): pixels past it have no pinhole point; check the calibration",
                field=cam.lens.origin[1],
            )
        held = held_fraction(k, cam.lens, *size)
        if held < MIN_HELD:  # a lens that sends most of the view outside its own image is a calibration's mistake
            raise GraMiInputError(
                cam.lens.origin[0],
                f"camera {name}: the lens distortion {cam.lens.describe()} puts {100 * (1 - held):.0f} % of the pinhole view "
                "outside the image; check the calibration (the coefficients' model and scale)",
                field=cam.lens.origin[1],
            )

    def _check_leds(self) -> None:
        from scipy.spatial import cKDTree

        where = self.leds_path or self.calib_path
        leds = np.asarray(self.leds, float)
        if leds.ndim != 2 or leds.shape[1] != 3 or not np.isfinite(leds).all():
            raise GraMiInputError(where, "LED positions must be finite (x, y, z) triples")
        pairs = sorted(cKDTree(leds).query_pairs(1e-6)) if len(leds) > 1 else []
        if pairs:
            a, b = pairs[0]
            raise GraMiInputError(where, f"LEDs {a} and {b} are at one position {leds[a].round(6).tolist()}: an LED listed twice")

    def _check_frames(self) -> None:
        keys = [key for key, _, _ in self.frames]
        if not keys:
            raise GraMiInputError(self.folder, "no frames to import")
        if twice := sorted({k for k in keys if keys.count(k) > 1}):
            raise GraMiInputError(self.folder, f"frame {twice[0]} is listed twice")
        # One name, one thing: envmaps are stored by file name; two different files with one name get distinct names.
        stored: dict[str, Path] = {}
        for _, entry, drive in self.frames:
            if entry.kind != "envmap":
                continue
            name, source = entry.envmap, Path(drive).resolve()
            if name in stored and stored[name] != source:
                stem, suffix = Path(name).stem, Path(name).suffix
                n = 1
                while f"envmaps/{stem}_{n}{suffix}" in stored and stored[f"envmaps/{stem}_{n}{suffix}"] != source:
                    n += 1
                entry.envmap = name = f"envmaps/{stem}_{n}{suffix}"
            stored[name] = source

    def led_gains(self, path: Path | None, estimate: bool = False) -> np.ndarray | None:
        """The LEDs' gains over their mean: from ``path`` (--led-gains), else as the source states them, else None
        (equal, or to be estimated from the images). Two answers (a source that states gains and a file besides, or
        either and ``estimate``) are refused."""
        numbers = self.led_numbers or list(range(len(self.leds)))
        if path is not None and self.stated_gains is not None:
            raise GraMiParameterError(
                "led_gains", f"{self.calib_path} states the LEDs' gains itself ({self.gains_field}): give one or the other"
            )
        if estimate and (path is not None or self.stated_gains is not None):
            said = path if path is not None else f"{self.calib_path}'s {self.gains_field}"
            raise GraMiParameterError("estimate_led_gains", f"the gains are given ({said}): estimate them or give them, not both")
        if path is not None:
            return read_led_gains(path, numbers)
        return None if self.stated_gains is None else normalised_gains(self.stated_gains, numbers, self.calib_path)

    @property
    def mesh_moved(self) -> bool:
        """Whether the meshes moved with the cameras (--mesh-frame calibration), as the alignment records it."""
        return bool(self.alignment and self.alignment["mesh_moved"])

    def mesh_metres(self, positions: np.ndarray) -> np.ndarray:
        """A mesh frame's positions in metres, in the LEDs' frame (moved with the calibration where it was tracked in it)."""
        metres = positions * (self.units if self.mesh_units is None else self.mesh_units)
        if not self.mesh_moved:
            return metres
        scale, rotation, translation = self.alignment_move
        return scale * metres @ rotation.T + translation * self.units

    def mesh_directions(self, normals: np.ndarray) -> np.ndarray:
        """A mesh frame's normals turned as :meth:`mesh_metres` turns its positions."""
        return normals @ self.alignment_move[1].T if self.mesh_moved else normals
