"""Per-texel albedo and roughness from a multi-view lightstage capture (paper Eq. 3, Supp. "Microfacet Parameters").

The one-bounce model is linear in albedo: for an observation j of texel t (a camera pixel under a frame's lighting),

    O_j = a_t ⊙ D_j + S_j(r_t),    D_j = Σ_k V_k I_k T(ωi) T(ωk) cosθk / (π d_k²),   S_j = Σ_k V_k I_k f_spec cosθk / d_k²

(:mod:`gra_mi.brdf`). So instead of gradient descent on rendered images, the fit works texel by texel:

1. **Observations**: every training camera and frame projects each texel into its image; texels that face the
   camera, are not occluded and fall inside the mask (alpha = 1 on all four bilinear taps) are observed.
2. **Roughness grid**: for each candidate roughness, accumulate per-texel sufficient statistics over all views
   (Σ D², Σ D·O, Σ D·S, Σ S², Σ S·O, Σ O²); the albedo minimising the squared error is then closed-form, as is that
   error. Each texel keeps its best candidate, refined by a parabola through its neighbours.
3. **L1 (the paper's loss)**: iteratively reweighted least squares on the albedo at the chosen roughness.

Visibility comes from the per-frame cache, so the LEDs are traced once per frame for the whole fit. Texels no camera
observes keep defaults and are reported; albedo is bounded to [0, 1], roughness to [0, 1]. Each stage is
checkpointed: an interrupted fit resumes where it stopped.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture, load_observation
from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_path, atomic_write_text, write_exr, write_png

logger = logging.getLogger(__name__)

DEFAULT_ALBEDO = 0.5
DEFAULT_ROUGHNESS = 0.5
L1_DELTA = 1e-3  # IRLS weight floor: residuals below this count as this


@dataclass
class FitConfig:
    roughness_candidates: int = 11
    """Roughness values tried on a uniform grid over [0, 1] before per-texel refinement."""
    irls_iterations: int = 3
    """L1 reweighting iterations after the least-squares solution (0: plain least squares)."""
    resolution: int | None = None
    """UV resolution of the fitted maps (default: the capture's)."""

    def validate(self) -> None:
        if self.roughness_candidates < 3:
            raise GraMiParameterError("roughness_candidates", f"must be at least 3, got {self.roughness_candidates}")
        if self.irls_iterations < 0:
            raise GraMiParameterError("irls_iterations", f"must be >= 0, got {self.irls_iterations}")
        if self.resolution is not None and self.resolution < 1:
            raise GraMiParameterError("resolution", f"must be >= 1, got {self.resolution}")


@dataclass
class View:
    frame: int
    camera: str
    texels: np.ndarray  # indices of the observed valid texels
    observed: np.ndarray  # (n, 3) captured radiance


@dataclass
class FitResult:
    albedo: np.ndarray  # (R, R, 3)
    roughness: np.ndarray  # (R, R, 1)
    observed_cameras: np.ndarray  # (M,) how many cameras saw each valid texel
    loss_curve: list[tuple[float, float, str]] = field(default_factory=list)  # (seconds, mean L1, stage)
    per_view_l1: dict[str, float] = field(default_factory=dict)


def _camera_visible(scene, camera, positions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Texels facing the camera with nothing in between."""
    import mitsuba as mi

    to_cam = camera.position - positions
    dist = np.linalg.norm(to_cam, axis=1)
    d = to_cam / dist[:, None]
    facing = np.sum(normals * d, axis=1) > 0
    origin = positions + normals * 1e-4
    ray = mi.Ray3f(
        mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)), mi.Float((dist * (1 - 1e-4)).astype(np.float32))
    )
    blocked = np.array(scene.ray_test(ray, coherent=False, active=mi.Bool(facing)))
    return facing & ~blocked


def sample_image(image: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear RGB at pixel positions (pixel centres at +0.5), and whether all four taps are fully covered."""
    h, w = image.shape[:2]
    x, y = xy[:, 0] - 0.5, xy[:, 1] - 0.5
    inside = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = np.clip(x - x0, 0, 1)[:, None], np.clip(y - y0, 0, 1)[:, None]
    taps = [image[y0, x0], image[y0, x0 + 1], image[y0 + 1, x0], image[y0 + 1, x0 + 1]]
    value = (taps[0] * (1 - fx) + taps[1] * fx) * (1 - fy) + (taps[2] * (1 - fx) + taps[3] * fx) * fy
    covered = inside & np.all(np.stack([t[:, 3] for t in taps]) > 0.999, axis=0)
    return value[:, :3], covered


class MaterialFitter:
    def __init__(self, capture: Capture, config: FitConfig, cache_dir: str | Path | None = None):
        from gra_mi.core.runtime import ensure_mitsuba
        from gra_mi.render.relighter import Relighter
        from gra_mi.stage.scene import LightstageScene

        ensure_mitsuba()
        self.capture = capture
        self.config = config
        self.ls = LightstageScene.load(capture.folder / "scene.xml")
        self.stage = self.ls.stage
        resolution = config.resolution or capture.uv_resolution
        self.relighter = Relighter(self.ls, resolution, cache_dir=cache_dir)
        self.atlas = self.relighter.atlas
        self.train = [f for f in capture.frames if f.split == "train"]
        self._lighting = {f.frame: capture.lighting(self.stage, f) for f in self.train}

    # ----------------------------------------------------------------------------------------------------------

    def gather_views(self, progress_bar=True) -> list[View]:
        """Observations of every training camera in every training frame."""
        from gra_mi.core.progress import progress

        views = []
        jobs = [(f.frame, cam) for f in self.train for cam in self.capture.train_cameras]
        for frame, cam_name in progress(jobs, description="observations") if progress_bar else jobs:
            cam = self.stage.camera(cam_name)
            geom = self.relighter.geometry(frame)
            self.ls.set_frame(frame)
            p = np.array(geom.position).T.astype(np.float64)
            n = np.array(geom.geo_normal).T.astype(np.float64)
            seen = _camera_visible(self.ls.scene, cam, p, n)
            xyz = cam.project(p[seen])
            image = load_observation(self.capture, cam_name, frame)
            value, covered = sample_image(image, xyz[:, :2])
            ok = covered & (xyz[:, 2] > 0)
            views.append(View(frame, cam_name, np.flatnonzero(seen)[ok], value[ok].astype(np.float32)))
        return views

    def parts(self, view: View, roughness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(D, S) at the view's observed texels for per-texel roughness (M,)."""
        from gra_mi.render.shading import shade_texels

        cam = self.stage.camera(view.camera)
        shading = shade_texels(
            self.relighter.geometry(view.frame), self.relighter.visibility(view.frame), self.stage.led_positions,
            self._lighting[view.frame], np.ones((self.atlas.num_texels, 3), np.float32), roughness, cam.position,
        )  # fmt: skip
        return shading.diffuse_unit[view.texels], shading.specular[view.texels]

    # ----------------------------------------------------------------------------------------------------------

    def fit(self, out: Path | None = None) -> FitResult:
        from gra_mi.core.progress import progress

        cfg = self.config
        m = self.atlas.num_texels
        start = time.perf_counter()
        checkpoint = None if out is None else out / "checkpoint.npz"
        state = dict(np.load(checkpoint)) if checkpoint is not None and checkpoint.is_file() else {}
        curve: list[tuple[float, float, str]] = [tuple(x) for x in json.loads(str(state["curve"]))] if "curve" in state else []

        def save(**arrays) -> None:
            state.update(arrays)
            if checkpoint is not None:
                with atomic_path(checkpoint) as tmp, open(tmp, "wb") as fh:
                    np.savez(fh, **{**state, "curve": json.dumps(curve)})

        views = self.gather_views()
        cameras_seen = np.zeros(m, np.int64)
        for cam in self.capture.train_cameras:
            seen = np.zeros(m, bool)
            for v in views:
                if v.camera == cam:
                    seen[v.texels] = True
            cameras_seen += seen

        # 2. Roughness grid with closed-form albedo -----------------------------------------------------------
        grid = np.linspace(0.0, 1.0, cfg.roughness_candidates)
        if "grid_error" not in state:
            s_dd, s_do, s_oo = np.zeros((m, 3)), np.zeros((m, 3)), np.zeros((m, 3))
            s_ds, s_ss, s_os = (np.zeros((len(grid), m, 3)) for _ in range(3))
            for g, r in enumerate(progress(list(grid), description="roughness grid")):
                for v in views:
                    d, s = self.parts(v, np.full(m, r, np.float32))
                    o = v.observed.astype(np.float64)
                    if g == 0:
                        np.add.at(s_dd, v.texels, d * d)
                        np.add.at(s_do, v.texels, d * o)
                        np.add.at(s_oo, v.texels, o * o)
                    np.add.at(s_ds[g], v.texels, d * s)
                    np.add.at(s_ss[g], v.texels, s * s)
                    np.add.at(s_os[g], v.texels, o * s)
            with np.errstate(invalid="ignore", divide="ignore"):
                albedo_g = np.clip((s_do[None] - s_ds) / s_dd[None], 0.0, 1.0)
            albedo_g = np.where(s_dd[None] > 0, albedo_g, DEFAULT_ALBEDO)
            error_g = (s_oo[None] - 2 * albedo_g * s_do[None] + albedo_g**2 * s_dd[None] + s_ss - 2 * s_os + 2 * albedo_g * s_ds).sum(
                axis=2
            )
            save(grid_error=error_g)
        error_g = state["grid_error"]
        best = np.argmin(error_g, axis=0)
        # Parabola through the best candidate and its neighbours (clamped to the grid's ends).
        lo, hi = np.clip(best - 1, 0, len(grid) - 1), np.clip(best + 1, 0, len(grid) - 1)
        e0, e1, e2 = (error_g[idx, np.arange(m)] for idx in (lo, best, hi))
        curvature = e0 - 2 * e1 + e2
        step = grid[1] - grid[0]
        with np.errstate(invalid="ignore", divide="ignore"):
            shift = np.where((curvature > 1e-30) & (lo != best) & (hi != best), 0.5 * (e0 - e2) / curvature, 0.0)
        roughness = np.clip(grid[best] + np.clip(shift, -1, 1) * step, 0.0, 1.0).astype(np.float32)
        observed = cameras_seen > 0
        roughness[~observed] = DEFAULT_ROUGHNESS
        curve.append((time.perf_counter() - start, float("nan"), "roughness grid"))

        # 3. Albedo at the chosen roughness: least squares, then L1 by reweighting ---------------------------
        cache = [self.parts(v, roughness) for v in progress(views, description="albedo")]
        weights = [np.ones_like(v.observed, dtype=np.float64) for v in views]
        albedo = np.full((m, 3), DEFAULT_ALBEDO)
        for it in range(cfg.irls_iterations + 1):
            num, den = np.zeros((m, 3)), np.zeros((m, 3))
            for v, (d, s), w in zip(views, cache, weights, strict=True):
                np.add.at(num, v.texels, w * d * (v.observed - s))
                np.add.at(den, v.texels, w * d * d)
            with np.errstate(invalid="ignore", divide="ignore"):
                albedo = np.where(den > 0, np.clip(num / den, 0.0, 1.0), DEFAULT_ALBEDO)
            total, count = 0.0, 0
            for k, (v, (d, s)) in enumerate(zip(views, cache, strict=True)):
                residual = np.abs(v.observed - (albedo[v.texels] * d + s))
                total += residual.sum()
                count += residual.size
                weights[k] = 1.0 / np.maximum(residual, L1_DELTA)
            curve.append((time.perf_counter() - start, total / max(count, 1), "least squares" if it == 0 else f"L1 reweighting {it}"))
            save(albedo=albedo, roughness=roughness)

        per_view = {}
        for v, (d, s) in zip(views, cache, strict=True):
            per_view[f"{v.camera}/frame_{v.frame:04d}"] = (
                float(np.mean(np.abs(v.observed - (albedo[v.texels] * d + s)))) if v.texels.size else float("nan")
            )
        result = FitResult(
            self.atlas.scatter(albedo.astype(np.float32), fill=DEFAULT_ALBEDO),
            self.atlas.scatter(roughness[:, None], fill=DEFAULT_ROUGHNESS),
            cameras_seen,
            curve,
            per_view,
        )
        return result


def write_fit_outputs(fitter: MaterialFitter, result: FitResult, out: Path) -> Path:
    """albedo.exr, roughness.exr (+ PNG previews), convergence plot, fit_report.md and fit.json."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    write_exr(out / "albedo.exr", result.albedo)
    write_exr(out / "roughness.exr", result.roughness)
    write_png(out / "albedo.png", result.albedo)
    write_png(out / "roughness.png", result.roughness)

    curve = [c for c in result.loss_curve if np.isfinite(c[1])]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([c[0] for c in curve], [c[1] for c in curve], "o-")
    for t, loss, name in curve:
        ax.annotate(name, (t, loss), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("mean L1 over observations")
    ax.set_title("Material fit convergence")
    fig.tight_layout()
    fig.savefig(out / "convergence.png", dpi=110)
    plt.close(fig)

    m = fitter.atlas.num_texels
    never = int(np.sum(result.observed_cameras == 0))
    lines = [
        "# Material fit",
        "",
        f"Capture `{fitter.capture.folder}` ({fitter.capture.renderer} ground truth); {m} texels at {fitter.atlas.resolution}²; "
        f"{len(fitter.train)} training frames × {len(fitter.capture.train_cameras)} cameras.",
        "",
        f"- texels never observed: {never} ({100 * never / m:.1f} %), kept at albedo {DEFAULT_ALBEDO}, roughness {DEFAULT_ROUGHNESS}",
        f"- texels seen by ≥ 3 cameras: {int(np.sum(result.observed_cameras >= 3))}",
        "",
        "## Convergence",
        "",
        "![convergence](convergence.png)",
        "",
        "| time (s) | mean L1 | stage |",
        "|---|---|---|",
    ]
    lines += [f"| {t:.1f} | {loss:.5f} | {name} |" for t, loss, name in result.loss_curve]
    gt = fitter.capture.folder / "gt"
    metrics = {}
    if (gt / "albedo.exr").is_file():
        from gra_mi.core.io import read_exr

        seen = result.observed_cameras >= 3
        true_albedo = fitter.atlas.gather(read_exr(gt / "albedo.exr")[..., :3])
        true_rough = fitter.atlas.gather(read_exr(gt / "roughness.exr")[..., :1])[:, 0]
        fit_albedo = fitter.atlas.gather(result.albedo)
        fit_rough = fitter.atlas.gather(result.roughness)[:, 0]
        metrics = {
            "albedo_mae": float(np.mean(np.abs(fit_albedo - true_albedo)[seen])),
            "albedo_rel_median": float(np.median((np.abs(fit_albedo - true_albedo) / np.maximum(true_albedo, 1e-3))[seen])),
            "roughness_mae": float(np.mean(np.abs(fit_rough - true_rough)[seen])),
        }
        lines += ["", "## Against the true maps (texels seen by ≥ 3 cameras)", "", "| metric | value |", "|---|---|"]
        lines += [f"| {k} | {v:.4f} |" for k, v in metrics.items()]
    lines += ["", "## Per view (mean L1 over observed texels)", "", "| view | L1 |", "|---|---|"]
    lines += [f"| {k} | {v:.5f} |" for k, v in sorted(result.per_view_l1.items())]
    per_frame: dict[int, list[float]] = {}
    for key, value in result.per_view_l1.items():
        per_frame.setdefault(int(key.split("frame_")[1]), []).append(value)
    lines += ["", "## Per frame", "", "| frame | L1 |", "|---|---|"]
    lines += [f"| {f} | {np.nanmean(v):.5f} |" for f, v in sorted(per_frame.items())]
    atomic_write_text(out / "fit_report.md", "\n".join(lines) + "\n")
    atomic_write_text(
        out / "fit.json",
        json.dumps(
            {"config": asdict(fitter.config), "metrics": metrics, "loss_curve": result.loss_curve, "never_observed": never}, indent=1
        )
        + "\n",
    )
    return out / "fit_report.md"


def run_fit(capture_dir: str | Path, out: str | Path, config: FitConfig) -> tuple[FitResult, Path]:
    from gra_mi.core.runtime import ensure_mitsuba

    config.validate()
    capture = Capture.load(capture_dir)
    ensure_mitsuba()
    out = Path(out)
    fitter = MaterialFitter(capture, config, cache_dir=out / "cache")
    result = fitter.fit(out)
    return result, write_fit_outputs(fitter, result, out)
