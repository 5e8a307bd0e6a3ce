"""What a material fit writes: the maps (EXR + PNG), the confidence map, plots, ``fit_report.md`` and ``fit.json``.

Where the capture has true maps (synthetic captures: ``gt/``), the report scores the fit against them next to the
baseline of knowing nothing (a constant: the true map's median over the scored texels), over texels seen by ≥ 3
training cameras, overall and per material region (skin, cloth); and it relights the held-out lighting from the
held-out cameras with the fitted maps against the captured images.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import load_observation
from gra_mi.core.io import atomic_write_text, pyplot, read_exr, save_figure, write_exr, write_png
from gra_mi.core.metrics import compare, mean_l1, subject_mask
from gra_mi.core.progress import progress

logger = logging.getLogger(__name__)

SCORED_MIN_CAMERAS = 3


def map_errors(albedo: np.ndarray, roughness: np.ndarray, true_albedo: np.ndarray, true_roughness: np.ndarray) -> dict[str, float]:
    """Albedo MAE, median relative error and scale bias (the median of fit / truth − 1: the part of the error one
    gain would remove), roughness MAE and median absolute error over the given texels."""
    if roughness.size == 0:
        return {}
    floor = np.maximum(true_albedo, 1e-3)
    rel = np.abs(albedo - true_albedo) / floor
    return {
        "albedo_mae": float(np.mean(np.abs(albedo - true_albedo))),
        "albedo_rel_median": float(np.median(rel)),
        "albedo_bias": float(np.median(albedo / floor) - 1),
        "roughness_mae": float(np.mean(np.abs(roughness - true_roughness))),
        "roughness_median_abs": float(np.median(np.abs(roughness - true_roughness))),
    }


def _true_maps(fitter):
    gt = fitter.capture.folder / "gt"
    if not (gt / "albedo.exr").is_file() or not (gt / "roughness.exr").is_file():
        return None
    atlas = fitter.atlas
    true_albedo = read_exr(gt / "albedo.exr")[..., :3]
    true_rough = read_exr(gt / "roughness.exr")[..., :1]
    region = gt / "cloth.exr" if (gt / "cloth.exr").is_file() else gt / "sheen.exr"
    cloth = read_exr(region)[..., :1] if region.is_file() else np.zeros_like(true_rough)
    if true_albedo.shape[0] != atlas.resolution:  # fitted at another resolution: the truth resampled onto its texels
        from gra_mi.fit.maps import resample
        from gra_mi.render.atlas import UVAtlas

        seq = fitter.ls.sequence
        truth_atlas = UVAtlas.build(seq.faces, seq.uvs, true_albedo.shape[0])
        sampled = [resample(truth_atlas, m, atlas) for m in (true_albedo, true_rough, cloth)]
        return sampled[0], sampled[1][:, 0], sampled[2][:, 0] > 0.5
    return atlas.gather(true_albedo), atlas.gather(true_rough)[:, 0], atlas.gather(cloth)[:, 0] > 0


def score_maps(fitter, result) -> tuple[dict, dict, dict]:
    """(metrics of the fit, metrics of the constant-median baseline), each {region: {metric: value}}, and the number
    of texels scored per region."""
    truth = _true_maps(fitter)
    if truth is None:
        return {}, {}, {}
    true_albedo, true_rough, cloth = truth
    scored = result.observed_cameras >= SCORED_MIN_CAMERAS
    fit_albedo, fit_rough = fitter.atlas.gather(result.albedo), fitter.atlas.gather(result.roughness)[:, 0]
    const_albedo = np.broadcast_to(np.median(true_albedo[scored], axis=0) if scored.any() else 0.5, true_albedo.shape)
    const_rough = np.full_like(true_rough, np.median(true_rough[scored]) if scored.any() else 0.5)
    ours, baseline, counts = {}, {}, {}
    for region, sel in (("all", scored), ("skin", scored & ~cloth), ("cloth", scored & cloth)):
        if not sel.any():
            continue
        ours[region] = map_errors(fit_albedo[sel], fit_rough[sel], true_albedo[sel], true_rough[sel])
        baseline[region] = map_errors(const_albedo[sel], const_rough[sel], true_albedo[sel], true_rough[sel])
        counts[region] = int(sel.sum())
    return ours, baseline, counts


def relight_scores(fitter, result, cache_dir: Path | None) -> dict[str, dict]:
    """PSNR and mean L1 of renders with the fitted maps (and the fit's bounces of light) under the capture's held-out
    (test) lighting, from held-out and training cameras, against the captured images."""
    from gra_mi.render.relighter import Relighter

    capture = fitter.capture
    test = [f for f in capture.frames if f.split == "test"]
    if not test:
        return {}
    relighter = Relighter(
        fitter.ls, albedo=result.albedo, roughness=result.roughness, cache_dir=cache_dir, transport=fitter.config.transport
    )
    scores: dict[str, list] = {"held-out cameras": [], "training cameras": []}
    cameras = [(c, "held-out cameras") for c in capture.eval_cameras] + [(capture.train_cameras[0], "training cameras")]
    for entry in progress(test, description="relight held-out lighting"):
        intensities = capture.lighting(fitter.stage, entry)
        for cam, split in ((c, s) for c, s in cameras if capture.has_image(c, entry)):
            image = relighter.render(entry.mesh_frame, cam, intensities).image
            truth = load_observation(capture, cam, entry.frame)
            scored = compare(image, truth)
            scores[split].append((scored["psnr"], mean_l1(image, truth, subject_mask(truth)), scored["brightness"]))
    return {
        split: {
            "psnr": float(np.mean([v[0] for v in values])),
            "l1": float(np.mean([v[1] for v in values])),
            "brightness": float(np.mean([v[2] for v in values])),
            "images": len(values),
        }
        for split, values in scores.items()
        if values
    }


def _plot_convergence(result, map_curve: list[tuple[float, float, float]], path: Path) -> None:
    plt = pyplot()
    curve = [c for c in result.loss_curve if np.isfinite(c[1])]
    panels = 2 if map_curve else 1
    fig, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 3.6), squeeze=False)
    ax = axes[0, 0]
    ax.plot([c[0] for c in curve], [c[1] for c in curve], "o-", ms=3)
    for t, loss, name in curve[:2] + curve[-1:]:
        ax.annotate(name, (t, loss), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"mean L1 ({result.loss_measure})")
    ax.set_title("Material fit: image error")
    if map_curve:
        ax = axes[0, 1]
        ax.plot([t for t, _, _ in map_curve], [r for _, r, _ in map_curve], "o-", ms=3, label="roughness MAE")
        ax.plot([t for t, _, _ in map_curve], [a for _, _, a in map_curve], "s-", ms=3, label="albedo median rel. error")
        ax.set_xlabel("time (s)")
        ax.set_title("Error against the true maps (texels seen by ≥ 3 cameras)")
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)


def _plot_maps_vs_truth(fitter, result, path: Path) -> None:
    """truth | fit | |error| for albedo and roughness, masked to the atlas."""
    plt = pyplot()
    mask = fitter.atlas.mask[..., None]
    true_albedo, true_rough, _ = _true_maps(fitter)  # at the fit's texels (resampled if the truth has another resolution)
    true_albedo, true_rough = fitter.atlas.scatter(true_albedo), fitter.atlas.scatter(true_rough[:, None])
    rows = [
        ("albedo", true_albedo, result.albedo, 0.3),
        ("roughness", true_rough, result.roughness, 0.3),
    ]
    fig, axes = plt.subplots(2, 3, figsize=(10, 6.8))
    for row, (name, truth, fit, err_max) in enumerate(rows):
        error = np.abs(fit - truth).mean(axis=2) * mask[..., 0]
        shown = [np.clip(truth * mask, 0, 1), np.clip(fit * mask, 0, 1), error]
        for col, (image, title) in enumerate(zip(shown, ("truth", "fit", "|error|"), strict=True)):
            ax = axes[row, col]
            if col == 2:
                im = ax.imshow(image, origin="lower", cmap="magma", vmin=0, vmax=err_max)
                fig.colorbar(im, ax=ax, fraction=0.046)
            else:
                ax.imshow(image[..., 0] if image.shape[2] == 1 else image, origin="lower", cmap="gray", vmin=0, vmax=1)
            ax.set_title(f"{name}: {title}", fontsize=9)
            ax.axis("off")
    fig.tight_layout()
    save_figure(fig, path, dpi=100)


def _table(ours: dict, baseline: dict, counts: dict) -> list[str]:
    lines = ["| region | texels | metric | fit | constant median (baseline) |", "|---|---|---|---|---|"]
    for region in ours:
        for metric, value in ours[region].items():
            lines.append(f"| {region} | {counts[region]} | {metric} | {value:.4f} | {baseline[region][metric]:.4f} |")
    return lines


def write_fit_outputs(fitter, result, out: Path, config) -> Path:
    """Everything a fit folder holds besides its checkpoints: the maps, the confidence map, plots, fit.json (the
    record) and fit_report.md (rendered from it); returns the report's path."""
    out.mkdir(parents=True, exist_ok=True)
    _write_maps(fitter.atlas, result, out)
    record = fit_record(fitter, result, out, config)
    for said in record["warnings"]:
        logger.warning(said)
    _plot_convergence(result, record["map_curve"], out / "convergence.png")
    if _true_maps(fitter) is not None:
        _plot_maps_vs_truth(fitter, result, out / "maps_vs_truth.png")
    atomic_write_text(out / "fit.json", json.dumps(record, indent=1) + "\n")
    atomic_write_text(out / "fit_report.md", fit_markdown(record))
    return out / "fit_report.md"


def _write_maps(atlas, result, out: Path) -> None:
    write_exr(out / "albedo.exr", result.albedo)
    write_exr(out / "roughness.exr", result.roughness)
    write_png(out / "albedo.png", result.albedo)
    write_png(out / "roughness.png", result.roughness)
    ev = result.evidence
    if ev is not None:
        confidence = np.stack([ev.views, ev.highlights, ev.information], axis=1).astype(np.float32)
        write_exr(out / "confidence.exr", atlas.scatter(confidence), channel_names=["views", "highlights", "information"])
        preview = np.stack([ev.views / max(ev.views.max(), 1), np.minimum(ev.highlights / 4.0, 1.0), np.zeros_like(ev.views)], axis=1)
        write_png(out / "confidence.png", atlas.scatter(preview.astype(np.float32)))


def fit_record(fitter, result, out: Path, config) -> dict:
    """fit.json: the maps against the truth (and the constant baseline), relighting the held-out lighting, the
    convergence, and what the views said about the texels."""
    ours, baseline, counts = score_maps(fitter, result)
    truth, map_curve = _true_maps(fitter), []
    if truth is not None and result.snapshots:
        true_albedo, true_rough, _ = truth
        scored = result.observed_cameras >= SCORED_MIN_CAMERAS
        for t, a, r in result.snapshots:
            e = map_errors(a[scored], r[scored], true_albedo[scored], true_rough[scored])
            if e:  # empty when no texel is seen by enough cameras to be scored
                map_curve.append((t, e["roughness_mae"], e["albedo_rel_median"]))
    ev = result.evidence
    seen = None if ev is None else ev.views > 0
    return {
        "config": asdict(config),
        "metrics": dict(ours.get("all", {})),
        "regions": ours,
        "baseline": baseline,
        "scored_texels": counts,
        "relight": relight_scores(fitter, result, out / "cache"),
        "loss_curve": result.loss_curve,
        "loss_measure": result.loss_measure,
        "map_curve": map_curve,
        "never_observed": int(np.sum(result.observed_cameras == 0)),
        "albedo_gain": None if result.albedo_gain is None else [float(g) for g in result.albedo_gain],
        "calibration": "as configured" if config.calibrate_brightness is not None else "automatic",
        "capture": {"folder": str(fitter.capture.folder), "renderer": fitter.capture.renderer}
        | {"training_frames": len(fitter.all_train), "training_cameras": len(fitter.train_cameras)},
        "processes": fitter.ranks.world,
        "texels": fitter.atlas.num_texels,
        "resolution": fitter.atlas.resolution,
        "scored_min_cameras": SCORED_MIN_CAMERAS,
        "well_seen_texels": int(np.sum(result.observed_cameras >= SCORED_MIN_CAMERAS)),
        "without_highlights": None if ev is None else [int(np.sum(seen & (ev.highlights == 0))), int(seen.sum())],
        "per_view_l1": result.per_view_l1,
        "albedo_headroom": None if fitter.headroom is None else asdict(fitter.headroom),
        "warnings": [said]
        if (said := fitter.headroom and fitter.headroom.warning(fitter.stage.max_led_intensity, _set_left_out(fitter, config)))
        else [],
    }


def _set_left_out(fitter, config) -> bool:
    """Whether the fit models one bounce in a scene with a set, whose light the photographs hold."""
    return config.transport.bounces == 1 and bool(fitter.ls.set_digest)


def _batch_said(cfg: dict) -> str:
    b = cfg.get("batch_views", 0)
    return f" of {b} views each, streamed from scratch files, seed {cfg.get('seed', 0)}" if b else ", every view each"


def fit_markdown(r: dict) -> str:
    """fit_report.md from the record."""
    cfg, m, never, k = r["config"], r["texels"], r["never_observed"], r["scored_min_cameras"]
    lines = [
        "# Material fit",
        "",
        f"Capture `{r['capture']['folder']}` ({r['capture']['renderer']} ground truth); {m} texels at {r['resolution']}²; "
        f"{r['capture']['training_frames']} training frames × {r['capture']['training_cameras']} cameras; solver `{cfg['solver']}`"
        + (f" ({cfg['iterations']} Adam iterations{_batch_said(cfg)})." if cfg["solver"] == "adam" else "."),
        *([f"Coarse to fine: {' → '.join(f'{r}²' for r in cfg['levels'])} (each level in the curve below)."] if cfg.get("levels") else []),
        *([f"Fitted by {r['processes']} processes, each on its share of the frames."] if r.get("processes", 1) > 1 else []),
        "",
        f"- texels never observed: {never} ({100 * never / m:.1f} %)"
        + (", filled from their neighbours" if r["without_highlights"] is not None else ", kept at the defaults"),
        f"- texels seen by ≥ {k} cameras (scored below): {r['well_seen_texels']}",
    ]
    lines[2:2] = [line for said in r.get("warnings", []) for line in (f"**Warning:** {said}.", "")]  # first under the title
    if r["albedo_gain"] is not None:
        lines.append(
            f"- brightness calibration: albedo × ({', '.join(f'{g:.3f}' for g in r['albedo_gain'])}) (R, G, B) so that the training "
            "views' renders hold the captured total light (L1 alone leaves them too dark by the light the model leaves out)"
        )
    elif r.get("calibration") == "automatic":
        lines.append("- no brightness calibration: most training frames are OLATs (--calibrate-brightness forces it)")
    if r["without_highlights"] is not None:
        no_highlight, seen = r["without_highlights"]
        lines.append(
            f"- observed texels without highlight evidence (roughness from their neighbours): {no_highlight} "
            f"({100 * no_highlight / max(seen, 1):.1f} %); confidence map: `confidence.exr` (views, highlights, "
            "information), preview `confidence.png` (red: views, green: highlights)"
        )
    if r["regions"]:
        lines += [
            "",
            f"## Against the true maps (texels seen by ≥ {k} cameras)",
            "",
            "The baseline knows nothing: every texel gets the true map's median.",
            "",
        ]
        lines += _table(r["regions"], r["baseline"], r["scored_texels"]) + ["", "![truth | fit | error](maps_vs_truth.png)"]
    if r["relight"]:
        lines += ["", "## Relighting the held-out lighting with the fitted maps (one bounce)", ""]
        lines += ["Display PSNR and brightness error over the subject (docs/accuracy.md, one comparison for every report).", ""]
        lines += ["| cameras | images | PSNR (dB) | brightness | mean L1 |", "|---|---|---|---|---|"]
        lines += [
            f"| {c} | {v['images']} | {v['psnr']:.2f} | {100 * v['brightness']:+.1f} % | {v['l1']:.5f} |" for c, v in r["relight"].items()
        ]
    lines += ["", "## Convergence (time to error)", "", "![convergence](convergence.png)", ""]
    lines += [f"| time (s) | mean L1 ({r['loss_measure']}) | stage |", "|---|---|---|"]
    lines += [f"| {t:.1f} | {loss:.5f} | {name} |" for t, loss, name in r["loss_curve"]]
    if r["map_curve"]:
        lines += ["", "| time (s) | roughness MAE | albedo median relative error |", "|---|---|---|"]
        lines += [f"| {t:.1f} | {rough:.4f} | {a:.4f} |" for t, rough, a in r["map_curve"]]
    lines += ["", "## Per view (mean L1)", "", "| view | L1 |", "|---|---|"]
    lines += [f"| {view} | {v:.5f} |" for view, v in sorted(r["per_view_l1"].items())]
    return "\n".join(lines) + "\n"
