"""How live `gra-mi view` is: the time from a change of lighting or viewpoint to the new image, on the server and as
the browser sees it.

The anny body in the default 331-LED rig at UV 512² (no fit: its own colours, roughness 0.5), a 512×288 view.
**Server**: :class:`gra_mi.apps.viewer.ViewerSession` alone — the lighting set, the texels shaded for the view's
camera, the texture rasterised (2×2 sub-samples), tone-mapped and JPEG-encoded as viser sends it; five changes of
each kind after the frame's visibility is cached (a new frame pays its trace once: shown too). **Browser**: the
page in headless Chromium (software WebGL) driven through its controls, from the key press or click to the new
view's timings line arriving (the image arrives just before it); where Chromium is not installed this part is
skipped and says so.

    .venv/bin/python benchmarks/viewer.py [--write docs/results/viewer.md]
"""

from __future__ import annotations

import io
import statistics
import time
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, run_benchmark, walking_scene

CHANGES = {  # what a viewer does, as lighting changes (value k: the k-th repetition)
    "new envmap": lambda k: {"mode": "envmap", "envmap": ("sun", "studio", "interior", "night")[k % 4]},
    "envmap rotation": lambda k: {"mode": "envmap", "rotation": float(15 * (k + 1))},
    "LED (OLAT) choice": lambda k: {"mode": "olat", "olat": 17 * (k + 1)},
    "point light moved": lambda k: {"mode": "point light", "point": (0.6 - 0.1 * k, 1.3, 0.6)},
}


def jpeg_ms(image: np.ndarray) -> float:
    from PIL import Image

    start = time.perf_counter()
    Image.fromarray(image).save(io.BytesIO(), format="JPEG", quality=92)
    return 1000 * (time.perf_counter() - start)


def server_rows(scene: Path, repeats: int = 5) -> list[dict]:
    from gra_mi.apps.viewer import ViewerSession, ViewSources, camera_pose, viewer_camera, with_lighting

    session = ViewerSession(ViewSources(scene=scene, uv_resolution=512))
    position, wxyz, fov = camera_pose(session.ls.stage.cameras[0])
    camera = viewer_camera(position, wxyz, fov, 512, 288)
    session.render(camera)  # the frame's visibility and the kernels: once
    rows = []
    frames = {"frame": {"mode": "envmap", "frame": 1}, "olat frame": {"mode": "olat", "olat": 17, "frame": 2}}
    rows_to_measure = [*CHANGES.items(), ("orbit (new viewpoint)", None), ("new frame (visibility traced)", "frame")]
    for name, change in [*rows_to_measure, ("new frame under an OLAT (its LED traced)", "olat frame")]:
        totals, parts = [], []
        for k in range(repeats if change not in frames else 1):
            start = time.perf_counter()
            if change in frames:
                with_lighting(session, **frames[change])
            elif change is not None:
                with_lighting(session, **change(k))
            view_camera = camera if change is not None else viewer_camera(position + np.array([0.1 * (k + 1), 0, 0]), wxyz, fov, 512, 288)
            view = session.render(view_camera)
            view.timings["jpeg"] = jpeg_ms(view.image)
            totals.append(1000 * (time.perf_counter() - start) + view.timings["jpeg"])
            parts.append(view.timings)
        with_lighting(session, mode="envmap", frame=0)
        parts_median = {p: statistics.median(t[p] for t in parts) for p in parts[0]}
        rows.append({"change": name, "total": statistics.median(totals), "spread": (min(totals), max(totals)), **parts_median})
    return rows


def browser_rows(scene: Path, repeats: int = 5) -> list[dict] | str:
    """Key press / click → the new view's timings line in headless Chromium (median of ``repeats``)."""
    from gra_mi.apps.viewer_browser import chromium, viewer_in_browser

    if chromium() is None:
        return "skipped: chromium and chromedriver are not installed (scripts/setup.sh installs them with apt)"
    from selenium.webdriver.common.keys import Keys

    with viewer_in_browser(scene, 512) as page:
        actions = {
            "new envmap": lambda k: page.choose("envmap", ("studio", "interior", "night", "sun")[k % 4]),
            "envmap rotation": lambda k: page.press("rotation (deg)", Keys.ARROW_RIGHT, 1),
            "point light moved": lambda k: page.press("point light (m)", Keys.ARROW_DOWN, 1),
        }
        rows = []
        for name, act in actions.items():
            if name == "point light moved":
                page.settle(page.choose("mode", "point light"))
            times = [page.settle(act(k)) * 1000 for k in range(repeats)]
            rows.append({"change": name, "browser": statistics.median(times), "spread": (min(times), max(times))})
        return rows


def goals(rows: list[dict], key: str, where: str, lighting: int, point: int) -> str:
    """Row by row against the goals (``lighting`` ms for a lighting change, ``point`` for a moved point light): met
    or missed by every repetition, else by the median only."""
    said = []
    for row in rows:
        goal = point if row["change"].startswith("point") else lighting if row["change"] in CHANGES else None
        if goal is None:
            continue
        (low, high), median = row["spread"], row[key]
        verdict = "met" if high <= goal else "missed" if low > goal else f"{'met' if median <= goal else 'missed'} by the median"
        said.append(f"{row['change']} {verdict} ({median:.0f} ms, {low:.0f}–{high:.0f}; goal {goal})")
    return f"Against the goals {where}: " + "; ".join(said) + "."


def markdown(server: list[dict], browser, stamp: str) -> str:
    lines = [
        "# `gra-mi view`: latency of a change",
        "",
        f"Generated by `benchmarks/viewer.py` ({stamp}). The anny body, 331 LEDs, UV 512², a 512×288 view; medians of 5,",
        "with the fastest and slowest of the 5 beside the totals.",
        "",
        "## On the server (ms)",
        "",
        "| change | total | fastest–slowest | shade | rasterize | tonemap | JPEG |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {r['change']} | **{r['total']:.0f}** | {r['spread'][0]:.0f}–{r['spread'][1]:.0f} | {r['shade']:.0f} | {r['rasterize']:.0f} "
        f"| {r['tonemap']:.0f} | {r['jpeg']:.0f} |"
        for r in server
    ]
    lines += [
        "",
        "'shade' includes setting the lighting (an envmap's mapping onto the LEDs) and, for a point light, its soft-shadow trace.",
        "",
        goals(server, "total", "on the server", 100, 300),
        "",
    ]
    lines += ["## In the browser (headless Chromium, software WebGL)", ""]
    if isinstance(browser, str):
        lines.append(browser)
    else:
        lines += ["| change | key press / click → new view (ms) | fastest–slowest |", "|---|---|---|"]
        lines += [f"| {r['change']} | **{r['browser']:.0f}** | {r['spread'][0]:.0f}–{r['spread'][1]:.0f} |" for r in browser]
        lines += [
            "",
            "Goals in the browser: ≤ 150 ms for a lighting change, ≤ 300 ms for a dragged light. Headless Chromium draws",
            "with SwiftShader (WebGL on the CPU, sharing the 2 cores with the server) and the timing includes the test",
            "driver's polling: an upper bound for a desktop browser with a GPU.",
            "",
            goals(browser, "browser", "in the browser", 150, 300),
        ]
    return "\n".join(lines) + "\n"


def measure(run: BenchmarkRun) -> str:
    scene = walking_scene(run.work, 3)
    return markdown(server_rows(scene), browser_rows(scene), run.stamp("anny, UV 512"))


if __name__ == "__main__":
    run_benchmark(__doc__, measure)
