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

CAPTURE_FORMAT = "gra-mi-capture/1"
UNIFORM_FRACTION = 0.5  # the tracking frames: every LED at half the stage maximum


@dataclass
class FrameLighting:
    frame: int
    split: str  # "train" or "test"
    sequence: int  # test sequence index (0 for training)
    kind: str  # "uniform", "envmap" or "pattern"
    envmap: str | None  # path relative to the capture folder
    pattern: str | None = None  # kind "pattern": LED drive values (JSON or .npy, docs/data-format.md), relative path


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

    def image_path(self, camera: str, frame: int) -> Path:
        return self.folder / "images" / camera / f"frame_{frame:04d}.exr"

    def save(self) -> None:
        data = {"format": CAPTURE_FORMAT, **asdict(self)}
        data["folder"] = None
        atomic_write_text(self.folder / "capture.json", json.dumps(data, indent=1) + "\n")

    @classmethod
    def load(cls, folder: str | Path) -> Capture:
        folder = Path(folder)
        path = folder / "capture.json"
        data = read_json(path, hint=" (make a capture with `gra-mi capture`)")
        if data.get("format") != CAPTURE_FORMAT:
            raise GraMiInputError(path, f"expected '{CAPTURE_FORMAT}', got {data.get('format')!r}", field="format")
        for key in ("train_cameras", "eval_cameras", "frames", "uv_resolution"):
            if key not in data:
                raise GraMiInputError(path, "missing", field=key)
        frames = []
        for i, f in enumerate(data["frames"]):
            try:
                entry = FrameLighting(**f)
            except TypeError as exc:
                raise GraMiInputError(path, f"bad entry: {exc}", field=f"frames[{i}]") from None
            needs = {"uniform": None, "envmap": entry.envmap, "pattern": entry.pattern}
            if entry.kind not in needs or (entry.kind != "uniform" and not needs[entry.kind]):
                raise GraMiInputError(
                    path, f"kind must be uniform, envmap (with envmap) or pattern (with pattern), got {f}", field=f"frames[{i}]"
                )
            frames.append(entry)
        return cls(
            folder,
            data.get("preset", "?"),
            data.get("renderer", "?"),
            int(data["uv_resolution"]),
            data["train_cameras"],
            data["eval_cameras"],
            frames,
            data.get("ground_truth", {}),
        )

    def lighting(self, stage, entry: FrameLighting) -> np.ndarray:
        """LED radiant intensities (L, 3) of a frame."""
        from gra_mi.stage.envmap import envmap_to_leds, load_envmap
        from gra_mi.stage.lightstage import load_pattern, uniform_pattern

        if entry.kind == "uniform":
            return uniform_pattern(stage, UNIFORM_FRACTION) * stage.gains
        if entry.kind == "pattern":
            return load_pattern(stage, self.folder / entry.pattern) * stage.gains
        return envmap_to_leds(load_envmap(self.folder / entry.envmap), stage).radiant_intensity(stage)


def load_observation(capture: Capture, camera: str, frame: int) -> np.ndarray:
    path = capture.image_path(camera, frame)
    image = read_exr(path)
    if image.shape[2] != 4:
        raise GraMiInputError(path, f"expected RGBA (alpha = mask), got {image.shape[2]} channels")
    return image
