"""The import report (``import_report.{json,md}`` and an overlay per camera): what a user reads first of an import
(:func:`gra_mi.capture.importer.import_capture` writes it last, from what the import measured on the way)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gra_mi.capture.placement import CameraPlan, WorldFrame, mask_at_source
from gra_mi.capture.source import Source
from gra_mi.capture.source_files import read_image
from gra_mi.core.io import atomic_write_text, read_exr, write_png
from gra_mi.core.progress import threaded

FEW_PLACED = 4  # fewer cameras placed by --align-cameras: said (docs/results/align-cameras.md)
STEADY_CHANGE = 0.05  # full-bright frames this far apart: the subject moved, or the LEDs drifted, during the OLATs


def _linearity_of_a_complete_camera(out: Path, source: Source, plans: list[CameraPlan], first: int, workers: int) -> dict | None:
    """:func:`linearity` of the first camera with its white frame and every OLAT (a gap would bias the sum)."""
    if source.olat_keys is None or source.white is None:
        return None
    wanted = [source.white, *source.olat_keys]
    plan = next((p for p in plans if all(k in source.images[p.index] for k in wanted)), None)
    if plan is None:
        return None
    return linearity(source, plan, read_exr(out / "images" / plan.camera.name / f"frame_{first:04d}.exr")[..., 3], workers)


def linearity(source: Source, plan: CameraPlan, mask: np.ndarray, workers: int) -> dict:
    """The white frame against the sum of every OLAT (door LEDs included) of one camera, over the subject: 1 for a
    linear sensor and a subject that held still (each LED's gain is in both). Beside it, how many distinct values a
    single OLAT takes there (its median): an 8-bit OLAT's truth is only as fine as its levels; and how steady the
    frames lit alike through the OLATs stay (:func:`_steadiness`)."""
    inside = mask_at_source(mask, plan) > 0.5
    total, levels = np.zeros(int(inside.sum()) * 3), []

    def read(number: int) -> tuple[np.ndarray, int]:
        pixels = read_image(source.images[plan.index][number])[0][inside].ravel()
        return pixels, len(np.unique(pixels))  # counted in the reading thread

    for pixels, count in threaded(read, list(source.olat_keys), f"linearity {plan.camera.name}", workers):
        total += pixels  # summed in order: the same sum whatever the threads
        levels.append(count)
    white = read_image(source.images[plan.index][source.white])[0][inside].ravel()
    ratio = float(total.sum() / max(white.sum(), 1e-12))
    found = {"camera": plan.camera.name, "olats_over_white": ratio, "olats": len(source.olat_keys), "olat_levels": float(np.median(levels))}
    return found | _steadiness(source, plan, inside)


def _steadiness(source: Source, plan: CameraPlan, inside: np.ndarray) -> dict:
    """How far the frames lit alike all through the OLATs (HumanOLAT's full-bright frames) stray from the first of
    them over the subject (relative RMS): a subject that moved, or LEDs that drifted, during the OLATs shows here."""
    keys = [k for k in source.steady_keys or [] if k in source.images[plan.index]]
    if len(keys) < 2:
        return {}
    first = read_image(source.images[plan.index][keys[0]])[0][inside]
    change = {k: float(np.sqrt(np.mean((read_image(source.images[plan.index][k])[0][inside] - first) ** 2)) / np.sqrt(np.mean(first**2)))
              for k in keys[1:]}  # fmt: skip
    worst = max(change, key=change.get)
    return {"steady_frames": len(keys), "steady_change": change[worst], "steady_worst": worst}


def write_report(
    out: Path, source: Source, frame: WorldFrame, plans: list[CameraPlan], checks: list[dict], record: dict, workers: int
) -> None:
    """import_report.json and .md, and an overlay per camera (mask green, reprojected mesh magenta, both white);
    ``workers``: threads that read the linearity check's images."""
    check_of = {c["camera"]: c for c in checks}
    first = record["checked_frame"]  # the frame the reprojection check compared the masks on
    for plan in plans:
        mask = read_exr(out / "images" / plan.camera.name / f"frame_{first:04d}.exr")[..., 3] > 0.5
        seen = check_of[plan.camera.name]["silhouette"]
        overlay = np.stack([seen.astype(float), mask.astype(float), seen.astype(float)], axis=-1)
        write_png(out / "import" / f"overlay_{plan.camera.name}.png", overlay, exposure=1.0)
    report = {
        "cameras": [{"camera": c["camera"], "mask_iou": round(c["iou"], 4)} | record["images"][c["camera"]] for c in checks],
        "frame": {
            "transform": frame.matrix(),
            "up_source": frame.up_source.round(6).tolist(),
            "up_estimated": frame.up_estimated,
            "up_off_axis_deg": round(frame.up_off_axis_deg, 3),
            "led_sphere_radius_m": round(frame.led_radius, 4),
            "led_sphere_rms_m": round(frame.led_fit_rms, 5),
        },
        "leds": {
            "count": len(source.leds),
            "left_out": record["left_out_leds"],
            "gains": record["gains"],
            "intensity": record.get("led_intensity"),
            "estimate": record.get("gain_estimate"),
        },
        "solved_frames": record.get("solved_frames", []),
        "linearity": _linearity_of_a_complete_camera(out, source, plans, first, workers),
        "frames": {"imported": sum(1 for _ in (out / "images" / plans[0].camera.name).glob("frame_*.exr"))},
        "uv_atlas": record["uv_atlas"],
        "set": [shape.label for shape in source.set_shapes],
        "alignment": _alignment(source),
    }
    atomic_write_text(out / "import_report.json", json.dumps(report, indent=1) + "\n")
    atomic_write_text(out / "import_report.md", import_markdown(report, source.format))


def _alignment(source: Source) -> dict | None:
    """How --align-cameras moved the calibration (in the places' units), with how closely the cameras land in metres."""
    if source.alignment is None:
        return None
    return source.alignment | {f"{k}_m": source.alignment[k] * source.units for k in ("rms", "max")}


def import_markdown(r: dict, source_format: str) -> str:
    f, leds = r["frame"], r["leds"]
    lines = [
        "# Import report",
        "",
        f"Source: {source_format}. {len(r['cameras'])} cameras, {r['frames']['imported']} lightings each; {leds['count']} "
        f"LEDs, the OLATs of {len(leds['left_out'])} left out; LED gains {leds['gains']}"
        + (f"; a fully driven LED's intensity {leds['intensity']}" if leds.get("intensity") else "")
        + f". UV atlas: {r['uv_atlas']}.",
        "",
        f"Up in the source: {f['up_source']} ({'estimated from the cameras' if f['up_estimated'] else 'given'}, "
        f"{f['up_off_axis_deg']:.2f}° off its nearest axis). LED sphere: radius {f['led_sphere_radius_m']:.3f} m, the LEDs "
        f"within {1000 * f['led_sphere_rms_m']:.1f} mm RMS of it. The transform into gra-mi's frame (Y up, metres) is in "
        "capture.json (`source.transform`).",
        "",
        "| camera | mesh over mask (IoU) | saturated (subject, most of any image; left out of the fit) | fx / fy | square-pixel resampling error | lens distortion undone |",
        "|---|---|---|---|---|---|",
    ]
    for c in r["cameras"]:
        error = "—" if c["resampling_error"] is None else f"{100 * c['resampling_error']:.2f} %"
        lens = (
            "—" if c.get("lens") is None else f"{c['lens']['model']}; the source holds {100 * c['lens']['held']:.1f} % of the pinhole image"
        )
        lines.append(
            f"| {c['camera']} | {c['mask_iou']:.3f} | {100 * c['saturated_fraction']:.2f} % | {c['anisotropy']:.4f} | {error} | {lens} |"
        )
    if a := r.get("alignment"):
        lines += ["", f"The calibration moved into the LEDs' frame by {len(a['cameras'])} cameras' places ({a['file']}): scaled "
                  f"{a['scale']:.6g}×, turned {a['rotation_deg']:.2f}°; they land within {1000 * a['rms_m']:.2f} mm RMS, "
                  f"{1000 * a['max_m']:.2f} mm at most, of their places"
                  + ("; the mesh moved with it (--mesh-frame calibration)." if a["mesh_moved"] else ".")]  # fmt: skip
        if len(a["cameras"]) < FEW_PLACED:
            lines[-1] += (f" Only {len(a['cameras'])} cameras placed: their places' errors grow several times over the rig, "
                          "and two names swapped may pass; place 6 or more, spread over it (docs/results/align-cameras.md).")  # fmt: skip
    if r.get("set"):
        lines += ["", f"The set (the scene's other shapes, in scene.xml as set_000 …): {', '.join(r['set'])}. They shadow the subject "
                  "and hide it from the cameras in every later stage; the light they reflect onto it is not modelled."]  # fmt: skip
    gaps = [
        f"{c['camera']} ({len(c['missing_frames'])}: {', '.join(map(str, c['missing_frames'][:8]))}{' …' if len(c['missing_frames']) > 8 else ''})"
        for c in r["cameras"]
        if c.get("missing_frames")
    ]
    if gaps:
        lines += ["", f"Missing images, skipped (--missing-images skip; the frames in capture.json say which): {'; '.join(gaps)}."]
    if turned := [f"{c['camera']} ({c['exif_turned']})" for c in r["cameras"] if c.get("exif_turned")]:
        lines += [
            "",
            f"Images with an EXIF orientation tag, read as stored (as COLMAP calibrates them): {', '.join(turned)}. A mask file "
            "that fits the mesh says nothing of how the images are turned: look at one of their imported images.",
        ]
    if (estimate := leds.get("estimate")) is not None:
        lines += [
            "",
            f"LED gains estimated in {estimate['rounds']} rounds ({estimate['seconds']:.0f} s): the one-bounce model's relative L1 on "
            f"the texels several LEDs light, {100 * estimate['relative_l1']['equal gains']:.1f} % with equal gains, "
            f"{100 * estimate['relative_l1']['estimated']:.1f} % with these. Not measured (kept 1): "
            f"{', '.join(map(str, estimate['unmeasured_leds'])) or 'none'}. ![LED gains](import/led_gains.png)",
        ]
        if estimate["suspect_leds"]:
            lines += [
                "",
                f"**Check the light order or positions**: the OLATs of LEDs {', '.join(map(str, estimate['suspect_leds']))} are lit "
                "elsewhere than their positions say (the model's L1 on them is several times the other LEDs'). A mixed-up firing "
                "order or LED file spoils the fit wherever they light.",
            ]
    lines += _solved_frames_lines(r.get("solved_frames", []))
    lines += _linearity_lines(r["linearity"])
    lines += [
        "",
        "Overlays (green: the mask, magenta: the mesh reprojected, white: both): "
        + " ".join(f"![{c['camera']}](import/overlay_{c['camera']}.png)" for c in r["cameras"]),
    ]
    return "\n".join(lines) + "\n"


def _linearity_lines(lin: dict | None) -> list[str]:
    """The linearity check (the OLATs' sum over the white frame) and, where the source has them, the full-bright frames'
    steadiness through the OLATs."""
    if lin is None:
        return []
    lines = [
        "",
        f"Linearity ({lin['camera']}): the sum of the {lin['olats']} OLATs over the white frame is {lin['olats_over_white']:.3f} "
        "over the subject (1: a linear sensor and a subject that held still, whatever the LEDs' gains). A single OLAT "
        f"takes a median of {lin['olat_levels']:.0f} distinct values there: held-out OLATs are only as fine a truth as that "
        "(docs/results/envmap-frames.md measures what that costs a synthetic pose).",
    ]
    if "steady_change" in lin:
        moved = lin["steady_change"] > STEADY_CHANGE
        lines += [
            "",
            f"{'**Moved or drifted**: ' if moved else ''}the {lin['steady_frames']} full-bright frames through the OLATs differ from "
            f"the first by up to {100 * lin['steady_change']:.1f} % (image {lin['steady_worst']:06d}) over the subject"
            + (": the subject moved or the LEDs drifted during the OLATs, which the fit takes for one still pose." if moved else "."),
        ]
    return lines


def _solved_frames_lines(rows: list[dict]) -> list[str]:
    """The frames whose drive was solved (--envmap-frames, --gradient-frames): how much of each frame its OLATs
    explain, what was subtracted."""
    if not rows:
        return []
    lines = [
        "",
        f"Frames lit by many LEDs at once, each one's LED drive solved from the OLATs on {', '.join(rows[0]['cameras'])}"
        " (held-out lighting, a test sequence per kind). ![drives](import/solved_drives.png)",
        "",
        "| image | frame (test sequence) | lit by | unexplained by its OLATs | light of LEDs outside the rig (subtracted) | mean drive (r, g, b; 1 = an OLAT's) |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        left = f" — **left out**: {row['left_out']}" if "left_out" in row else ""
        drive = ", ".join(f"{v:.3f}" for v in row["drive_mean"])
        lines.append(
            f"| {row['image']:06d} | {row['frame']} ({row['sequence']}){left} | {row['what']} | {100 * row['residual']:.1f} % "
            f"| {100 * row['outside_share']:.1f} % | {drive} |"
        )
    if unseen := rows[0]["unseen"]:
        lines += ["", f"LEDs no solving camera sees lit (drive 0, unknown): {', '.join(map(str, unseen))}."]
    return lines
