"""A lightstage capture on disk (``gra-mi-capture/1``, docs/data-format.md): what the fit, RelightNet and the refiner
read. :mod:`gra_mi.capture.synthetic` writes one; real data converted to this layout works the same.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_write_text, read_exr, read_json
from gra_mi.core.progress import threaded
from gra_mi.stage.envmap import envmap_to_leds, load_envmap
from gra_mi.stage.lightstage import load_calibration, load_pattern, uniform_pattern

CAPTURE_FORMAT = "gra-mi-capture/1"
UNIFORM_FRACTION = 0.5  # the tracking frames: every LED at half the stage maximum


PATTERN_NAMES = {
    "olat": "OLATs",
    "white": "every LED",
    "envmap": "environment-map frames (drive solved from the OLATs)",
    "gradient": "gradient frames (drive solved from the OLATs)",
}


@dataclass
class FrameLighting:
    frame: int
    split: str  # "train" or "test"
    sequence: int  # test sequence index (0 for training)
    kind: str  # "uniform", "envmap" or "pattern"
    envmap: str | None  # path relative to the capture folder
    pattern: str | None = None  # kind "pattern": LED drive values (JSON or .npy, docs/data-format.md), relative path
    pose: int | None = None  # the subject's mesh frame; None: ``frame`` (a static pose lit many ways shares one)
    missing: list[str] = field(default_factory=list)  # cameras with no image of this frame (a real capture's gaps)

    @property
    def mesh_frame(self) -> int:
        """The frame of the subject's sequence this image shows (geometry, visibility): ``pose``, or ``frame``."""
        return self.frame if self.pose is None else self.pose

    @property
    def lighting_name(self) -> str:
        """What lit the frame, in words: its envmap's name, the kind of its LED pattern (by the file names gra-mi
        writes: OLATs, solved environment-map and gradient frames), or "uniform"."""
        if self.kind != "pattern":
            return Path(self.envmap).stem if self.envmap else "uniform"
        kind = Path(self.pattern or "").stem.rstrip("0123456789_")
        return PATTERN_NAMES.get(kind, f"LED pattern ({kind})" if kind else "LED pattern")


@dataclass
class Capture:
    folder: Path
    preset: str
    renderer: str
    uv_resolution: int
    train_cameras: list[str]
    eval_cameras: list[str]
    frames: list[FrameLighting]
    ground_truth: dict = field(default_factory=dict)  # how the images were rendered, and their measured noise
    source: dict = field(default_factory=dict)  # an imported capture: where from, and the transform into gra-mi's frame

    def image_path(self, camera: str, frame: int) -> Path:
        return self.folder / "images" / camera / f"frame_{frame:04d}.exr"

    def saturation_path(self, camera: str, frame: int) -> Path:
        """Pixels the source clipped (a channel at the top of its range), as a binary PNG next to the image; absent
        when none was."""
        return self.image_path(camera, frame).with_suffix(".saturated.png")

    def has_image(self, camera: str, entry: FrameLighting) -> bool:
        """Whether ``camera`` has an image of the frame (an import records the gaps of a real capture)."""
        return camera not in entry.missing

    def frames_with_images(self, camera: str, frames: list[int]) -> tuple[list[int], list[int], list[int]]:
        """(the frames of ``frames`` that ``camera`` has an image of, those it has none of, and the positions in the
        first list whose frame does not follow its predecessor there: a gap lies between the two)."""
        entries = {f.frame: f for f in self.frames}
        present, missing, breaks, last = [], [], [], None
        for k, f in enumerate(frames):
            if not self.has_image(camera, entries[f]):
                missing.append(f)
                continue
            if last is not None and k > last + 1:
                breaks.append(len(present))
            present.append(f)
            last = k
        return present, missing, breaks

    def require_images(self, cameras: list[str], entries: list[FrameLighting], needed_by: str) -> None:
        """Refuse, before any work, a stage that needs every image of ``cameras`` × ``entries`` where one is missing."""
        for entry in entries:
            gap = next((c for c in cameras if not self.has_image(c, entry)), None)
            if gap is not None:
                raise GraMiInputError(
                    self.folder / "capture.json",
                    f"camera {gap} has no image of frame {entry.frame} (the import recorded it missing), and {needed_by} needs "
                    "every one: hold that camera out of it (or re-import it with its images)",
                    field="frames",
                )

    def save(self) -> None:
        data = {"format": CAPTURE_FORMAT, **asdict(self)}
        for entry in data["frames"]:  # a complete capture's files stay as they were
            if not entry["missing"]:
                del entry["missing"]
        data["folder"] = None
        atomic_write_text(self.folder / "capture.json", json.dumps(data, indent=1) + "\n")

    @classmethod
    def load(cls, folder: str | Path) -> Capture:
        """Read and check ``capture.json`` against the schema (types, ranges, unknown keys, frames, camera names
        in the rig): a bad capture stops here, naming the field, before any work."""
        folder = Path(folder)
        path = folder / "capture.json"
        if folder.exists() and not folder.is_dir():
            raise GraMiInputError(folder, "is a file; expected a capture folder (made by `gra-mi capture`)")
        data = read_json(path, hint=" (make a capture with `gra-mi capture`)")
        if not isinstance(data, dict):
            raise GraMiInputError(path, f"expected a JSON object, got {type(data).__name__}")
        if data.get("format") != CAPTURE_FORMAT:
            raise GraMiInputError(path, f"expected '{CAPTURE_FORMAT}', got {data.get('format')!r}", field="format")
        unknown = sorted(set(data) - {"format", *cls.__dataclass_fields__})
        if unknown:
            raise GraMiInputError(path, f"unknown field(s) {unknown} (docs/data-format.md lists the fields)")
        for key in ("train_cameras", "eval_cameras", "frames", "uv_resolution"):
            if key not in data:
                raise GraMiInputError(path, "missing", field=key)
        for key in ("train_cameras", "eval_cameras"):
            names = data[key]
            if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
                raise GraMiInputError(path, f"expected a list of camera names, got {names!r}", field=key)
        uv = data["uv_resolution"]
        if not isinstance(uv, int) or isinstance(uv, bool) or uv < 1:
            raise GraMiInputError(path, f"expected an integer >= 1, got {uv!r}", field="uv_resolution")
        if not isinstance(data["frames"], list):
            raise GraMiInputError(path, "expected a list of frame entries", field="frames")
        frames = [_frame_entry(path, i, f) for i, f in enumerate(data["frames"])]
        seen: dict[int, int] = {}
        for i, entry in enumerate(frames):
            if entry.frame in seen:
                raise GraMiInputError(path, f"frame {entry.frame} is listed twice (entries {seen[entry.frame]} and {i})", field="frames")
            seen[entry.frame] = i
        capture = cls(
            folder,
            str(data.get("preset", "?")),
            str(data.get("renderer", "?")),
            uv,
            data["train_cameras"],
            data["eval_cameras"],
            frames,
            data.get("ground_truth", {}) or {},
            data.get("source", {}) or {},
        )
        capture._check_cameras(path)
        capture._check_missing(path)
        return capture

    def _check_missing(self, path: Path) -> None:
        cameras = self.train_cameras + self.eval_cameras
        for i, entry in enumerate(self.frames):
            unknown = [c for c in entry.missing if c not in cameras]
            if unknown:
                raise GraMiInputError(path, f"names camera(s) {unknown} that the capture does not have", field=f"frames[{i}].missing")
            if entry.missing and set(cameras) <= set(entry.missing):
                raise GraMiInputError(path, "every camera's image of this frame is missing: drop the frame", field=f"frames[{i}].missing")

    def _check_cameras(self, path: Path) -> None:
        """Every camera named in capture.json exists in the capture's rig (when it has one)."""
        calibration = self.folder / "rig" / "calibration.json"
        if not calibration.is_file():
            return

        self._sizes = {c.name: (c.width, c.height) for c in load_calibration(calibration).cameras}
        for key in ("train_cameras", "eval_cameras"):
            missing = [n for n in getattr(self, key) if n not in self._sizes]
            if missing:
                raise GraMiInputError(path, f"camera(s) {missing} are not in {calibration} (it has {sorted(self._sizes)})", field=key)

    def check_images(self) -> None:
        """Read and check every image once before work starts (a bad one found hours into a fit, or after caches
        were written, would leave partial output). About 2 ms an image at the small preset's size."""

        views = [(cam, f.frame) for cam in self.train_cameras + self.eval_cameras for f in self.frames if self.has_image(cam, f)]

        def check(view: tuple[str, int]) -> None:
            load_observation(self, *view)  # the image itself is not kept

        for _ in threaded(check, views, "checking the capture's images"):  # EXR decoding releases the GIL
            pass

    def load_scene(self):
        """The capture's scene (``scene.xml``), the subject's frames checked those the capture shows: every frame's
        pose must be one of the sequence's (named if not), and only those poses' positions and normals are read."""
        from gra_mi.stage.scene import LightstageScene
        from gra_mi.subject.sequence import check_frames

        ls = LightstageScene.load(self.folder / "scene.xml", every_frame=False)
        count = ls.sequence.num_frames
        for i, entry in enumerate(self.frames):
            if entry.mesh_frame >= count:
                field = f"frames[{i}].{'pose' if entry.pose is not None else 'frame'}"
                raise GraMiInputError(
                    self.folder / "capture.json", f"shows mesh frame {entry.mesh_frame}, but the subject has {count} frames", field=field
                )
        check_frames(ls.sequence, sorted({f.mesh_frame for f in self.frames}))
        return ls

    def camera_size(self, camera: str) -> tuple[int, int] | None:
        """(width, height) of a camera from the capture's rig, None where the capture has no rig folder."""
        return getattr(self, "_sizes", {}).get(camera)

    def lighting(self, stage, entry: FrameLighting) -> np.ndarray:
        """LED radiant intensities (L, 3) of a frame."""

        if entry.kind == "uniform":
            return uniform_pattern(stage, UNIFORM_FRACTION) * stage.gains
        if entry.kind == "pattern":
            return load_pattern(stage, self.folder / entry.pattern) * stage.gains
        return envmap_to_leds(load_envmap(self.folder / entry.envmap), stage).radiant_intensity(stage)


FRAME_KINDS = ("uniform", "envmap", "pattern")


def _frame_entry(path: Path, i: int, f) -> FrameLighting:
    where = f"frames[{i}]"
    if not isinstance(f, dict):
        raise GraMiInputError(path, f"expected an object with {list(FrameLighting.__dataclass_fields__)}, got {f!r}", field=where)
    try:
        entry = FrameLighting(**f)
    except TypeError as exc:
        raise GraMiInputError(path, f"bad entry: {exc}", field=where) from None
    if not isinstance(entry.missing, list) or not all(isinstance(c, str) for c in entry.missing):
        raise GraMiInputError(path, f"expected a list of camera names, got {entry.missing!r}", field=f"{where}.missing")
    for name in ("frame", "sequence", "pose"):
        value = getattr(entry, name)
        if name == "pose" and value is None:
            continue
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise GraMiInputError(path, f"expected an integer >= 0, got {value!r}", field=f"{where}.{name}")
    if entry.split not in ("train", "test"):
        raise GraMiInputError(path, f"expected 'train' or 'test', got {entry.split!r}", field=f"{where}.split")
    needs = {"uniform": None, "envmap": entry.envmap, "pattern": entry.pattern}
    if entry.kind not in needs or (entry.kind != "uniform" and not isinstance(needs[entry.kind], str)):
        raise GraMiInputError(path, f"kind must be uniform, envmap (with envmap) or pattern (with pattern), got {f}", field=f"{where}.kind")
    return entry


def load_fit_observation(capture: Capture, camera: str, frame: int) -> np.ndarray:
    """:func:`load_observation` with the alpha of clipped pixels set to 0: a saturated pixel says only that the
    radiance was at least the clip level, so the fit leaves it out as it leaves out the background."""
    image = load_observation(capture, camera, frame)
    path = capture.saturation_path(camera, frame)
    if path.is_file():
        from gra_mi.capture.source_files import read_mask

        clipped = read_mask(path)
        if clipped.shape != image.shape[:2]:
            raise GraMiInputError(path, f"is {clipped.shape[1]}x{clipped.shape[0]}, its image {image.shape[1]}x{image.shape[0]}")
        image[clipped, 3] = 0.0
    return image


def load_observation(capture: Capture, camera: str, frame: int) -> np.ndarray:
    """A captured image, RGBA (alpha = the subject mask), checked: linear radiance is finite and >= 0, the mask in
    [0, 1], the size the camera's calibration says (images at another resolution would be sampled with the wrong
    intrinsics)."""
    path = capture.image_path(camera, frame)
    recorded = next((f for f in capture.frames if f.frame == frame), None) if not path.is_file() else None
    if recorded is not None and not capture.has_image(camera, recorded):  # a stage that should have left it out
        capture.require_images([camera], [recorded], "this step")
    image = read_exr(path)
    if image.shape[2] != 4:
        raise GraMiInputError(path, f"expected RGBA (alpha = mask), got {image.shape[2]} channels")
    size = capture.camera_size(camera)
    if size is not None and (image.shape[1], image.shape[0]) != size:
        raise GraMiInputError(
            path,
            f"is {image.shape[1]}x{image.shape[0]} pixels, but camera {camera} in rig/calibration.json is {size[0]}x{size[1]} "
            "(resize the images or the calibration's intrinsics together)",
        )
    rgb, alpha = image[..., :3], image[..., 3]
    nan, inf = int(np.isnan(rgb).sum()), int(np.isinf(rgb).sum())
    if nan or inf:
        raise GraMiInputError(path, f"{nan} NaN and {inf} inf pixel values; captured radiance must be finite")
    if rgb.min() < 0:
        raise GraMiInputError(
            path,
            f"{int((rgb < 0).sum())} negative values (min {rgb.min():.3g}); captured radiance must be >= 0 (clamp after black-level subtraction)",
        )
    if not np.all(np.isfinite(alpha)) or alpha.min() < 0 or alpha.max() > 1:
        raise GraMiInputError(path, f"alpha (the subject mask) must be in [0, 1], got [{np.nanmin(alpha):.3g}, {np.nanmax(alpha):.3g}]")
    return image
