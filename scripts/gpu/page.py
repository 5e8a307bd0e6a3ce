"""docs/results/gpu.md from the GPU check's run folder and the CPU's (scripts/gpu_check.sh writes both): the CUDA
tests, the tiny demo's stages, benchmarks/stages.py and an Adam step (benchmarks/fit_step.py), each GPU figure
beside the CPU's, and the paper's H100 runtime table where it has the stage.

    python scripts/gpu/page.py --run RUN_DIR [--beside CPU_RUN_DIR] [--write docs/results/gpu.md]
"""

from __future__ import annotations

import argparse
import json
import xml.etree.ElementTree as ElementTree
from datetime import date
from pathlib import Path

PAPER_H100_MS = {"microfacet": 404.6, "relightnet": 25.4}  # Supp. "Runtime": per frame at 1024×540
LOG_LINES = 15  # of a failed part's log, on the page
PAPER_TOTAL = "VAE encoding 140.2, video model 840.3, VAE decoding 145.6; total 1556.2 ms per frame"


def read_run(folder: Path | None) -> dict:
    """What one check left in its folder; a part that is missing or unreadable (a run cut short) is empty, and
    ``unreadable`` names it: the page is written whatever the run left."""
    if folder is None or not folder.is_dir():
        return {}
    run = {"env": _read(folder / "env.txt", str, ""), "unreadable": [], "logs": {}}
    run["parts"] = {}
    for line in _read(folder / "parts.tsv", str, "").splitlines():
        try:
            name, rc, seconds, limit = line.split("\t")
            run["parts"][name] = {"rc": int(rc), "seconds": int(seconds), "limit": int(limit)}
        except ValueError:
            run["unreadable"].append(f"parts.tsv line {line!r}")
            continue
        if run["parts"][name]["rc"] != 0:  # what it said last: the page carries the error, not only the archive
            run["logs"][name] = _read(folder / f"{name}.log", str, "").rstrip().splitlines()[-LOG_LINES:]
    for name in ("demo", "stages"):
        run[name] = _read(folder / f"{name}.json", json.loads, {}, run["unreadable"])
    run["tests"] = _read(folder / "tests.xml", read_junit, {}, run["unreadable"])
    run["fit_step"] = _read(folder / "fit_step.md", str, "")
    return run


def _read(path: Path, parse, default, unreadable: list | None = None):
    if not path.is_file():
        return default
    try:
        return parse(path.read_text(errors="replace"))
    except (ValueError, ElementTree.ParseError) as error:
        if unreadable is not None:
            unreadable.append(f"{path.name} ({error})")
        return default


def read_junit(text: str) -> dict:
    root = ElementTree.fromstring(text)
    suites = [root] if root.tag == "testsuite" else list(root)
    counts = {key: sum(int(s.get(key, 0)) for s in suites) for key in ("tests", "failures", "errors", "skipped")}
    counts["seconds"] = sum(float(s.get("time", 0)) for s in suites)
    counts["failed"] = [
        (f"{case.get('classname')}::{case.get('name')}", (bad.get("message") or "").splitlines()[0][:200] if bad.get("message") else "")
        for s in suites
        for case in s.iter("testcase")
        for bad in [*case.findall("failure"), *case.findall("error")]
    ]
    return counts


def tests_section(gpu: dict, cpu: dict) -> list[str]:
    lines = ["## Tests: the CUDA variant of every variant-parametrised test", ""]
    t, c = gpu.get("tests"), cpu.get("tests")
    if not t:
        return lines + [f"No test report ({part_said(gpu, 'tests')}).", ""]
    passed = t["tests"] - t["failures"] - t["errors"] - t["skipped"]
    lines.append(
        f'`pytest -m "not slow" -k cuda_ad_rgb`: **{passed} passed, {t["failures"]} failed, {t["errors"]} errors, '
        f"{t['skipped']} skipped** in {t['seconds']:.0f} s ({part_said(gpu, 'tests')})."
    )
    if c:
        cpu_passed = c["tests"] - c["failures"] - c["errors"] - c["skipped"]
        lines.append(
            f"The same tests' `llvm_ad_rgb` twins on the CPU: {cpu_passed} passed, {c['failures'] + c['errors']} failed, in {c['seconds']:.0f} s."
        )
    lines.append("")
    if t["failed"]:
        lines += ["| failed | message |", "|---|---|"] + [f"| `{name}` | {message} |" for name, message in t["failed"]] + [""]
    return lines


def demo_section(gpu: dict, cpu: dict) -> list[str]:
    lines = ["## The tiny demo end to end (`gra-mi demo --preset tiny`)", ""]
    g, c = gpu.get("demo") or {}, cpu.get("demo") or {}
    lines.append(f"GPU: {part_said(gpu, 'demo')}; CPU: {part_said(cpu, 'demo')}.")
    for who, record in (("GPU", g), ("CPU", c)):
        by_reason: dict[str, list[str]] = {}
        for name, why in (record.get("not_made") or {}).items():
            by_reason.setdefault(why, []).append(f"`{name}`")
        for why, names in by_reason.items():
            lines.append(f"{who}, not made ({why}): {len(names)} file(s), {', '.join(names)}.")
    lines.append("")
    names = list(dict.fromkeys([*g.get("timings", {}), *c.get("timings", {})]))
    if names:
        lines += ["| stage | GPU s | CPU s | CPU / GPU |", "|---|---|---|---|"]
        for name in names:
            a, b = g.get("timings", {}).get(name), c.get("timings", {}).get(name)
            lines.append(f"| {name} | {seconds(a)} | {seconds(b)} | {ratio(b, a)} |")
        lines.append("")
    scores = [(split, stage) for split in ("novel lighting (envmap)",) for stage in ("microfacet", "relightnet")]
    for split, stage in scores:
        a, b = (r.get("relightnet", {}).get("splits", {}).get(split, {}).get(stage, {}).get("psnr") for r in (g, c))
        if a is not None and b is not None:
            lines.append(f"Held-out score, {stage} under novel envmaps: {a:.2f} dB on the GPU, {b:.2f} dB on the CPU.")
    return lines + [""]


def stages_section(gpu: dict, cpu: dict) -> list[str]:
    g, c = gpu.get("stages") or {}, cpu.get("stages") or {}
    lines = ["## Stages (`benchmarks/stages.py`)", ""]
    if not g:
        return lines + [f"No stage timings ({part_said(gpu, 'stages')}).", ""]
    lines += [f"GPU: {g.get('device')}. CPU: {c.get('device', 'not measured')}. Medians of repeated calls, ms.", ""]
    cpu_rows = {r["stage"]: r for r in c.get("stages", [])}
    lines += ["| stage | GPU | CPU | CPU / GPU | paper (H100) | note |", "|---|---|---|---|---|---|"]
    for row in g.get("stages", []):
        other = cpu_rows.get(row["stage"], {})
        paper = PAPER_H100_MS.get(row.get("paper"))
        lines.append(
            f"| {row['stage']} | {cell(row)} | {cell(other)} | {ratio(other.get('ms'), row.get('ms'))} | "
            f"{'' if paper is None else f'{paper:.1f}'} | {row.get('note', '')} |"
        )
    return lines + ["", f"The paper's other rows (no gra-mi stage is timed against them here): {PAPER_TOTAL}.", ""]


def fit_step_section(gpu: dict, cpu: dict) -> list[str]:
    """benchmarks/fit_step.py's tables (an Adam step, views joined or one kernel per view) on the GPU and the CPU."""
    lines = ["## An Adam step of the fit (`benchmarks/fit_step.py`, the tiny demo's capture)", ""]
    for who, run in (("GPU", gpu), ("CPU", cpu)):
        table = [line for line in run.get("fit_step", "").splitlines() if line.startswith("|")]
        lines += [f"{who}:", "", *table] if table else [f"{who}: no table ({part_said(run, 'fit_step')})."]
        lines.append("")
    return lines


def failed_logs(gpu: dict) -> list[str]:
    lines = []
    for name, tail in gpu.get("logs", {}).items():
        lines += [f"### The end of `{name}.log` ({part_said(gpu, name)})", "", "```", *tail, "```", ""]
    return (["## What the failed parts said", ""] + lines) if lines else []


def part_said(run: dict, name: str) -> str:
    part = run.get("parts", {}).get(name)
    if part is None:
        return "not run"
    if part["rc"] in (124, 137):
        return f"stopped at its {part['limit']} s limit"
    return f"exit {part['rc']} after {part['seconds']} s"


def cell(row: dict) -> str:
    if "ms" in row:
        return f"{row['ms']:.1f}"
    return f"failed: {row['error']}" if "error" in row else (f"skipped: {row['skipped']}" if "skipped" in row else "—")


def seconds(value) -> str:
    return "—" if value is None else f"{value:.2f}"


def ratio(cpu, gpu) -> str:
    return "—" if not cpu or not gpu else f"{cpu / gpu:.1f}×"


def page(gpu: dict, cpu: dict, commit: str = "unknown") -> str:
    stamp = (gpu.get("stages") or {}).get("stamp") or f"commit {commit}, {date.today().isoformat()} (the stage benchmark did not run)"
    cpu_stamp = (cpu.get("stages") or {}).get("stamp") or "no CPU run beside it"
    lines = [
        "# Results: on a GPU",
        "",
        f"Generated by `scripts/gpu_check.sh` (GPU: {stamp}; CPU: {cpu_stamp}).",
        "",
        "```",
        gpu.get("env", ""),
        "```",
        "",
    ]
    for who, run in (("GPU", gpu), ("CPU", cpu)):
        if run.get("unreadable"):
            lines += [f"{who} run, unreadable (cut short?): {'; '.join(run['unreadable'])}.", ""]
    lines += tests_section(gpu, cpu) + demo_section(gpu, cpu) + stages_section(gpu, cpu) + fit_step_section(gpu, cpu) + failed_logs(gpu)
    return "\n".join(lines).rstrip() + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, required=True, help="The GPU check's run folder (scripts/gpu_check.sh).")
    parser.add_argument("--beside", type=Path, default=None, help="The CPU check's run folder (bash scripts/gpu_check.sh --cpu).")
    parser.add_argument("--commit", default="unknown", help="The commit the GPU run was of (for a run whose stamp is missing).")
    parser.add_argument("--write", type=Path, default=None, help="Write the page here (else print it).")
    args = parser.parse_args()
    text = page(read_run(args.run), read_run(args.beside), args.commit)
    if args.write is None:
        print(text)
    else:
        args.write.write_text(text)
        print(f"wrote {args.write}")


if __name__ == "__main__":
    main()
