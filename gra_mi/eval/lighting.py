"""Relighting under environments against the physical truth: the lighting models side by side.

The truth is the capture's subject with its true materials (sheen, wrinkles, interreflections) path-traced by
Mitsuba under the environment itself, at infinity (:func:`gra_mi.capture.truth.render_envmap_truth`). Against
it, for every map and held-out camera:

- ``near field``: the fitted maps lit by the stage's LEDs where they are (how the capture was lit);
- ``far field``: the fitted maps lit by the LEDs as an environment at infinity (gra-mi's default for envmaps);
- ``far field, true maps``: the same with the true maps: what the lighting model alone costs;
- ``RelightNet``: RelightNet on the far-field render, when a trained one is given.

Scores are :func:`gra_mi.core.metrics.compare` (display PSNR, SSIM, brightness error), with the time per view.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.truth import TRUTH_VERSION, render_envmap_truth
from gra_mi.core.color import display_exposure
from gra_mi.core.config import name_list, option
from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_write_text, pyplot, read_exr, save_figure, to_srgb8, write_exr
from gra_mi.core.limits import require_memory
from gra_mi.core.metrics import compare, subject_mask
from gra_mi.core.progress import progress
from gra_mi.core.runtime import torch_device
from gra_mi.core.shard import Shard
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.transport import LightTransport
from gra_mi.stage.envmap import envmap_to_leds
from gra_mi.stage.envmap_library import BAKE_BYTES_PER_PIXEL, REFERENCE_MAPS, reference_map
from gra_mi.stage.scene import MAX_SPP

logger = logging.getLogger(__name__)

TRUTH_SPP = 256


@dataclass
class EnvmapAccuracyConfig:
    maps: list[str] = field(default_factory=lambda: ["sun", "studio", "interior", "night"], metadata=option(parse=name_list))
    """Reference maps to relight under, comma-separated, among sun, studio, interior, night (envmap_library.reference_map)."""
    frame: int | None = None
    """Subject frame (default: the first frame of the first test sequence)."""
    cameras: list[str] | None = field(default=None, metadata=option(parse=name_list))
    """Cameras to score, comma-separated names (default: the capture's held-out cameras)."""
    spp: int = TRUTH_SPP
    """Samples per pixel of the path-traced truth."""
    map_height: int = 64
    """Rows of the reference maps (lat-long, twice as wide)."""
    transport: LightTransport = field(default_factory=LightTransport)

    def validate(self) -> None:
        self.transport.validate(fixed=True)
        unknown = sorted(set(self.maps) - set(REFERENCE_MAPS))
        if unknown or not self.maps:
            raise GraMiParameterError("maps", f"expected names among {', '.join(REFERENCE_MAPS)}, got {', '.join(self.maps) or 'none'}")
        if not 1 <= self.spp <= MAX_SPP:
            raise GraMiParameterError("spp", f"must be in [1, {MAX_SPP}], got {self.spp}")
        if self.map_height < 8:
            raise GraMiParameterError("map_height", f"must be >= 8, got {self.map_height}")
        require_memory("map_height", BAKE_BYTES_PER_PIXEL * 2 * self.map_height**2, f"a {2 * self.map_height}x{self.map_height} map")


def _truth_files(out: Path, capture, env: np.ndarray, name: str, frame: int, cameras: list[str], spp: int):
    """(what made the truth of map ``name``, its record file, its images) under ``out/truth/NAME``, and whether they
    are there and agree."""
    folder = out / "truth" / name
    record = {
        "version": TRUTH_VERSION,
        "frame": frame,
        "spp": spp,
        "envmap_sum": float(np.asarray(env, np.float64).sum()),
        "capture": str(capture.folder.resolve()),
    }
    meta, paths = folder / "truth.json", {cam: folder / f"{cam}.exr" for cam in cameras}
    ready = meta.is_file() and json.loads(meta.read_text()) == record and all(p.is_file() for p in paths.values())
    return record, meta, paths, ready


def _cached_truth(out: Path, capture, env: np.ndarray, name: str, frame: int, cameras: list[str], spp: int) -> dict[str, np.ndarray]:
    """The truth renders, kept under ``out/truth/NAME`` with what made them (reused when everything agrees)."""

    record, meta, paths, ready = _truth_files(out, capture, env, name, frame, cameras, spp)
    if ready:
        return {cam: read_exr(p) for cam, p in paths.items()}
    images = render_envmap_truth(capture, env, frame, cameras, spp=spp)
    for cam, image in images.items():
        write_exr(paths[cam], image)
    atomic_write_text(meta, json.dumps(record, indent=1) + "\n")
    return images


def envmap_accuracy(
    capture_dir: str | Path,
    fit_dir: str | Path,
    out: str | Path,
    relightnet_dir: str | Path | None = None,
    config: EnvmapAccuracyConfig | None = None,
    shard: Shard | None = None,
) -> list[dict]:
    """Score every lighting model on every reference map and camera; write ``accuracy.json``, ``accuracy.md``,
    ``contact_sheet.png`` (truth | each model, per map) and every render (EXR) under ``out``. Returns the rows
    (one per map and model, averaged over the cameras). ``shard``: path-trace the truths of this shard's maps (the
    costly part); the shard that then finds every map's truth done scores them all (the others return no rows)."""

    config = config or EnvmapAccuracyConfig()
    config.validate()
    ensure_mitsuba()
    out, shard = Path(out), shard or Shard()
    capture, methods = _lighting_models(capture_dir, fit_dir, relightnet_dir, config.transport)
    ls = methods[0][1].ls
    frame, cameras = _views(config, capture, ls)
    if not shard.whole and not _shard_truths(out, capture, ls, config, frame, cameras, shard):
        return []
    rows, sheet = [], []
    for name in progress(config.maps, description="reference maps"):
        env = reference_map(name, config.map_height)
        lighting = envmap_to_leds(env, ls.stage)
        # The LEDs are normalised to the stage's maximum; the truth's environment takes the same factor.
        truths = _cached_truth(out, capture, env * lighting.scale, name, frame, cameras, config.spp)
        shown = [truths[cameras[0]]]
        for method in methods:
            row, image = _score_method(method, name, frame, cameras, lighting.radiant_intensity(ls.stage), truths, out)
            rows.append(row)
            shown.append(image)
        sheet.append(_sheet_row(shown))
    summary = _summarise(rows, [m for m, *_ in methods])
    record = {"frame": frame, "cameras": cameras, "spp": config.spp, "rows": rows, "summary": summary}
    atomic_write_text(out / "accuracy.json", json.dumps(record, indent=1) + "\n")
    atomic_write_text(out / "accuracy.md", accuracy_markdown(rows, summary, frame, cameras, config.spp))
    _write_sheet(out / "contact_sheet.png", sheet, config.maps, ["truth (path-traced)"] + [m for m, *_ in methods])
    return rows


def _shard_truths(out: Path, capture, ls, config: EnvmapAccuracyConfig, frame: int, cameras: list[str], shard: Shard) -> bool:
    """Path-trace the truths of the shard's maps; whether every map's truth is now done."""

    def truth_env(name: str) -> np.ndarray:
        env = reference_map(name, config.map_height)
        return env * envmap_to_leds(env, ls.stage).scale

    for name in progress(shard.take(config.maps), description=f"path-traced truths (shard {shard})"):
        _cached_truth(out, capture, truth_env(name), name, frame, cameras, config.spp)
    waiting = [n for n in config.maps if not _truth_files(out, capture, truth_env(n), n, frame, cameras, config.spp)[3]]
    if waiting:
        logger.info("shard %s done; the truths of %s are another shard's: the last shard scores", shard, ", ".join(waiting))
    return not waiting


def _lighting_models(capture_dir, fit_dir, relightnet_dir, transport):
    """(capture, [(name, relighter, RelightNet or None, far field)]): near and far field with the fitted maps, far
    field with the true maps, and RelightNet on the far-field render when given; every render with ``transport``'s
    bounces."""
    from gra_mi.fit.fitted import fitted_relighter
    from gra_mi.render.relighter import Relighter, load_texture

    capture, fitted = fitted_relighter(capture_dir, fit_dir, transport=transport)
    truth_maps = Relighter(
        fitted.ls,
        albedo=load_texture(capture.folder / "gt" / "albedo.exr", 3, "albedo"),
        roughness=load_texture(capture.folder / "gt" / "roughness.exr", 1, "roughness"),
        transport=transport,
    )
    methods = [("near field", fitted, None, False), ("far field", fitted, None, True), ("far field, true maps", truth_maps, None, True)]
    if relightnet_dir is not None:
        from gra_mi.relightnet.model import RelightNet, check_input_transport

        net = RelightNet.load(relightnet_dir, torch_device())
        check_input_transport(net.config, transport, relightnet_dir)
        methods.append(("RelightNet (far field)", fitted, net, True))
    return capture, methods


def _views(config: EnvmapAccuracyConfig, capture, ls) -> tuple[int, list[str]]:
    """The frame and cameras scored, checked against the capture."""
    frame = config.frame if config.frame is not None else next((f.frame for f in capture.frames if f.split == "test"), 0)
    cameras = config.cameras or capture.eval_cameras
    if not 0 <= frame < ls.sequence.num_frames:
        raise GraMiParameterError("frame", f"frame {frame} out of range [0, {ls.sequence.num_frames}) of {capture.folder}")
    known = [c.name for c in ls.stage.cameras]
    unknown = [c for c in cameras if c not in known]
    if unknown:
        raise GraMiParameterError("cameras", f"no camera {', '.join(unknown)} in {capture.folder}; it has {', '.join(known)}")
    return frame, cameras


def _score_method(method, name: str, frame: int, cameras: list[str], intensities, truths: dict, out: Path) -> tuple[dict, np.ndarray]:
    """One lighting model under one map on every camera, against the truth: its row, and its first camera's image."""
    from gra_mi.relightnet.infer import render_view

    label, relighter, net, far = method
    scores, seconds, negative, first = [], [], 0, None
    slug = label.replace(",", "").replace(" ", "_").replace("(", "").replace(")", "")
    for cam in cameras:
        start = time.perf_counter()
        image = render_view(relighter, net, frame, cam, intensities, far_field=far).image
        seconds.append(time.perf_counter() - start)
        scores.append(compare(image, truths[cam]))
        negative += int(((image[..., :3] < 0).any(axis=-1) & (image[..., 3] > 0)).sum())
        write_exr(out / "renders" / name / slug / f"{cam}.exr", image)
        first = image if first is None else first
    row = {
        "map": name,
        "method": label,
        "psnr": float(np.mean([s["psnr"] for s in scores])),
        "ssim": float(np.mean([s["ssim"] for s in scores])),
        "brightness": float(np.mean([s["brightness"] for s in scores])),
        "worst_brightness": float(max((s["brightness"] for s in scores), key=abs)),
        "negative_pixels": negative,
        "seconds_per_view": float(np.median(seconds[1:] if len(seconds) > 1 else seconds)),
        "cameras": len(cameras),
    }
    return row, first


def _sheet_row(images: list[np.ndarray]) -> np.ndarray:
    """Truth and renders side by side at the truth's exposure, cropped to the subject (8-bit sRGB)."""
    truth = images[0]
    exposure = display_exposure(truth, subject_mask(truth))
    ys, xs = np.nonzero(truth[..., 3] > 0)
    if ys.size:
        y0, y1 = max(ys.min() - 4, 0), min(ys.max() + 5, truth.shape[0])
        x0, x1 = max(xs.min() - 4, 0), min(xs.max() + 5, truth.shape[1])
    else:
        y0, y1, x0, x1 = 0, truth.shape[0], 0, truth.shape[1]
    return np.concatenate([to_srgb8(im[y0:y1, x0:x1, :3], exposure) for im in images], axis=1)


def _write_sheet(path: Path, rows: list[np.ndarray], names: list[str], columns: list[str]) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(len(rows), 1, figsize=(2.0 * len(columns), 3.2 * len(rows)), squeeze=False)
    for ax, row, name in zip(axes[:, 0], rows, names, strict=True):
        ax.imshow(row)
        ax.set_title(f"{name}: " + " | ".join(columns), fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path)


def _summarise(rows: list[dict], methods: list[str]) -> dict:
    out = {}
    for method in methods:
        mine = [r for r in rows if r["method"] == method]
        out[method] = {
            "median_psnr": float(np.median([r["psnr"] for r in mine])),
            "median_ssim": float(np.median([r["ssim"] for r in mine])),
            "worst_brightness": float(max((r["worst_brightness"] for r in mine), key=abs)),
            "seconds_per_view": float(np.median([r["seconds_per_view"] for r in mine])),
            "negative_pixels": int(sum(r["negative_pixels"] for r in mine)),
        }
    return out


def accuracy_table(rows: list[dict], summary: dict) -> list[str]:
    """The Markdown table: maps × models, display PSNR / brightness error, then the medians, the worst view and time."""
    maps = list(dict.fromkeys(r["map"] for r in rows))
    methods = list(summary)
    lines = ["| map | " + " | ".join(methods) + " |", "|---|" + "---|" * len(methods)]
    for name in maps:
        cells = []
        for method in methods:
            r = next(r for r in rows if r["map"] == name and r["method"] == method)
            cells.append(f"{r['psnr']:.1f} / {100 * r['brightness']:+.1f} %")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines.append("| **median PSNR** | " + " | ".join(f"**{s['median_psnr']:.1f}**" for s in summary.values()) + " |")
    lines.append("| worst view's brightness | " + " | ".join(f"{100 * s['worst_brightness']:+.1f} %" for s in summary.values()) + " |")
    lines.append("| negative pixels | " + " | ".join(str(s["negative_pixels"]) for s in summary.values()) + " |")
    lines.append("| time per view | " + " | ".join(f"{1000 * s['seconds_per_view']:.0f} ms" for s in summary.values()) + " |")
    return lines


def accuracy_markdown(rows: list[dict], summary: dict, frame: int, cameras: list[str], spp: int) -> str:
    lines = [
        "# Relighting under environments, against the path-traced truth\n",
        f"Frame {frame}, cameras {', '.join(cameras)}; truth: the true materials path-traced under the map at infinity "
        f"({spp} spp). Cells: display PSNR (dB) / brightness error of the subject, mean over the cameras "
        "(:func:`gra_mi.core.metrics.compare`).\n",
        *accuracy_table(rows, summary),
        "\nTruth (path-traced) | each model, first camera, at the truth's exposure: ![truth | models](contact_sheet.png)\n",
    ]
    return "\n".join(lines) + "\n"
