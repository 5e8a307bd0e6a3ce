"""The demo's report.md, rendered from its record (demo.json), which is composed of the stages' own records: the
evaluation (eval.json), the fit (fit.json), RelightNet's validation (validation.json), the refiner's rollout
(refine.json + train.json), the lighting models (accuracy.json) and the capture's measurements (capture.json).
Nothing here computes a metric."""

from __future__ import annotations

import math

from gra_mi.core.stamp import stamp_said
from gra_mi.eval.lighting import accuracy_table
from gra_mi.eval.report import eval_table, protocol_said

NAN = float("nan")


def demo_markdown(record: dict) -> str:
    sections = (_header, _stages, _fit, _relightnet, _refiner, _lighting, _noise, _fidelity, _files)
    if "refiner" not in record:  # the static-pose (OLAT) demo: no video stages, no reference-map lighting models
        sections = (_header, _stages, _fit, _relightnet, _noise, _files)
    return "\n".join(line for section in sections for line in section(record)) + "\n"


def _not_made_said(r: dict) -> list[str]:
    """The outputs this machine could not make (their links below lead nowhere), or nothing."""
    not_made = r.get("not_made") or {}
    if not not_made:
        return []
    return ["**Not made on this machine:** " + "; ".join(f"`{name}`: {why}" for name, why in not_made.items()) + ".", ""]


def _header(r: dict) -> list[str]:

    rig, subject, evaluation = r["capture"]["rig"], r["capture"]["subject"], r["eval"]
    table, notes = eval_table(evaluation)
    first_split = next(iter(evaluation["protocol"]["splits"]))
    return [
        f"# gra-mi demo — preset `{r['preset']['name']}`",
        "",
        f"Mitsuba variant `{r['runtime']['variant']}`. Capture: {rig['leds']} LEDs on a {rig['radius']:.1f} m sphere, "
        f"{rig['cameras']} cameras ({rig['width']}×{rig['height']}; held out: {', '.join(r['capture']['eval_cameras'])}); "
        f"subject: {subject['vertices']} vertices, {subject['triangles']} triangles, {subject['frames']} frames "
        f"({', '.join(subject['clips'])}); ground truth: `{r['capture']['renderer']}`.",
        "",
        *_not_made_said(r),
        "## Every stage against the truth (`gra-mi eval`)",
        "",
        protocol_said(evaluation) + " Details: [eval/eval.md](eval/eval.md).",
        "",
        *table,
        "",
        *notes,
        "",
        f"Truth | each stage, ꟻLIP error below: ![contact sheet](eval/contact_{first_split}.png)",
        "",
        *_composite_said(r),
    ]


def _composite_said(r: dict) -> list[str]:
    if "video" not in r:
        return ["Each split's truth: " + "; ".join(f"{s}: {a['truth']}" for s, a in r["eval"]["protocol"]["splits"].items()), ""]
    return [
        "RelightNet's render of the held-out camera over the held-out environment, on a platform with the subject's shadow "
        f"(path-traced under the same environment): ![composite](composite.png) · video: [{r['video']}]({r['video']}) · "
        "every stage side by side, composited: [eval/videos/](eval/videos/)",
        "",
    ]


def _stages(r: dict) -> list[str]:
    lines = ["## Pipeline stages", "", "| stage | status | time (s) |", "|---|---|---|"]
    lines += [f"| {name} | done | {seconds:.1f} |" for name, seconds in r["timings"].items()]
    total = sum(r["timings"].values())
    lines += [f"| **all** | | **{total:.0f} ({total / 60:.1f} min)** |"]
    return lines + ["", "Rig: ![rig](plots/rig.png)", ""]


def _fit(r: dict) -> list[str]:
    fit = r["fit"]
    lines = [
        "## Material fit",
        "",
        "Full report: [fit/fit_report.md](fit/fit_report.md). ![albedo](fit/albedo.png) ![roughness](fit/roughness.png)",
        "",
    ]
    if fit.get("metrics"):
        ours, baseline = fit["metrics"], fit["baseline"]["all"]
        lines += ["| against the true maps (texels seen by ≥ 3 cameras) | fit | constant median (baseline) |", "|---|---|---|"]
        lines += [f"| {k} | {v:.4f} | {baseline[k]:.4f} |" for k, v in ours.items()]
    return lines + [
        "",
        "Held-out lighting: left the ground truth (the capture), right gra-mi's one-bounce relight with the fitted maps; rows:",
        "frames × cameras (training camera, then held-out camera), over the background plate. Scores: the table above.",
        "",
        "![truth vs relit](contact_truth_vs_relit.png)",
        "",
    ]


def _relightnet(r: dict) -> list[str]:
    v = r["relightnet"]
    rows = [
        f"| {split} | {m['microfacet']['views']} | {m['microfacet']['psnr']:.2f} | {m['microfacet']['ssim']:.4f} | "
        f"{100 * m['microfacet']['brightness']:+.1f} % | {m['relightnet']['psnr']:.2f} | {m['relightnet']['ssim']:.4f} | "
        f"{100 * m['relightnet']['brightness']:+.1f} % |"
        for split, m in v["splits"].items()
    ]
    return [
        "## RelightNet (ablation: microfacet only vs + RelightNet)",
        "",
        f"Weights kept: step {v['kept_step']} of {r['preset']['relightnet_steps']}, chosen on the selection views "
        f"(step 0 would be the microfacet render itself); output gain {v['output_gain']:.4f} (the training views' "
        "total light). Display PSNR, SSIM, and brightness Σ render / Σ truth − 1 over the subject.",
        "",
        "| split | views | microfacet PSNR | SSIM | brightness | + RelightNet PSNR | SSIM | brightness |",
        "|---|---|---|---|---|---|---|---|",
        *rows,
        "",
        "Validation during training: ![validation](relightnet/validation.png)",
        "",
        "Held-out views — ground truth | microfacet | RelightNet: ![grid](relightnet/grid.png)",
        "",
    ]


def _zoom_said(zoom: float) -> str:
    return "the subject's box at the delivered frames' own resolution" if zoom == 1 else f"{zoom:g}× the delivered frames"


def _cameras_said(preset: dict) -> str:
    count = preset.get("refiner_train_cameras")
    return "the training cameras" if not count else f"{count} of the training cameras"


def _refiner(r: dict) -> list[str]:
    f = r["refiner"]
    train, chosen = f["train"], f["train"]["mix"]["chosen"]
    return [
        "## Video refiner (tiny WAN2.1-VACE, CPU)",
        "",
        f"Fine-tuned {train['steps']} steps (LoRA, VACE and envmap layers: {train['parameters']['trainable']:,} of "
        f"{train['parameters']['total']:,} parameters) from the shipped tiny prior — a DiT pretrained on another subject "
        f"(`pipelines/pretrain_tiny_refiner.py`) — on RelightNet renders of {_cameras_said(r['preset'])}, seen as subject crops of "
        f"{f['size']} pixels ({_zoom_said(r['preset'].get('refiner_zoom', 4.0))}; the refined crop's change goes back into the "
        "frame), then rolled over "
        f"the held-out sequence `{f['sequence']}`: {f['frames']} frames in {f['windows']} windows of 17 "
        f"({f['steps']} Euler steps each, {f['frames_per_second']:.2f} frames/s).",
        "",
        "| against the ground truth (subject pixels of the delivered frames, display PSNR) | PSNR (dB) |",
        "|---|---|",
        f"| RelightNet render (the refiner's input) | {f.get('psnr_coarse', NAN):.2f} |",
        *([f"| the refiner's own output (mix 1) | {f['psnr_own_output']:.2f} |"] if "psnr_own_output" in f else []),
        f"| delivered: input + s·(refined − input), s = {chosen:g} chosen on the selection sequence | {f.get('psnr_refined', NAN):.2f} |",
        "| the ground truth through the tiny VAE alone (encode + decode: what the VAE by itself loses; goal ≥ 30) | "
        f"{f.get('psnr_vae_round_trip', NAN):.2f} |",
        "",
        f"Joins between windows: mean change into a new window {f['seam_jump']:.4f}, over its 5 handed-off frames "
        f"{f['join_frame_change']:.4f}, between all other consecutive frames {f['inner_frame_change']:.4f} "
        "(mean absolute change in [0, 1] display values). " + _refiner_verdict(f),
        "",
        f"Video (RelightNet | refined | ground truth): [comparison.mp4](refiner/refined/{f['sequence']}/comparison.mp4) · ",
        "loss: ![refiner loss](refiner/model/loss.png)",
        "",
        *_mix_table(train["mix"]),
    ]


def _refiner_verdict(refiner: dict) -> str:
    """What the refiner table says, in words (the goals: VAE round trip ≥ 30 dB, refined within 0.4 dB of its input)."""
    vae, coarse, refined = (refiner.get(k, NAN) for k in ("psnr_vae_round_trip", "psnr_coarse", "psnr_refined"))
    own, chosen = refiner.get("psnr_own_output", refined), refiner["train"]["mix"]["chosen"]
    said = [f"The tiny VAE {'keeps' if vae >= 30 else 'does not keep'} the image ({vae:.1f} dB; goal ≥ 30)."]
    if own < coarse - 0.4:
        said.append(
            f"The refiner's own output is {coarse - own:.1f} dB below its input (goal: within 0.4 dB): what the truth adds to "
            "the RelightNet render is mostly detail the tiny refiner cannot predict from this capture's few relit frames, "
            "so the detail it samples is its own (docs/results/limitations.md: the measurements and what it would take)."
        )
    if chosen == 0:
        said.append(
            "On the selection sequence no mix above 0 kept the PSNR within 0.4 dB of the input's with a ꟻLIP and "
            "temporal error no worse, so the refiner delivers its input unchanged."
        )
    else:
        within = "within" if refined >= coarse - 0.4 else "not within"
        said.append(f"The delivered video (mix {chosen:g}) is {within} 0.4 dB of its input ({refined - coarse:+.2f} dB).")
    return " ".join(said)


def _mix_table(mix: dict) -> list[str]:
    """The refiner's mix choice on the selection sequences (train.json), as report lines."""
    if "scores" not in mix:
        return [f"Mix 1: {mix.get('why', 'not chosen')}.", ""]
    rows = [
        f"Mix, chosen on the selection sequence ({', '.join(mix['sequences'])}: the held-out lighting on a training "
        f"camera, first window): PSNR at most {mix['psnr_budget']} dB below the input's (s = 0), ꟻLIP and temporal error "
        "no worse, then the lowest ꟻLIP. ![mix](refiner/model/mix.png)",
        "",
        "| mix | PSNR (dB) | ꟻLIP | temporal (%) |",
        "|---|---|---|---|",
    ]
    for row in mix["scores"]:
        kept = " (kept)" if row["mix"] == mix["chosen"] else ""
        rows.append(f"| {row['mix']:g}{kept} | {row['psnr']:.2f} | {row['flip']:.4f} | {100 * row['temporal']:.2f} |")
    return rows + [""]


def _lighting(r: dict) -> list[str]:

    return [
        "## Relighting under environments: lighting models against the path-traced truth",
        "",
        "Reproducing the capture (above) lights the subject as the stage did: near field. Relighting under an environment",
        "means the environment at infinity: far field, `gra-mi relight`'s default for envmaps. Here both, on reference",
        "maps with a sun, a studio, an interior and a night scene, against the true materials path-traced under each map",
        "(details: [lighting/accuracy.md](lighting/accuracy.md)).",
        "",
        *accuracy_table(r["lighting"]["rows"], r["lighting"]["summary"]),
        "",
        "Truth | near field | far field | far field with the true maps | RelightNet: ![lighting models](lighting/contact_sheet.png)",
        "",
        "## Near-field point light",
        "",
        "![point light](point_light.png) ![conditioning](point_light_conditioning.png)",
        "",
    ]


def _noise(r: dict) -> list[str]:
    truth = r["capture"]["ground_truth"]
    lines = [
        "## Ground-truth noise",
        "",
        "Relative RMS noise over the subject's pixels of one ground-truth image, against a render of the same view with "
        f"{_reference_said(truth)} (direct light from every LED: {truth.get('spp', '?')} spp; interreflections: "
        f"{truth.get('indirect_spp', '?')} spp"
        + (
            f"; the environment-lit training frames at {truth['relit_spp']} and {truth['relit_indirect_spp']} spp: training data, "
            "their unbiased noise averages out over many frames, while the scored frames keep the full counts"
            if "relit_spp" in truth
            else ""
        )
        + (
            f"; the held-out frames, which every score is measured against, at {truth['held_out_spp']} and "
            f"{truth['held_out_indirect_spp']} spp: their noise would cap each score and shrink each stage's gain"
            if "held_out_spp" in truth
            else ""
        )
        + ").",
        "",
        "| frame | lighting | samples (direct, indirect) | relative RMSE | s / image |",
        "|---|---|---|---|---|",
    ]
    if not truth.get("noise"):
        lines.append(f"| – | not measured: the `{r['capture']['renderer']}` ground truth | – | – | – |")
    for label, row in truth.get("noise", {}).items():
        lines.append(
            f"| {row['frame']} | {label} ({row['envmap'] or row.get('pattern') or 'all LEDs'}) | {_samples_said(row, truth)} | {100 * row['relative_rmse']:.2f} % "
            f"| {row['seconds_per_image']:.2f} |"
        )
    return lines + [""]


def _reference_said(truth: dict) -> str:
    factor = next(iter(truth.get("noise", {}).values()), {}).get("reference_factor")
    return "16× the samples" if factor is None else f"{factor}× the samples, its own noise divided out"


def _samples_said(row: dict, truth: dict) -> str:
    direct, indirect = row.get("spp", [truth.get("spp", "?"), truth.get("indirect_spp", "?")])  # older records: the capture's
    return f"{direct}, {indirect}"


def _fidelity(r: dict) -> list[str]:
    lines = [
        "## Envmap → LED fidelity (irradiance at the stage centre)",
        "",
        "Per-normal irradiance error of the LED mapping over 256 normals, next to the best non-negative LED intensities "
        "can do (NNLS on irradiance alone). Error relative to each normal's irradiance, floored at 5 % of the mean. "
        "Glossy: the same for a glossy lobe (about GGX roughness 0.35), where the irradiance optimum falls apart because it "
        "moves the light: why the barycentric mapping is the one used.",
        "",
        "| envmap | max | mean | NNLS optimum max | NNLS optimum mean | glossy mean | NNLS glossy mean |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, f in r["capture"]["ground_truth"].get("envmap_fidelity", {}).items():
        glossy = (100 * f.get(k, math.nan) for k in ("glossy_mean_rel_error", "optimum_glossy_mean_rel_error"))
        lines.append(
            f"| {name} | {100 * f['max_rel_error']:.2f} % | {100 * f['mean_rel_error']:.2f} % | "
            f"{100 * f['optimum_max_rel_error']:.2f} % | {100 * f['optimum_mean_rel_error']:.2f} % | "
            + " | ".join(f"{g:.1f} %" for g in glossy)
            + " |"
        )
    lines.append("")
    for name in r["led_mappings"]:
        lines += [f"LED mapping of {name}: ![LED mapping](plots/leds_{name}.png)", ""]
    return lines


def _files(r: dict) -> list[str]:
    video = f"Video: [{r['video']}]({r['video']}) · " if "video" in r else ""
    return [
        f"{video}Avatar: [avatar.usdz](avatar.usdz) (USD, with the rig's cameras) · [avatar.glb](avatar.glb) (glTF); "
        "both open in Blender (docs/export.md)",
        *(f"- {verdict}" for verdict in r.get("export", {}).values()),
        "",
        "Data: `capture/` (images, masks, true maps, `scene.xml` loads in plain Mitsuba), `fit/` (albedo.exr, roughness.exr),",
        "`renders/` (linear RGBA EXR), `demo.json` (this report's numbers, from the stages' own records).",
    ]


# --------------------------------------------------------------------------------------------------------------
# Published: the README's headline and docs/results/demo.md (scripts/publish_demo.py)
# --------------------------------------------------------------------------------------------------------------


def headline(record: dict) -> list[str]:
    """The evaluation table of a demo run, stamped: the README's results."""

    table, notes = eval_table(record["eval"])
    return [
        f"`gra-mi demo` ({stamp_said(record['stamp'])}): {protocol_said(record['eval'])}",
        "",
        *table,
        "",
        *notes,
    ]


def results_page(record: dict) -> str:
    """docs/results/demo.md: the headline, the fit, RelightNet, the refiner and the lighting models of one run."""
    sections = [_fit, _relightnet, _refiner, _lighting, _stages] if "refiner" in record else [_fit, _relightnet, _noise, _stages]
    title = "the demo" if "refiner" in record else f"the demo, preset `{record['preset']['name']}` (a static pose's reflectance field)"
    lines = [f"# Results: {title}", "", "> Generated by `scripts/publish_demo.py` from a `gra-mi demo` run's demo.json.", ""]
    lines += headline(record) + [""]
    for section in sections:
        lines += [line for line in section(record) if "![" not in line]  # the images stay in the run's folder
    return "\n".join(lines) + "\n"


def with_block(text: str, name: str, lines: list[str]) -> str:
    """``text`` with the lines between ``<!-- name -->`` and ``<!-- /name -->`` replaced."""
    start, end = f"<!-- {name} -->", f"<!-- /{name} -->"
    if start not in text or end not in text:
        raise ValueError(f"no {start} … {end} block to replace")
    head, rest = text.split(start, 1)
    return head + start + "\n" + "\n".join(lines) + "\n" + end + rest.split(end, 1)[1]
