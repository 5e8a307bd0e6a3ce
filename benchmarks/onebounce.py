"""Speed of the one-bounce core on the default rig (anny body, 331 LEDs, 512² UV), measured side by side.

    .venv/bin/python benchmarks/onebounce.py [--quick] [--image 1024x540] [--subject SAVED_SEQUENCE] [--write PAGE]

Its page's table:
  - visibility for one new frame, and its throughput against raw ``scene.ray_test`` on the same rays;
  - relight of a visibility-cached frame for one camera under a new envmap (texel shading, rasterisation);
  - equal-error speedup over Mitsuba's ``direct`` integrator on the same scene and material;
  - far field against near field; peak memory.
Timings are medians of repeated runs (the machine is shared and noisy).
"""

from __future__ import annotations

import resource
from pathlib import Path

import numpy as np

from gra_mi.apps.harness import BenchmarkRun, envmap_drives, run_benchmark, table_page, timed
from gra_mi.core.runtime import segment


def relative_rmse(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    diff = (image[..., :3] - reference[..., :3])[mask]
    return float(np.sqrt(np.mean(diff**2)) / np.mean(reference[..., :3][mask]))


def setup(args, work: Path):
    """(scene, relighter, stage) of the anny walk (or ``--subject``) in the default rig at ``--image``."""
    from gra_mi.core.io import atomic_write_text
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.lightstage import default_lightstage
    from gra_mi.stage.scene import LightstageScene, subject_scene_xml, write_rig
    from gra_mi.subject.anny_body import anny_sequence
    from gra_mi.subject.sequence import save_sequence

    width, height = (int(v) for v in args.image.lower().split("x"))
    stage = default_lightstage(width=width, height=height)
    write_rig(stage, work / "rig")
    subject = args.subject.resolve() if args.subject else work / "subject"
    if args.subject is None:
        save_sequence(anny_sequence(["walk"], frames_per_clip=6), subject)
    atomic_write_text(work / "scene.xml", subject_scene_xml("rig", str(subject)))
    ls = LightstageScene.load(work / "scene.xml", frame=1)
    return ls, Relighter(ls, args.uv_resolution), stage


def visibility_rows(ls, relighter, stage, repeats: int) -> tuple[list, int, object]:
    """1. Visibility for a new frame, against raw ray_test on the same rays: (rows, the frame, its geometry)."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.leds import LedLayout
    from gra_mi.render.visibility import compute_visibility

    rows = []
    frames = iter(range(1, 6))

    def new_frame_visibility():
        f = next(frames)
        ls.set_frame(f)
        bits = compute_visibility(ls.scene, relighter.geometry(f), LedLayout.of(stage))
        dr.eval(bits)
        return f

    t_vis, frame = timed(new_frame_visibility, min(repeats, 4))
    geom = relighter.geometry(frame)
    m = dr.width(geom.position)
    # The same rays, built up front (LED-major, facing pairs only), so that only ray_test is timed.
    p, n, ng = (np.array(a).T for a in (geom.position, geom.normal, geom.geo_normal))
    origins, dirs, maxts = [], [], []
    for led in stage.led_positions:
        d = led - p
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        facing = (np.sum(n * d, 1) > 0) & (np.sum(ng * d, 1) > 0)
        origins.append((p + ng * 1e-4)[facing])
        dirs.append(d[facing])
        maxts.append(dist[facing] * (1 - 1e-4) - 1e-4)
    origins, dirs, maxts = (np.concatenate(a).astype(np.float32) for a in (origins, dirs, maxts))
    ray = segment(mi.Point3f(*origins.T), mi.Vector3f(*dirs.T), mi.Float(maxts))
    dr.eval(ray)
    t_raw, _ = timed(lambda: dr.eval(ls.scene.ray_test(ray, coherent=True)), repeats)
    t_trace, _ = timed(lambda: compute_visibility(ls.scene, geom, LedLayout.of(stage)), repeats)
    n_rays = origins.shape[0]
    rows.append(
        (
            "visibility, one new frame (mesh update + texel geometry + tracing)",
            f"{t_vis * 1e3:.0f} ms",
            f"{m} texels, {n_rays / 1e6:.1f} M facing pairs traced",
        )
    )
    rows.append(("  of which `compute_visibility` (texels × 331 LEDs)", f"{t_trace * 1e3:.0f} ms", ""))
    rows.append(("raw `scene.ray_test`, same rays", f"{t_raw * 1e3:.0f} ms", f"{n_rays / t_raw / 1e6:.1f} M rays/s"))
    rows.append(("visibility throughput / raw ray_test (whole new frame)", f"{t_raw / t_vis:.2f}", "goal ≥ 0.8 (CPU)"))
    rows.append(("`compute_visibility` throughput / raw ray_test", f"{t_raw / t_trace:.2f}", ""))

    return rows, frame, geom


def relight_rows(ls, relighter, stage, frame: int, geom, repeats: int) -> tuple[list, dict]:
    """2. Relight of a cached frame under a new envmap: (rows, what the comparisons reuse)."""
    from gra_mi.render.leds import LedLayout
    from gra_mi.render.rasterize import rasterize_to_camera
    from gra_mi.render.shading import shade_texels
    from gra_mi.stage.lightstage import olat_pattern

    rows = []
    width, height = stage.cameras[0].width, stage.cameras[0].height
    relighter.visibility(frame)
    ls.set_frame(frame)  # the mesh the camera rays are traced against
    intensities = envmap_drives(stage)
    cam = stage.cameras[0]
    counter = iter(range(10**6))

    def shade():
        i = next(counter) % len(intensities)
        return shade_texels(
            geom, relighter.visibility(frame), LedLayout.of(stage), intensities[i], relighter.albedo, relighter.roughness, cam.position
        )

    shade()  # compile
    t_shade, shading = timed(shade, repeats)
    t_raster, image_uv = timed(
        lambda: rasterize_to_camera(ls, cam, relighter.atlas.scatter(shading.radiance), relighter.atlas.mask), repeats
    )
    rows.append(("relight, cached frame, new envmap: texel shading (all LEDs, GGX)", f"{t_shade * 1e3:.0f} ms", "goal ≤ 100 ms"))
    olats = iter(range(10**6))

    def shade_olat():  # a reflectance field's frames, an OLAT fit's views: one LED on, a new one each call
        pattern = olat_pattern(stage, next(olats) % stage.num_leds)
        return shade_texels(
            geom, relighter.visibility(frame), LedLayout.of(stage), pattern, relighter.albedo, relighter.roughness, cam.position
        )

    shade_olat()  # compile
    t_olat, _ = timed(shade_olat, repeats)
    rows.append(("  the same, one LED on (an OLAT, another LED each call)", f"{t_olat * 1e3:.0f} ms", f"{t_shade / t_olat:.1f}× less"))
    rows.append((f"  + rasterise the texture into the camera ({width}×{height})", f"{t_raster * 1e3:.0f} ms", ""))

    return rows, {"intensities": intensities, "cam": cam, "t_ours": t_shade + t_raster, "image_uv": image_uv}


def direct_rows(ls, relighter, stage, frame: int, geom, ours: dict, quick: bool, work: Path, subject: Path) -> tuple[list, object]:
    """3. Equal error against Mitsuba's direct integrator: (rows, the near-field shading)."""
    import mitsuba as mi

    from gra_mi.core.io import write_exr
    from gra_mi.render.leds import LedLayout
    from gra_mi.render.rasterize import rasterize_to_camera
    from gra_mi.render.shading import shade_texels

    repeats = 2 if quick else 5
    intensities, cam, image_uv, t_ours = ours["intensities"], ours["cam"], ours["image_uv"], ours["t_ours"]
    tmp = work
    rows = []
    write_exr(tmp / "albedo.exr", relighter.albedo_tex)
    ply = subject / "frames" / f"frame_{frame:04d}.ply"
    from gra_mi.stage.scene import camera_xml, led_sampling_weights, xml_attribute

    # The stock integrator run as a user would: LEDs picked in proportion to their power (gra-mi's own scenes do).
    emitters = "".join(
        f'<emitter type="point"><point name="position" value="{", ".join(map(str, q))}"/><rgb name="intensity" value="{", ".join(map(str, i))}"/>'
        f'<float name="sampling_weight" value="{w:.9g}"/></emitter>'
        for q, i, w in zip(stage.led_positions, intensities[1], led_sampling_weights(intensities[1]), strict=True)
    )
    xml = (
        f'<scene version="3.0.0">{camera_xml(cam, "1")}{emitters}<shape type="ply"><string name="filename" value="{xml_attribute(ply)}"/>'
        f'<bsdf type="gra_microfacet"><texture type="bitmap" name="albedo"><string name="filename" value="{xml_attribute(tmp / "albedo.exr")}"/></texture>'
        '<float name="roughness" value="0.5"/></bsdf></shape></scene>'
    )
    scene = mi.load_string(xml)
    onebounce = mi.load_dict({"type": "gra_onebounce"})
    ref_spp = 16 if quick else 64
    reference = np.array(mi.render(scene, integrator=onebounce, spp=ref_spp, seed=99))
    mask = (reference[..., 3] > 0.999) & (image_uv[..., 3] > 0.5)
    shading = shade_texels(
        geom, relighter.visibility(frame), LedLayout.of(stage), intensities[1], relighter.albedo, relighter.roughness, cam.position
    )
    ours = rasterize_to_camera(ls, cam, relighter.atlas.scatter(shading.radiance), relighter.atlas.mask)
    err_ours = relative_rmse(ours, reference, mask)
    rows.append(
        (f"gra-mi UV relight vs image-space one-bounce reference ({ref_spp} spp)", f"rel. RMSE {err_ours:.4f}", f"{t_ours * 1e3:.0f} ms")
    )
    t_ob1, img_ob1 = timed(lambda: np.array(mi.render(scene, integrator=onebounce, spp=1, seed=5)), max(2, repeats // 2))
    rows.append(
        (
            "`gra_onebounce` image space, 1 spp (no cache)",
            f"rel. RMSE {relative_rmse(img_ob1, reference, mask):.4f}",
            f"{t_ob1 * 1e3:.0f} ms",
        )
    )
    direct = mi.load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    points = []
    for spp in [4, 16] if quick else [4, 16, 64, 256]:
        t_d, img = timed(lambda spp=spp: np.array(mi.render(scene, integrator=direct, spp=spp, seed=spp)), 1 if spp > 16 else 2)
        err = relative_rmse(img, reference, mask)
        points.append((spp, t_d, err))
        rows.append((f"Mitsuba `direct`, {spp} spp", f"rel. RMSE {err:.4f}", f"{t_d * 1e3:.0f} ms"))
    # Monte Carlo error falls as 1/sqrt(spp) and time grows linearly: extrapolate to our error.
    spp_last, t_last, err_last = points[-1]
    spp_equal = spp_last * (err_last / err_ours) ** 2
    t_equal = t_last * spp_equal / spp_last
    rows.append(("`direct` at equal error (extrapolated)", f"{spp_equal:.0f} spp", f"{t_equal:.1f} s"))
    rows.append(("equal-error speedup over `direct`", f"{t_equal / t_ours:.0f}×", "goal ≥ 50×"))

    return rows, shading


def far_field_rows(ls, relighter, frame: int, shading, intensities, cam, uv_resolution: int) -> list:
    """4. Far field against near field, and the peak memory."""
    from gra_mi.render.relighter import Relighter
    from gra_mi.render.shading import shade_texels

    rows = []
    far = Relighter(ls, uv_resolution, far_field=True)
    far_shading = shade_texels(
        far.geometry(frame), far.visibility(frame), far.leds(), intensities[1], far.albedo, far.roughness, cam.position
    )
    lit = shading.radiance.sum(axis=1) > 0
    far_err = float(np.mean(np.abs(far_shading.radiance - shading.radiance)[lit]) / np.mean(shading.radiance[lit]))
    rows.append(("far field vs near field (mean abs. error / mean, UV texels)", f"{100 * far_err:.1f} %", "LEDs at 2 m"))
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rows.append(("peak memory (process)", f"{peak:.0f} MiB", ""))

    return rows


def measure(run: BenchmarkRun) -> str:
    import drjit as dr

    args = run.args
    repeats = 2 if args.quick else 5
    ls, relighter, stage = setup(args, run.work)
    subject = args.subject.resolve() if args.subject else run.work / "subject"
    rows, frame, geom = visibility_rows(ls, relighter, stage, repeats)
    more, ours = relight_rows(ls, relighter, stage, frame, geom, repeats)
    rows += more
    more, shading = direct_rows(ls, relighter, stage, frame, geom, ours, args.quick, run.work, subject)
    rows += more
    rows += far_field_rows(ls, relighter, frame, shading, ours["intensities"], ours["cam"], args.uv_resolution)
    texels = int(relighter.atlas.mask.sum())
    title = f"One-bounce core — {dr.thread_count()} threads, {texels} texels at {args.uv_resolution}², {stage.num_leds} LEDs"
    return table_page(title, "onebounce.py", run.stamp(f"anny walk, {args.image}"), rows)


def arguments(parser) -> None:
    parser.add_argument("--quick", action="store_true", help="Fewer repeats and spp (a smoke run).")
    parser.add_argument("--uv-resolution", type=int, default=512, help="UV resolution. Default: 512.")
    parser.add_argument("--image", default="512x270", help="Camera image size WxH. Default: 512x270 (the paper's is 1024x540).")
    parser.add_argument(
        "--subject",
        type=Path,
        default=None,
        help="A saved subject sequence (a folder with frames/, ≥ 6 frames) to use instead of building the anny walk.",
    )


if __name__ == "__main__":
    run_benchmark(__doc__, measure, arguments=arguments, variant=None)
