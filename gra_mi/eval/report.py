"""The evaluation's report: eval.json's record rendered as Markdown (the per-stage table, the notes under it, the
protocol in one paragraph) and CSV. :mod:`gra_mi.eval.protocol` computes the record; this only reads it, so the demo's
page renders the same tables from a stored record."""

from __future__ import annotations

import csv
import io
from collections.abc import Callable

import numpy as np

STAGE_TITLES = {
    "microfacet": "microfacet (fitted maps)",
    "RelightNet": "+ RelightNet",
    "refined": "+ video refiner",
    "deflickered": "+ flicker correction",
}
STAGES = tuple(STAGE_TITLES)  # in the order they run
UNCHANGED = 1e-3  # a stage whose frames differ from its input's by less (relative mean |Δ|) delivered its input

METRICS: list[tuple[str, str, Callable[[float], str]]] = [
    ("psnr", "PSNR ↑", lambda v: f"{v:.2f}"),
    ("ssim", "SSIM ↑", lambda v: f"{v:.3f}"),
    ("flip", "ꟻLIP ↓", lambda v: f"{v:.3f}"),
    ("lpips", "LPIPS ↓", lambda v: f"{v:.3f}"),
    ("temporal", "temporal ↓", lambda v: f"{100 * v:.2f}"),
]
WIDE_SPLITS = 2  # more splits than this: one column group of their means, and a per-split table below


def _metrics(report: dict) -> list[tuple[str, str, Callable]]:
    return [m for m in METRICS if m[0] != "lpips" or report["protocol"]["lpips"]]


def _split_means(stages: dict, splits: list[str]) -> dict:
    """Each stage's metrics averaged over the splits, for stages scored on all of them."""
    means = {}
    for stage, result in stages.items():
        scored = [result["splits"].get(s) for s in splits]
        if all(m and "skipped" not in m for m in scored):
            numbers = [k for k, v in scored[0].items() if isinstance(v, int | float)]
            means[stage] = {k: float(np.mean([m[k] for m in scored])) for k in numbers}
            if _unchanged(result):
                means[stage]["unchanged_from"] = _unchanged(result)
    return means


def eval_table(report: dict) -> tuple[list[str], list[str]]:
    """The Table-2-like Markdown table (rows: stages; columns: metrics × splits, FVD, time; with more than
    ``WIDE_SPLITS`` splits, metrics × their mean, then one row per stage and split) and the notes on what was skipped
    and why."""
    protocol, stages = report["protocol"], report["stages"]
    splits, metrics = list(protocol["splits"]), _metrics(report)
    notes = []
    for stage, result in stages.items():
        for split in splits:
            scored = result["splits"].get(split)
            if scored and "skipped" in scored:
                notes.append(f"- {STAGE_TITLES[stage]}, {split}: skipped: {scored['skipped']}")
            elif scored is None and result["status"] == "done":
                notes.append(f"- {STAGE_TITLES[stage]}, {split}: no output for this sequence")
        if result["status"] != "done":
            notes.append(f"- {STAGE_TITLES[stage]}: {result['status']}")
        if _unchanged(result):
            notes.append(
                f"- {STAGE_TITLES[stage]}: delivered its input ({STAGE_TITLES[_unchanged(result)]}) unchanged on every split "
                f"(mean difference below {UNCHANGED:.1%}): its row repeats its input's numbers"
                + (" (the refiner's mix is 0: refine.json)" if stage == "refined" else "")
            )
    notes += [f"- problem: {p}" for p in report["problems"]]
    if len(splits) <= WIDE_SPLITS:
        return _wide_table(stages, splits, metrics, protocol["fvd"]), notes
    label = f"mean of {len(splits)} splits"
    means = _split_means(stages, splits)
    table = _wide_table(
        {s: {**r, "splits": {label: means[s]} if s in means else {}} for s, r in stages.items()}, [label], metrics, protocol["fvd"]
    )
    table += ["", "| stage | split | " + " | ".join(label for _, label, _ in metrics) + " |", "|---|---|" + "---|" * len(metrics)]
    for stage, result in stages.items():
        for split in splits:
            m = result["splits"].get(split)
            if m and "skipped" not in m:
                table.append(f"| {STAGE_TITLES[stage]} | {split} | " + " | ".join(_cell(m, k, fmt) for k, _, fmt in metrics) + " |")
    return table, notes


def _unchanged(result: dict) -> str | None:
    """The stage whose frames this one delivered unchanged on every scored split, or None."""
    sources = {m.get("unchanged_from") for m in result["splits"].values() if "skipped" not in m}
    return next(iter(sources)) if len(sources) == 1 and None not in sources else None


def _title(stage: str, result: dict) -> str:
    return STAGE_TITLES[stage] + (" (= its input, unchanged)" if _unchanged(result) else "")


def _cell(scored: dict | None, key: str, fmt: Callable[[float], str]) -> str:
    return fmt(scored[key]) if scored and key in scored and np.isfinite(scored[key]) else "–"


def _wide_table(stages: dict, splits: list[str], metrics, fvd: bool) -> list[str]:
    header = ["stage"] + [f"{split} {label}" if k == 0 else label for split in splits for k, (_, label, _) in enumerate(metrics)]
    header += ["FVD ↓"] if fvd else []
    header.append("s / frame")
    lines = ["| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
    for stage, result in stages.items():
        cells = [_title(stage, result)] + [_cell(result["splits"].get(split), key, fmt) for split in splits for key, _, fmt in metrics]
        if fvd:
            cells.append(f"{result['fvd']:.1f} ({result['fvd_clips']} clips)" if result.get("fvd") is not None else "–")
        cells.append(f"{result['seconds_per_frame']:.2f}" if result.get("seconds_per_frame") else "–")
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def protocol_said(report: dict) -> str:
    """One paragraph: what was scored, how, at which size."""
    protocol = report["protocol"]
    scored = next(iter(protocol["splits"].values()))
    frames = (
        f"{_frames_said(protocol['frames'])} ({scored['frames']} frames per sequence, {len(scored['scored'])} scored)"
        if not all(s.get("lighting_set") for s in protocol["splits"].values())
        else "every lighting of each held-out set (a static pose: "
        + "–".join(
            str(n)
            for n in sorted({min(s["frames"] for s in protocol["splits"].values()), max(s["frames"] for s in protocol["splits"].values())})
        )
        + " lightings per split)"
    )
    tall = [s["subject_pixels"] for s in protocol["splits"].values() if "subject_pixels" in s]
    least, most = (min(t[0] for t in tall), max(t[1] for t in tall)) if tall else (0, 0)
    tall_said = f", the subject {least}–{most} pixels tall" if least < most else f", the subject {most} pixels tall" if tall else ""
    return (
        f"Held-out cameras under the held-out lighting, at {protocol['resolution'][0]}×{protocol['resolution'][1]} "
        f"(capture images × {protocol['scale']:.3g}{tall_said}). Per-frame metrics on {frames}; the temporal error on every consecutive pair"
        + ("; FVD on all 17-frame clips" if protocol["fvd"] else "")
        + ". One mask per frame for every stage: the truth's alpha ≥ 0.5. PSNR, SSIM, ꟻLIP"
        + (", LPIPS" if protocol["lpips"] else "")
        + " on display values at the truth's exposure; temporal: mean |Δframe − Δtruth| in % of the display range "
        "(docs/evaluation.md). s / frame: render time (the microfacet render includes each frame's visibility trace, "
        "which RelightNet then reuses), the refiner's rollout."
    )


def eval_markdown(report: dict) -> str:
    protocol = report["protocol"]
    lines, notes = eval_table(report)
    text = ["# Evaluation: every stage against the truth", "", protocol_said(report), "", *lines, ""]
    if notes:
        text += ["Skipped, and why:", "", *notes, ""]
    if not protocol["lpips"]:
        text.append("LPIPS: not measured (give `--lpips-weights`). ")
    if not protocol["fvd"]:
        text.append("FVD: not measured (give `--i3d-weights`).")
    text.append("")
    for s, about in protocol["splits"].items():
        gaps = f" ({len(about['missing'])} more without an image, left out)" if about.get("missing") else ""
        text.append(
            f"- {s}: camera {about['camera']}, lighting {about['lighting']}, {about['frames']} frames{gaps}, truth {about['truth']}"
        )
    for s, why in protocol.get("unscored", {}).items():
        text.append(f"- {s}: not scored: {why}")
    text.append("")
    for s in protocol["splits"]:
        videos = f"[videos/{s}.mp4](videos/{s}.mp4)"
        if s in protocol.get("composited", []):
            videos += f", over the environment on a platform: [videos/{s}_composite.mp4](videos/{s}_composite.mp4)"
        text.append(f"{s}: truth | each stage, ꟻLIP below: ![contact sheet](contact_{s}.png) · side by side: {videos}")
    return "\n".join(text) + "\n"


def _frames_said(how: str) -> str:
    return {
        "every10": "every 10th frame (the paper's protocol)",
        "window-middles": "the middle frame of each 17-frame refiner window",
        "all": "every frame",
    }[how]


def eval_csv(report: dict) -> str:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(
        ["stage", "split", "status", "psnr", "ssim", "brightness", "flip", "lpips", "temporal", "frames_scored", "fvd", "seconds_per_frame"]
    )
    for stage, result in report["stages"].items():
        if not result["splits"]:
            writer.writerow([stage, "", result["status"]] + [""] * 9)
        for split, m in result["splits"].items():
            writer.writerow(
                [stage, split, m.get("skipped", result["status"])]
                + [m.get(k, "") for k in ("psnr", "ssim", "brightness", "flip", "lpips", "temporal", "frames_scored")]
                + [result.get("fvd") or "", result.get("seconds_per_frame") or ""]
            )
    return buffer.getvalue()
