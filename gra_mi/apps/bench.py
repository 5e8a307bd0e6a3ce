"""Speed against error for every approximation of the coarse renderer (``gra-mi bench``).

Each configuration renders the same view (the anny body on the default 331-LED rig under a sunny sky) and is
compared, in the same run, with the exact reference: all LEDs, near field, visibility at full UV resolution,
float32 everywhere. Reported per configuration: time (median of repeats), the memory of what it caches, and the
error against the reference over covered pixels — mean relative error, PSNR, and 1 − SSIM of the tone-mapped images
(a perceptual proxy, kornia). Outputs: report.md, results.csv, results.json and a Pareto plot (time vs error).
"""

from __future__ import annotations

import csv
import json
import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import timed
from gra_mi.core import metrics
from gra_mi.core.guard import scratch_folder
from gra_mi.core.io import atomic_write_text, pyplot, save_figure, to_srgb8, write_exr, write_png
from gra_mi.core.progress import progress
from gra_mi.render.leds import LedLayout
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.stage.envmap import envmap_to_leds
from gra_mi.stage.envmap_library import SkyParams, bake_sunsky
from gra_mi.stage.lightstage import Lightstage, default_lightstage
from gra_mi.stage.scene import LightstageScene, camera_xml, led_sampling_weights, rig_scene, xml_attribute
from gra_mi.subject.anny_body import anny_sequence

logger = logging.getLogger(__name__)


@dataclass(kw_only=True, frozen=True)
class BenchPreset:
    uv_resolution: int
    width: int
    height: int
    frames: int  # frames of the walk clip (visibility sharing needs several)
    repeats: int
    led_counts: list[int]
    uv_resolutions: list[int]
    visibility_resolutions: list[int]
    share_frames: list[int]
    direct_spp: list[int]
    bounce_rays: list[int]  # rays per texel of the two-bounce rows
    path_spp: int  # samples per pixel of their reference (Mitsuba's path, max_depth 3)


PRESETS = {
    "quick": BenchPreset(
        uv_resolution=128, width=256, height=135, frames=3, repeats=2, led_counts=[16, 64], uv_resolutions=[64, 128, 256],
        visibility_resolutions=[64], share_frames=[2], direct_spp=[4, 16], bounce_rays=[8, 32], path_spp=256,
    ),
    "full": BenchPreset(
        uv_resolution=512, width=512, height=270, frames=6, repeats=5, led_counts=[8, 16, 32, 64, 128, 331],
        uv_resolutions=[128, 256, 512, 1024], visibility_resolutions=[128, 256], share_frames=[2, 4], direct_spp=[4, 16, 64, 256],
        bounce_rays=[8, 16, 32, 64, 128], path_spp=1024,
    ),
}  # fmt: skip


@dataclass
class Result:
    group: str
    name: str
    time_ms: float  # per view, visibility already cached unless the group is about visibility
    amortised_ms: float  # per view including visibility, amortised over the views that share it
    cache_mb: float  # memory of the cached quantities this configuration keeps per frame
    mean_rel_error: float
    psnr_db: float
    ssim_loss: float


# --------------------------------------------------------------------------------------------------------------
# Metrics
# --------------------------------------------------------------------------------------------------------------


def image_errors(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> tuple[float, float, float]:
    """Mean relative error (|a − r| / max(r, 2e-2)), PSNR (peak = reference max) and 1 − SSIM of sRGB previews."""

    a, r = image[..., :3], reference[..., :3]
    exposure = 0.8 / max(float(np.percentile(r[mask], 99)), 1e-6)
    shown_a, shown_r = (to_srgb8(x, exposure)[..., :3].astype(np.float32) / 255.0 for x in (a, r))
    return metrics.relative_error(a, r, mask), metrics.psnr(a, r, mask), 1.0 - metrics.ssim(shown_a, shown_r, mask, peak=1.0)


# --------------------------------------------------------------------------------------------------------------
# Approximations under study
# --------------------------------------------------------------------------------------------------------------


def subsample_leds(envmap: np.ndarray, stage, k: int, scale: float) -> np.ndarray:
    """A k-LED stage (every (L/k)-th LED of the spiral) with the envmap integrated onto it; the rest off.

    ``scale`` is the full stage's normalisation, so both light the subject with the same energy.
    """

    keep = np.unique(np.round(np.linspace(0, stage.num_leds - 1, k)).astype(int))
    sub = Lightstage(stage.led_positions[keep], stage.cameras, stage.center, stage.radius, None, None, stage.max_led_intensity)
    out = np.zeros((stage.num_leds, 3))
    out[keep] = envmap_to_leds(envmap, sub, normalize=False).radiant_intensity(sub) * scale
    return out


def half(x: np.ndarray) -> np.ndarray:
    return np.asarray(x, np.float32).astype(np.float16).astype(np.float32)


# --------------------------------------------------------------------------------------------------------------


class BenchSetup:
    """The scene every measurement shares (the anny body, the default rig, a sunny sky on camera 0), the cached atlases,
    geometry and visibility per UV resolution, the exact reference render, and the results so far."""

    def __init__(self, preset: BenchPreset, out: Path):
        from gra_mi.render.relighter import Relighter

        self.preset, self.out = preset, out
        self.work = scratch_folder("gra_mi_bench_")
        self.stage = default_lightstage(width=preset.width, height=preset.height)
        self.ls = LightstageScene.load(rig_scene(self.work, anny_sequence(["walk"], frames_per_clip=2 * preset.frames), self.stage))
        self.seq = self.ls.sequence
        self.frame = preset.frames - 1  # the evaluated frame; earlier frames feed visibility sharing
        self.cam = self.stage.cameras[0]
        self.env = bake_sunsky(SkyParams(25.0, 200.0, 3.0, 0.2), 64)  # a sun behind-left of camera 0: hard shadows
        self.lighting = envmap_to_leds(self.env, self.stage)
        self.intensities = self.lighting.radiant_intensity(self.stage)
        base = Relighter(self.ls, preset.uv_resolution)
        self.albedo_tex, self.rough_tex = base.albedo_tex, base.roughness_tex
        self.atlases: dict[int, object] = {}
        self.results: list[Result] = []
        self.R = preset.uv_resolution
        self.ref_geom = self.geometry(self.R, self.frame)
        self.ref_vis = self.visibility(self.R, self.frame)
        self.t_vis_ref, _ = self.timed(lambda: self.visibility(self.R, self.frame))
        self.t_ref, self.reference = self.timed(lambda: self.render(self.R, self.ref_geom, self.ref_vis))
        self.mask = self.reference[..., 3] > 0.5

    def timed(self, fn: Callable[[], object]) -> tuple[float, object]:
        """Median milliseconds over the preset's repeats, after a first, untimed call that compiles the kernels."""
        seconds, value = timed(fn, self.preset.repeats, warmup=True)
        return 1e3 * seconds, value

    def atlas(self, res: int):
        from gra_mi.render.atlas import UVAtlas

        if res not in self.atlases:
            self.atlases[res] = UVAtlas.build(self.seq.faces, self.seq.uvs, res)
        return self.atlases[res]

    def geometry(self, res: int, f: int):
        from gra_mi.render.atlas import TexelGeometry

        return TexelGeometry.from_frame(self.atlas(res), self.seq.vertices[f], self.seq.normals[f])

    def visibility(self, res: int, f: int, far: bool = False):
        from gra_mi.render.visibility import compute_visibility

        self.ls.set_frame(f)
        return compute_visibility(self.ls.scene, self.geometry(res, f), LedLayout.of(self.stage, far))

    def materials(self, res: int) -> tuple[np.ndarray, np.ndarray]:
        a = self.atlas(res)
        if res == self.R:
            return a.gather(self.albedo_tex), a.gather(self.rough_tex)[:, 0]
        tex = a.bake_vertex_attribute(self.seq.vertex_colors, fill=0.5)
        return a.gather(tex), np.full(a.num_texels, 0.5, np.float32)

    def render(self, res: int, geom, vis, leds=None, far=False, store=lambda x: x) -> np.ndarray:
        from gra_mi.render.rasterize import rasterize_to_camera
        from gra_mi.render.shading import shade_texels

        a = self.atlas(res)
        alb, rough = self.materials(res)
        leds = self.intensities if leds is None else leds
        self.ls.set_frame(self.frame)
        shading = shade_texels(geom, vis, LedLayout.of(self.stage, far), leds, alb, rough, self.cam.position)
        return rasterize_to_camera(self.ls, self.cam, a.scatter(store(shading.radiance)), a.mask)

    def cache_mb(self, res: int, geometry_bytes_per_texel: int = 36) -> float:
        words = (self.stage.num_leds + 31) // 32
        return self.atlas(res).num_texels * (4 * words + geometry_bytes_per_texel) / 2**20

    def record(self, group: str, name: str, t_ms: float, amortised: float, mb: float, image: np.ndarray, reference=None) -> None:
        reference = self.reference if reference is None else reference
        rel, psnr, ssim_loss = image_errors(image, reference, reference[..., 3] > 0.5)
        self.results.append(Result(group, name, t_ms, amortised, mb, rel, psnr, ssim_loss))


# --------------------------------------------------------------------------------------------------------------
# The measurements: each approximation against the exact reference
# --------------------------------------------------------------------------------------------------------------


def bench_led_sampling(b: BenchSetup, k: int) -> None:
    """Fewer LEDs: every n-th (subsampled, re-normalised) or the k brightest (importance)."""
    for name, leds in (
        ("subsample", subsample_leds(b.env, b.stage, k, b.lighting.scale)),
        ("importance", LedLayout.of(b.stage).brightest(b.intensities, k)),
    ):
        t, img = b.timed(lambda leds=leds: b.render(b.R, b.ref_geom, b.ref_vis, leds))
        b.record("LEDs", f"{name} k={k}", t, t + b.t_vis_ref, b.cache_mb(b.R), img)


def bench_low_visibility(b: BenchSetup, low: int) -> None:
    t_low, bits = b.timed(
        lambda: upsample_visibility(b.visibility(low, b.frame), b.atlas(low), b.atlas(b.R), b.ls.scene, b.ref_geom, LedLayout.of(b.stage))
    )
    t, img = b.timed(lambda: b.render(b.R, b.ref_geom, bits))
    mb = b.cache_mb(low, 0) + b.cache_mb(b.R, 36) - b.cache_mb(b.R, 0)
    b.record("visibility", f"visibility at {low}², upsampled", t, t + t_low, mb, img)


def bench_shared_visibility(b: BenchSetup, k: int) -> None:
    """Visibility shared over k consecutive frames: the evaluated frame uses that of k − 1 frames before."""
    bits = b.visibility(b.R, b.frame - (k - 1))
    t, img = b.timed(lambda: b.render(b.R, b.ref_geom, bits))
    b.record("visibility", f"shared over {k} frames (worst frame)", t, t + b.t_vis_ref / k, b.cache_mb(b.R) / k, img)


def bench_far_field(b: BenchSetup) -> None:
    bits = b.visibility(b.R, b.frame, far=True)
    t, img = b.timed(lambda: b.render(b.R, b.ref_geom, bits, far=True))
    b.record("lighting model", "far field (directional LEDs)", t, t + b.t_vis_ref, b.cache_mb(b.R), img)


def bench_antialiasing(b: BenchSetup) -> None:
    """Sub-samples per pixel of the rasterisation against 8×8 of them (shading is shared: texels are shaded once)."""
    from gra_mi.render.rasterize import RASTER_SAMPLES, rasterize_to_camera
    from gra_mi.render.shading import shade_texels

    a = b.atlas(b.R)
    alb, rough = b.materials(b.R)
    b.ls.set_frame(b.frame)
    t_shade, shading = b.timed(
        lambda: shade_texels(b.ref_geom, b.ref_vis, LedLayout.of(b.stage), b.intensities, alb, rough, b.cam.position)
    )
    texture = a.scatter(shading.radiance)
    _, exact = b.timed(lambda: rasterize_to_camera(b.ls, b.cam, texture, a.mask, 8))
    for n in (1, 2, 3, 8):
        t, img = b.timed(lambda n=n: rasterize_to_camera(b.ls, b.cam, texture, a.mask, n))
        label = f"{n}×{n} sub-samples (rasterising: {t:.0f} ms)"
        label += " (default)" if n == RASTER_SAMPLES else " (the reference of this group)" if n == 8 else ""
        b.record("anti-aliasing", label, t_shade + t, t_shade + t + b.t_vis_ref, b.cache_mb(b.R), img, exact)


def bench_half_storage(b: BenchSetup) -> None:
    import mitsuba as mi

    from gra_mi.render.atlas import TexelGeometry

    g = b.ref_geom
    g = TexelGeometry(*(type(v)(*[mi.Float(half(np.array(c))) for c in v]) for v in (g.position, g.normal, g.geo_normal)), g.digest)
    t, img = b.timed(lambda: b.render(b.R, g, b.ref_vis, store=half))
    b.record("storage", "float16 texel geometry and radiance", t, t + b.t_vis_ref, b.cache_mb(b.R, 18), img)


def bench_uv_resolution(b: BenchSetup, res: int) -> None:
    geom = b.geometry(res, b.frame)
    t_v, bits = b.timed(lambda: b.visibility(res, b.frame))
    t, img = b.timed(lambda: b.render(res, geom, bits))
    b.record("UV resolution", f"{res}² UV", t, t + t_v, b.cache_mb(res), img)


def bench_mitsuba_direct(b: BenchSetup) -> None:
    """Mitsuba's own ``direct`` integrator with the same BSDF and LEDs: the generic peer, at several spp."""
    import mitsuba as mi

    write_exr(b.work / "albedo.exr", b.albedo_tex)
    write_exr(b.work / "rough.exr", b.rough_tex)
    ply = b.work / "subject" / "frames" / f"frame_{b.frame:04d}.ply"
    emitters = "".join(
        f'<emitter type="point"><point name="position" value="{", ".join(map(str, q))}"/><rgb name="intensity" value="{", ".join(map(str, i))}"/>'
        f'<float name="sampling_weight" value="{w:.9g}"/></emitter>'  # LEDs picked by power, as gra-mi's own scenes do
        for q, i, w in zip(b.stage.led_positions, b.intensities, led_sampling_weights(b.intensities), strict=True)
    )
    xml = (
        f'<scene version="3.0.0">{camera_xml(b.cam, "1")}{emitters}<shape type="ply"><string name="filename" value="{xml_attribute(ply)}"/>'
        f'<bsdf type="gra_microfacet"><texture type="bitmap" name="albedo"><string name="filename" value="{xml_attribute(b.work / "albedo.exr")}"/></texture>'
        f'<texture type="bitmap" name="roughness"><string name="filename" value="{xml_attribute(b.work / "rough.exr")}"/></texture></bsdf></shape></scene>'
    )
    scene = mi.load_string(xml)
    integrator = mi.load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    mi.render(scene, integrator=integrator, spp=1)  # compile
    for spp in b.preset.direct_spp:
        t, img = b.timed(lambda spp=spp: np.array(mi.render(scene, integrator=integrator, spp=spp, seed=spp)))
        b.record("Mitsuba direct", f"direct {spp} spp", t, t, 0.0, img)


def bench_bounces(b: BenchSetup) -> None:
    """Light after the first bounce against Mitsuba's ``path`` (max_depth 3: one interreflection) with the same maps and
    LEDs: one bounce, then two with K rays per texel. Time per view under a new lighting (the frame's visibility and
    bounce operator cached); amortised: a new frame (its visibility trace and operator trace) for that one view."""
    import itertools

    from gra_mi.render.path_reference import path_reference
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.transport import LightTransport

    def relighter(bounces: int, rays: int = 1, smoothing: int = LightTransport().bounce_smoothing):
        transport = LightTransport(bounces=bounces, bounce_rays=rays, bounce_smoothing=smoothing)
        rel = Relighter(b.ls, b.R, b.albedo_tex, b.rough_tex, transport=transport)
        rel.only_for([b.cam.name])  # as `gra-mi relight` renders: the light its cameras can see
        return rel

    start = time.perf_counter()
    reference = path_reference(relighter(1), b.frame, b.cam, b.intensities, max_depth=3, spp=b.preset.path_spp, folder=b.work / "path")
    t_path = 1e3 * (time.perf_counter() - start)
    b.record(
        "bounces", f"Mitsuba path, max_depth 3, {b.preset.path_spp} spp (this group's reference)", t_path, t_path, 0.0, reference, reference
    )
    change = itertools.count(1)  # a new lighting each call: nothing after the first bounce is reused
    default = LightTransport()
    for bounces, rays, smoothing in (
        [(1, 1, 0)] + [(2, k, default.bounce_smoothing) for k in b.preset.bounce_rays] + [(2, default.bounce_rays, 0)]
    ):
        rel = relighter(bounces, rays, smoothing)
        t, img = b.timed(lambda rel=rel: rel.render(b.frame, b.cam, b.intensities * (1 + 1e-6 * next(change))).image)
        label, t_op, mb = "1 bounce (the paper's model)", 0.0, b.cache_mb(b.R)
        if bounces > 1:
            op = rel.bounce_operator(b.frame)
            t_op, _ = b.timed(lambda rel=rel: (rel._operators.clear(), rel.bounce_operator(b.frame)))
            smoothed = f"smoothing radius {smoothing}" if smoothing else "not smoothed"
            label = f"2 bounces, {rays} rays/texel, {smoothed} ({op.traced / op.num_texels:.0%} of texels trace)"
            mb += op.nbytes / 2**20
        b.record("bounces", label, t, t + b.t_vis_ref + t_op, mb, img, reference)
        if (rays, smoothing) == (default.bounce_rays, default.bounce_smoothing) and bounces > 1:  # the hull test's saving
            t_all = _trace_every_texel(b, rel, rays)
            b.record("bounces", f"{label[:-1]}; without the hull test: every texel traces)", t, t + b.t_vis_ref + t_all, mb, img, reference)


def _trace_every_texel(b: BenchSetup, rel, rays: int) -> float:
    """Milliseconds of the bounce operator's trace from every texel of the evaluated frame (no hull test)."""
    from gra_mi.render.bounce import trace_operator

    every, geom = np.arange(rel.atlas.num_texels), rel.geometry(b.frame)
    b.ls.set_frame(b.frame)
    t, _ = b.timed(lambda: trace_operator(b.ls.scene, b.ls.subject_shape(), geom, rel.atlas, b.seq.uvs, b.seq.faces, every, rays))
    return t


def run_bench(out: Path, preset_name: str = "full") -> Path:
    """Every approximation of the one-bounce render against the exact one: time, amortised time, memory, error."""

    chosen = ensure_mitsuba()
    preset = PRESETS[preset_name]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    b = BenchSetup(preset, out)
    write_exr(out / "reference.exr", b.reference)
    write_png(out / "reference.png", b.reference, exposure=None)
    stage, R = b.stage, b.R
    b.record(
        "reference",
        f"exact ({R}² UV, {stage.num_leds} LEDs, near field, full visibility, float32)",
        b.t_ref,
        b.t_ref + b.t_vis_ref,
        b.cache_mb(R),
        b.reference,
    )
    jobs = [(f"LEDs {k}", lambda k=k: bench_led_sampling(b, k)) for k in preset.led_counts]
    jobs += [(f"visibility {low}", lambda low=low: bench_low_visibility(b, low)) for low in preset.visibility_resolutions if low < R]
    jobs += [(f"share {k}", lambda k=k: bench_shared_visibility(b, k)) for k in preset.share_frames]
    jobs += [
        ("far field", lambda: bench_far_field(b)),
        ("anti-aliasing", lambda: bench_antialiasing(b)),
        ("half", lambda: bench_half_storage(b)),
    ]
    jobs += [(f"uv {res}", lambda res=res: bench_uv_resolution(b, res)) for res in preset.uv_resolutions if res != R]
    jobs.append(("direct", lambda: bench_mitsuba_direct(b)))
    jobs.append(("bounces", lambda: bench_bounces(b)))
    for _, job in progress(jobs, description="bench"):
        job()
    return _write_report(out, preset_name, chosen, stage, b.atlas(R).num_texels, b.results)


def upsample_visibility(bits_low, atlas_low, atlas_high, scene, geom_high, leds):
    """Visibility of each full-resolution texel taken from the low-resolution texel that contains it.

    Texels whose low-resolution cell is empty (chart borders) are traced at full resolution.
    """
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.atlas import TexelGeometry
    from gra_mi.render.visibility import compute_visibility

    s = atlas_high.resolution // atlas_low.resolution
    lookup = np.full(atlas_low.resolution**2, -1, np.int64)
    lookup[atlas_low.texel_index] = np.arange(atlas_low.num_texels)
    row, col = np.divmod(atlas_high.texel_index, atlas_high.resolution)
    source = lookup[(row // s) * atlas_low.resolution + col // s]
    low = np.array(bits_low, dtype=np.uint32).reshape(-1, atlas_low.num_texels)
    high = low[:, np.maximum(source, 0)]
    missing = np.flatnonzero(source < 0)
    if missing.size:
        sub = TexelGeometry(
            *(type(v)(*[mi.Float(np.array(c)[missing]) for c in v]) for v in (geom_high.position, geom_high.normal, geom_high.geo_normal)),
            geom_high.digest,
        )
        high[:, missing] = np.array(compute_visibility(scene, sub, leds), dtype=np.uint32).reshape(-1, missing.size)
    out = mi.UInt32(np.ascontiguousarray(high).ravel())
    dr.eval(out)
    return out


def _pareto(points: list[tuple[float, float]]) -> list[int]:
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], float("inf")
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


ERROR_BUDGET = 0.01
"""Mean relative error at which an approximation counts as "as good as exact" in the conclusions."""


def conclusions(results: list[Result], front: set[int]) -> list[str]:
    """The report's conclusions, computed from the results: per group, the fastest configuration within
    :data:`ERROR_BUDGET` of the reference and the cheapest one with its error; then the Pareto front."""
    lines = []
    for group in dict.fromkeys(r.group for r in results):
        rows = [r for r in results if r.group == group]
        cheapest = min(rows, key=lambda r: r.amortised_ms)
        good = [r for r in rows if r.mean_rel_error <= ERROR_BUDGET]
        line = f"- **{group}**: cheapest {cheapest.name} ({cheapest.amortised_ms:.0f} ms, error {100 * cheapest.mean_rel_error:.2f} %)"
        if good:
            best = min(good, key=lambda r: r.amortised_ms)
            line += f"; fastest within {100 * ERROR_BUDGET:.0f} % error: {best.name} ({best.amortised_ms:.0f} ms)"
        else:
            line += f"; none within {100 * ERROR_BUDGET:.0f} % error"
        lines.append(line + ".")
    on_front = ", ".join(f"{results[i].name} ({results[i].group})" for i in sorted(front, key=lambda i: results[i].amortised_ms))
    return [*lines, "", f"On the Pareto front (no configuration both faster and more accurate): {on_front}."]


def _write_report(out: Path, preset_name: str, variant: str, stage, texels: int, results: list[Result]) -> Path:

    plt = pyplot()

    rows = [asdict(r) for r in results]
    atomic_write_text(out / "results.json", json.dumps(rows, indent=1) + "\n")
    with open(out / "results.csv.tmp", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    (out / "results.csv.tmp").replace(out / "results.csv")

    # Anti-aliasing rows are scored against their own reference (8×8 sub-samples): off the Pareto front and plot.
    plotted = [i for i, r in enumerate(results) if r.group != "anti-aliasing"]
    points = {i: (results[i].amortised_ms, max(results[i].mean_rel_error, 1e-6)) for i in plotted}
    front = {plotted[k] for k in _pareto([points[i] for i in plotted])}
    fig, ax = plt.subplots(figsize=(8, 5.5))
    groups = sorted({results[i].group for i in plotted})
    colors = dict(zip(groups, plt.cm.tab10(np.linspace(0, 1, 10))[: len(groups)], strict=True))
    for i in plotted:
        r = results[i]
        ax.scatter(
            points[i][0],
            points[i][1],
            color=colors[r.group],
            s=60 if i in front else 25,
            edgecolors="black" if i in front else "none",
            label=r.group,
        )
        ax.annotate(r.name.split(" (")[0], points[i], fontsize=6, xytext=(3, 3), textcoords="offset points")
    f = sorted(front, key=lambda i: points[i][0])
    ax.plot([points[i][0] for i in f], [points[i][1] for i in f], "k--", lw=0.8)
    handles, labels = ax.get_legend_handles_labels()
    unique = dict(zip(labels, handles, strict=True))
    ax.legend(unique.values(), unique.keys(), fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per view, visibility amortised (ms)")
    ax.set_ylabel("mean relative error vs exact reference")
    ax.set_title(f"Speed against error — {stage.num_leds} LEDs, {texels} texels ({preset_name})")
    fig.tight_layout()
    save_figure(fig, out / "pareto.png", dpi=120)

    lines = [
        f"# gra-mi bench — speed against error ({preset_name}, `{variant}`)",
        "",
        "One view of the anny body on the default rig under a low sun, every configuration measured in the same run",
        "against the exact reference (all LEDs, near field, full-resolution visibility, float32, 3×3 sub-samples per pixel);",
        "the anti-aliasing rows against the same shading rasterised with 8×8 sub-samples (not on the Pareto plot).",
        "Time: median per view with visibility cached; amortised: including visibility spread over the views that share",
        "it (one frame, one view here). Cache: memory kept per frame (visibility bits + texel geometry).",
        "",
        "| group | configuration | time (ms) | amortised (ms) | cache (MiB) | mean rel. error | PSNR (dB) | 1 − SSIM | Pareto |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for i, r in enumerate(results):
        lines.append(
            f"| {r.group} | {r.name} | {r.time_ms:.0f} | {r.amortised_ms:.0f} | {r.cache_mb:.1f} | {r.mean_rel_error:.4f} | "
            f"{r.psnr_db:.1f} | {r.ssim_loss:.4f} | {'★' if i in front else ''} |"
        )
    lines += [
        "",
        "![Pareto](pareto.png)",
        "",
        "## What the numbers say (derived from the table above)",
        "",
        *conclusions(results, front),
        "",
        "Raw numbers: `results.csv`, `results.json`.",
    ]
    report = out / "report.md"
    atomic_write_text(report, "\n".join(lines) + "\n")
    return report
