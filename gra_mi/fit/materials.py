"""Per-texel albedo and roughness from a multi-view lightstage capture (paper Eq. 3, Supp. "Microfacet Parameters").

Two stages (``FitConfig.solver``: "adam" runs both, "closed-form" the first alone):

**Closed form** (the initialiser). The one-bounce model is linear in albedo: for an observation j of texel t (a camera
pixel under a frame's lighting),

    O_j = a_t ⊙ D_j + S_j(r_t),    D_j = Σ_k V_k I_k T(ωi) T(ωk) cosθk / (π d_k²),   S_j = Σ_k V_k I_k f_spec cosθk / d_k²

(:mod:`gra_mi.render.brdf`). So the first stage works texel by texel:

1. **Observations**: every training camera and frame projects each texel into its image; texels that face the
   camera, are not occluded and fall inside the mask (alpha = 1 on all four bilinear taps) are observed.
2. **Roughness grid**: for each candidate roughness, accumulate per-texel sufficient statistics over all views
   (Σ D², Σ D·O, Σ D·S, Σ S², Σ S·O, Σ O²); the albedo minimising the squared error is then closed-form, as is that
   error. Each texel keeps its best candidate, refined by a parabola through its neighbours.
3. **L1 (the paper's loss)**: iteratively reweighted least squares on the albedo at the chosen roughness.

**Adam on the maps** (:mod:`gra_mi.fit.optimize`): the L1 between the one-bounce render and every training image,
pixel by pixel with each pixel's footprint, plus a smoothness prior over the body's surface
(:mod:`gra_mi.fit.prior`); texels without highlight evidence take their roughness from their neighbours.

Visibility comes from the per-frame cache, so the LEDs are traced once per frame for the whole fit. Albedo is bounded
to [0, 1], roughness to [0, 1]. Each stage is checkpointed: an interrupted fit resumes where it stopped.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

import numpy as np

from gra_mi.capture.dataset import Capture, load_fit_observation
from gra_mi.core.config import comma_list, name_list, option
from gra_mi.core.errors import GraMiParameterError
from gra_mi.core.io import atomic_path, read_checkpoint_npz
from gra_mi.core.limits import require_memory
from gra_mi.core.metrics import subject_mask
from gra_mi.core.progress import progress
from gra_mi.core.provenance import claim_output
from gra_mi.core.runtime import columns
from gra_mi.fit.grid import GridSums, refine_on_grid
from gra_mi.fit.headroom import AlbedoHeadroom
from gra_mi.fit.levels import fit_levels
from gra_mi.fit.maps import DEFAULT_ALBEDO, DEFAULT_ROUGHNESS, LevelStart
from gra_mi.fit.optimize import Evidence
from gra_mi.fit.prior import SurfaceGraph
from gra_mi.fit.ranks import FitRanks
from gra_mi.fit.report import write_fit_outputs
from gra_mi.fit.views import ViewStore
from gra_mi.render.atlas import MIN_RESOLUTION
from gra_mi.render.runtime import ensure_mitsuba
from gra_mi.render.transport import LightTransport

logger = logging.getLogger(__name__)

L1_DELTA = 1e-3  # IRLS weight floor: residuals below this count as this
ALBEDO_FILL_STRENGTH = 0.01  # texels no camera saw take their neighbours' closed-form albedo (observed ones keep theirs)


SOLVERS = ("adam", "closed-form")

RUN_TO_RUN = 2e-3
"""How far two runs of the same fit may differ per texel (albedo and roughness). Not bit-reproducible by design:
Dr.Jit's CPU and GPU backends sum the gradient's scatter-add over texels with threads, in whatever order they
finish, and Adam's step (a ratio of moments) turns last-bit differences into up to ~1e-4 (3 runs of `tiny`) and
6e-4 (`small`) after its iterations; a resumed fit is compared with an uninterrupted one within this bound."""


def _resolutions(text: str) -> list[int]:
    """``--levels``: a comma list of UV resolutions."""
    import argparse

    try:
        return [int(x) for x in comma_list(text)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a comma list of UV resolutions such as 256,512,1024, got '{text}'") from None


INDIRECT_ROUNDS = 2  # closed forms solved again with the light after the first bounce frozen (docs/accuracy.md)
FIT_BYTES_PER_TEXEL = 160  # float32 state per texel of a fit, views' texel lists included (a lower bound)


@dataclass
class FitConfig:
    solver: str = field(default="adam", metadata=option(choices=SOLVERS))
    """adam: the closed-form solution, then Dr.Jit + Adam on the maps against the images with the surface prior;
    closed-form: the per-texel grid search and L1 reweighting alone (no prior; fast, noisy roughness)."""
    iterations: int = 60
    """Adam iterations (steps; with --batch-views, each uses that many views)."""
    batch_views: int = 0
    """Training views per Adam step, their gradients accumulated one view at a time (the paper: batch 1, 8
    accumulation steps: 8). Every view is used once per epoch, in a seeded random order. With a batch, each view's
    footprints and shading inputs live in scratch files (FIT/views.tmp) and are read when needed, so the fit's memory
    is set by the batch, not by the capture's size; the closed form streams the views too. 0: every view every step,
    all held in memory (fastest on a small capture)."""
    seed: int = 0
    """Seed of the minibatch order (--batch-views)."""
    levels: list[int] | None = field(default=None, metadata=option(parse=_resolutions))
    """Coarse to fine: UV resolutions fitted in turn, e.g. 256,512,1024. The first runs the whole fit; each next one
    starts from the previous roughness upsampled (with its highlight confidence) and its albedo solved per texel at
    that roughness, runs --iterations Adam steps, and is checkpointed in FIT/level_RRRR/. The last is the fitted
    resolution (--uv-resolution, if given, must equal it)."""
    lr_albedo: float = 0.01
    """Adam's learning rate for albedo (it decays to a tenth over the run)."""
    lr_roughness: float = 0.03
    """Adam's learning rate for roughness (it decays to a tenth over the run)."""
    smooth_albedo: float = 0.1
    """Weight of the albedo smoothness prior (mean squared difference across surface neighbours)."""
    smooth_roughness: float = 3.0
    """Weight of the roughness smoothness prior; stronger than albedo's, whose evidence is denser."""
    min_view_cos: float = 0.35
    """Pixels whose surface is seen more obliquely than this cosine are left out of the Adam loss (silhouettes:
    mixed footprints, and grazing reflection the one-bounce BRDF explains worst)."""
    roughness_candidates: int = 11
    """Closed form: roughness values tried on a uniform grid over [0, 1] before per-texel refinement."""
    irls_iterations: int = 3
    """Closed form: L1 reweighting iterations after the least-squares solution (0: plain least squares)."""
    resolution: int | None = field(default=None, metadata=option(flag="--uv-resolution"))
    """UV resolution of the fitted maps (default: the capture's)."""
    cameras: list[str] | None = field(default=None, metadata=option(parse=name_list))
    """Training cameras to fit on, comma-separated (a subset bounds the fit's memory on a large capture). Default: all."""
    frame_step: int = 1
    """Fit on every Nth training frame (lighting) only (1: all)."""
    calibrate_brightness: bool | None = None
    """After the fit, scale the albedo (one gain per channel) so that renders of the training views hold the captured
    total light: L1 fits each pixel's median, and the light the one-bounce model leaves out (interreflections, sheen)
    is one-sided, so without it every render comes out a few per cent too dark. Default: on, unless most training
    frames are OLATs (one LED each), whose dim views' indirect light it would put into the albedo (it cost an
    imported OLAT pose 0.5–1.2 dB on held-out cameras: docs/results/envmap-frames.md)."""
    transport: LightTransport = field(default_factory=LightTransport)

    def validate(self) -> None:
        self.transport.validate(fixed=True)
        if self.solver not in SOLVERS:
            raise GraMiParameterError("solver", f"expected one of {', '.join(SOLVERS)}, got {self.solver!r}")
        if self.iterations < 0:
            raise GraMiParameterError("iterations", f"must be >= 0, got {self.iterations}")
        for name in ("lr_albedo", "lr_roughness", "smooth_albedo", "smooth_roughness"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise GraMiParameterError(name, f"must be a finite number >= 0, got {value}")
        if not 0.0 <= self.min_view_cos < 1.0:
            raise GraMiParameterError("min_view_cos", f"must be in [0, 1), got {self.min_view_cos}")
        if self.roughness_candidates < 3:
            raise GraMiParameterError("roughness_candidates", f"must be at least 3, got {self.roughness_candidates}")
        if self.irls_iterations < 0:
            raise GraMiParameterError("irls_iterations", f"must be >= 0, got {self.irls_iterations}")
        if self.frame_step < 1:
            raise GraMiParameterError("frame_step", f"must be >= 1, got {self.frame_step}")
        if self.resolution is not None and self.resolution < MIN_RESOLUTION:
            raise GraMiParameterError("resolution", f"must be >= {MIN_RESOLUTION}, got {self.resolution}")
        if self.batch_views < 0:
            raise GraMiParameterError("batch_views", f"must be >= 0 (0: every view each step), got {self.batch_views}")
        if self.levels is not None:
            self._validate_levels(self.levels)
        largest = max(self.levels or [self.resolution or 0])
        # per texel during a fit: the maps, their Adam moments and gradients, the atlas and the views' texel lists
        require_memory("levels" if self.levels else "resolution", largest**2 * FIT_BYTES_PER_TEXEL, f"a {largest}² UV fit")

    def _validate_levels(self, levels: list[int]) -> None:
        if not levels or any(r < MIN_RESOLUTION for r in levels) or any(b <= a for a, b in zip(levels, levels[1:], strict=False)):
            raise GraMiParameterError(
                "levels", f"expected increasing UV resolutions of at least {MIN_RESOLUTION}, e.g. 256,512,1024; got {levels}"
            )
        if self.resolution is not None and self.resolution != levels[-1]:
            raise GraMiParameterError(
                "levels", f"the last level ({levels[-1]}) is the fitted resolution; --uv-resolution says {self.resolution}"
            )


@dataclass
class View:
    """A training camera in a training frame; its observed texels and their radiance are in the fitter's
    :class:`~gra_mi.fit.views.ViewStore` (:meth:`MaterialFitter.observation`)."""

    frame: int  # the capture's frame: its image and lighting
    pose: int  # the subject's mesh frame it shows
    camera: str
    count: int  # observed texels

    @property
    def name(self) -> str:
        return f"{self.camera}/frame_{self.frame:04d}"


@dataclass
class FitResult:
    albedo: np.ndarray  # (R, R, 3)
    roughness: np.ndarray  # (R, R, 1)
    observed_cameras: np.ndarray  # (M,) how many cameras saw each valid texel
    loss_curve: list[tuple[float, float, str]] = field(default_factory=list)  # (seconds, mean L1, stage)
    per_view_l1: dict[str, float] = field(default_factory=dict)
    loss_measure: str = "texel space"  # what the curve's L1 is measured on
    evidence: Evidence | None = None  # Adam: what the views say about each texel (the confidence map)
    snapshots: list[tuple[float, np.ndarray, np.ndarray]] = field(default_factory=list)  # Adam: (seconds, albedo, roughness) per checkpoint
    albedo_gain: np.ndarray | None = None  # (3,) the brightness calibration's gain, already applied to ``albedo``


def _camera_visible(scene, camera, geom) -> np.ndarray:
    """(M,) texels facing the camera with nothing in between. On the device, the camera's position a kernel input:
    rays made from NumPy arrays gave Mitsuba's tracing kernel code that depends on the buffers' alignment (an LLVM
    compile for about every view)."""
    import drjit as dr
    import mitsuba as mi

    from gra_mi.core.runtime import opaque, segment

    to_cam = opaque(mi.Point3f, camera.position) - geom.position
    dist = dr.norm(to_cam)
    d = to_cam / dist
    facing = dr.dot(geom.geo_normal, d) > 0
    ray = segment(geom.position + geom.geo_normal * 1e-4, d, dist * (1 - 1e-4))
    return np.asarray(facing & ~scene.ray_test(ray, coherent=False, active=facing))


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
    def __init__(
        self,
        capture: Capture,
        config: FitConfig,
        cache_dir: str | Path | None = None,
        frames: list | None = None,
        ranks: FitRanks | None = None,
    ):
        """``frames``: the capture's frames to fit on (default: its training frames, every ``config.frame_step``-th);
        ``ranks``: the processes the fit runs on (default: this one alone), of which this one fits its share of the
        frames (``train``; ``all_train`` holds every process's)."""
        from gra_mi.render.relighter import Relighter

        ensure_mitsuba()
        self.capture = capture
        self.config = config
        self.headroom: AlbedoHeadroom | None = None  # the least-squares albedo's reach past 1 (fit/headroom.py)
        self.ls = capture.load_scene()
        self.stage = self.ls.stage
        resolution = config.resolution or capture.uv_resolution
        # streamed: 4 frames' visibility held in memory, the rest read from the cache folder
        self.relighter = Relighter(
            self.ls, resolution, cache_dir=cache_dir, visibility_keep=4 if config.batch_views > 0 else None, transport=config.transport
        )
        self._frozen: tuple | None = None  # (the maps' relighter, frame → its light after the first bounce)
        self.atlas = self.relighter.atlas
        self.ranks = ranks or FitRanks()
        self.all_train = frames if frames is not None else [f for f in capture.frames if f.split == "train"][:: config.frame_step]
        self.train = self.ranks.take(self.all_train)
        self.train_cameras = config.cameras or capture.train_cameras
        unknown = [c for c in self.train_cameras if c not in capture.train_cameras]
        if unknown:
            raise GraMiParameterError(
                "cameras", f"{', '.join(unknown)}: not training cameras of {capture.folder} ({', '.join(capture.train_cameras)})"
            )
        self._lighting = {f.frame: capture.lighting(self.stage, f) for f in self.train}
        self._loops: dict = {}  # (frame, camera) → TexelLedLoop of the view's observed texels (streamed: the last)
        self.streamed = config.batch_views > 0
        self.store = ViewStore()  # :meth:`fit` puts it on disk when streamed

    # ----------------------------------------------------------------------------------------------------------

    def gather_views(self, progress_bar=True) -> list[View]:
        """Observations of every training camera in every training frame."""

        views = []
        jobs = [(f.frame, f.mesh_frame, cam) for f in self.train for cam in self.train_cameras if self.capture.has_image(cam, f)]
        for frame, pose, cam_name in progress(jobs, description="observations") if progress_bar else jobs:
            cam = self.stage.camera(cam_name)
            geom = self.relighter.geometry(pose)
            self.ls.set_frame(pose)
            p = np.array(geom.position).T.astype(np.float64)
            seen = _camera_visible(self.ls.scene, cam, geom)
            xyz = cam.project(p[seen])
            image = load_fit_observation(self.capture, cam_name, frame)
            value, covered = sample_image(image, xyz[:, :2])
            ok = covered & (xyz[:, 2] > 0)
            texels = np.flatnonzero(seen)[ok]
            view = View(frame, pose, cam_name, int(texels.size))
            self.store.put(f"observed:{view.name}", texels=texels, observed=value[ok].astype(np.float32))
            views.append(view)
        return views

    def observation(self, view: View) -> tuple[np.ndarray, np.ndarray]:
        """(indices of the valid texels the view observes, (n, 3) their captured radiance)."""
        arrays = self.store.get(f"observed:{view.name}")
        return arrays["texels"], arrays["observed"]

    def cameras_seen(self, views: list[View]) -> np.ndarray:
        """(M,) how many training cameras saw each valid texel in any frame."""
        seen = {cam: np.zeros(self.atlas.num_texels, bool) for cam in self.train_cameras}
        for v in views:
            seen[v.camera][self.observation(v)[0]] = True
        return np.sum(self.ranks.sum(np.stack(list(seen.values()))) > 0, axis=0).astype(np.int64)

    def parts(self, view: View, roughness: np.ndarray, texels: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(D, S) at the view's observed texels (``texels``, if already read) for per-texel roughness (M,). Only those
        texels are shaded; their LED-loop inputs are gathered once per view (streamed: kept for the last view only)."""
        import mitsuba as mi

        if view.count == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        texels = self.observation(view)[0] if texels is None else texels
        diffuse, spec = self._loop(view, texels).run(mi.Float(np.asarray(roughness, np.float32)[texels]))
        return columns(diffuse), columns(spec)

    def grid_parts(self, view: View, candidates: np.ndarray, texels: np.ndarray):
        """(D, (S for each candidate roughness)) at the view's ``texels`` (a view with texels), as Dr.Jit arrays left on
        the device: every texel at each candidate value, from one walk over the LEDs (:meth:`parts` for one value at a
        time, its result for each)."""
        import drjit as dr
        import mitsuba as mi

        # opaque: the candidates are kernel inputs, not literals (one kernel for every grid, float32 as parts' values)
        return self._loop(view, texels).run(tuple(dr.opaque(mi.Float, float(np.float32(r))) for r in candidates))

    def _loop(self, view: View, texels: np.ndarray):
        """The view's LED loop over ``texels``: its inputs gathered once (streamed: kept for the last view only)."""
        from gra_mi.render.shading import TexelLedLoop

        key = (view.frame, view.camera)
        if key not in self._loops:
            if self.streamed:
                self._loops.clear()
            self._loops[key] = TexelLedLoop.build(
                self.relighter.geometry(view.pose), self.relighter.visibility(view.pose, False), texels, self.relighter.leds(False),
                self._lighting[view.frame], self.stage.camera(view.camera).position, self.frozen_indirect(view.frame, view.pose, view.camera),
            )  # fmt: skip
        return self._loops[key]

    # ----------------------------------------------------------------------------------------------------------

    def fit(self, out: Path | None = None, start: LevelStart | None = None) -> FitResult:
        """The closed-form solution (or, at a finer level, the coarser level's maps), then (solver "adam") the
        optimisation of the maps against the images."""
        self.store = ViewStore.for_fit(self.streamed, out, self.ranks.rank)
        try:
            closed = self.fit_closed_form(out) if start is None else self.start_from(start)
            for _ in range(INDIRECT_ROUNDS if self.config.transport.bounces > 1 else 0):
                self.freeze_indirect(closed)  # the closed form again, its light after the first bounce held fixed
                closed = self.fit_closed_form(None) if start is None else self.start_from(start)
            result = closed if self.config.solver == "closed-form" else self.optimize(closed, out, start)
        finally:
            self.store.close()
        return self.calibrate_brightness(result) if self.calibrates else result

    @property
    def calibrates(self) -> bool:
        """Whether the fit ends with the brightness calibration: as configured, else unless most training frames are
        OLATs (lit by one LED)."""
        if self.config.calibrate_brightness is not None:
            return self.config.calibrate_brightness
        alone = sum(int(np.count_nonzero(light.max(axis=1))) == 1 for light in self._lighting.values())
        return self.ranks.total(alone) <= len(self.all_train) / 2

    def freeze_indirect(self, result: FitResult) -> None:
        """Hold the light after the first bounce at what ``result``'s maps make of it: from now on every view's LED loop
        adds it (the operator is linear in the albedo of the hit texels, so a closed-form solve with it fixed, repeated,
        converges to the maps that explain the images with it)."""
        maps = self.relighter.with_maps(result.albedo, result.roughness)
        light = {f.frame: maps.indirect(f.mesh_frame, self._lighting[f.frame], [], [], False) for f in self.train}
        self._frozen = (maps, light)
        self._loops.clear()

    def frozen_indirect(self, frame: int, pose: int, camera: str) -> tuple[np.ndarray, np.ndarray] | None:
        """(what each texel's diffuse layer takes in, the specular light toward ``camera``) of the frozen light after the
        first bounce in training frame ``frame``; None while the fit models one bounce."""
        import mitsuba as mi

        if self._frozen is None:
            return None
        maps, light = self._frozen
        op, along_rays, diffuse = light[frame]
        spec = op.specular_response(maps.geometry(pose), self.stage.camera(camera).position, mi.Float(maps.roughness), along_rays)
        return diffuse, columns(spec)

    def calibrate_brightness(self, result: FitResult) -> FitResult:
        """One gain per albedo channel (a ratio of sums) that gives renders of every training view (rasterised as the
        relit images are, every covered pixel, grazing ones included) the captured total light, each view weighted
        by its own brightness. The roughness and the specular light stay as fitted."""
        from dataclasses import replace

        relighter = self.relighter.with_maps(result.albedo, result.roughness)  # the visibility the fit traced
        sums = np.zeros((3, 3))  # rows: captured, diffuse, specular
        for entry in self.train:
            for cam in (c for c in self.train_cameras if self.capture.has_image(c, entry)):
                shading, _ = relighter.shade(entry.mesh_frame, cam, self._lighting[entry.frame])
                truth = load_fit_observation(self.capture, cam, entry.frame)
                mask = subject_mask(truth)
                if not mask.any():
                    continue
                parts = np.concatenate([relighter.albedo * shading.diffuse_unit, shading.specular], axis=1)
                image = relighter.rasterize(entry.mesh_frame, cam, self.atlas.scatter(parts))  # one pass: diffuse, specular
                diffuse, specular = image[..., :3], image[..., 3:6]
                weight = 1.0 / max(float(truth[mask, :3].mean()), 1e-12)
                for row, part in enumerate((truth[..., :3], diffuse, specular)):
                    sums[row] += weight * part[mask].sum(axis=0, dtype=np.float64)
        sums = self.ranks.sum(sums)
        if not sums[1].all():
            logger.warning("brightness calibration skipped: a colour channel has no diffuse light in any training view")
            return result
        gain = np.clip((sums[0] - sums[2]) / sums[1], 0.5, 2.0)
        logger.info("brightness calibration: albedo gain %s", np.round(gain, 4).tolist())
        # Texels no view saw keep the default (closed form); filled ones (Adam) come from calibrated neighbours.
        fitted = (result.observed_cameras > 0) | (result.evidence is not None)
        albedo = self.atlas.gather(result.albedo)
        albedo[fitted] = np.clip(albedo[fitted] * gain, 0.0, 1.0)
        return replace(result, albedo=self.atlas.scatter(albedo.astype(np.float32), fill=DEFAULT_ALBEDO), albedo_gain=gain)

    def optimize(self, closed: FitResult, out: Path | None = None, start: LevelStart | None = None) -> FitResult:
        """Adam on the UV maps (:mod:`gra_mi.fit.optimize`) from the closed-form albedo and the median of its roughness
        (or, at a finer level, from the coarser level's maps, its highlight evidence carried).

        The closed form's per-texel roughness is mostly noise (on `small`'s path-traced capture MAE 0.20, against
        0.06 for a constant), so only its median is kept; texels no camera saw start from their neighbours' albedo.
        """
        from gra_mi.fit import optimize as opt

        cfg, clock = self.config, time.perf_counter()
        offset = closed.loss_curve[-1][0] if closed.loss_curve else 0.0
        batches = opt.build_batches(self, cfg.min_view_cos, store=self.store)
        geom = self.relighter.geometry(self.all_train[0].mesh_frame)  # the same graph in every process
        graph = SurfaceGraph.build(np.array(geom.position).T.astype(np.float64), np.array(geom.normal).T.astype(np.float64))
        albedo_cf, roughness_cf = self.atlas.gather(closed.albedo), self.atlas.gather(closed.roughness)[:, 0]
        albedo, roughness = (albedo_cf, roughness_cf) if start is not None else self._adam_start(graph, closed)
        evidence = opt.gather_evidence(batches, albedo, roughness)
        highlights = evidence.highlights > 0
        held = None if start is None else start.carried_highlights(self.atlas) & ~highlights
        settings = opt.OptimizeSettings(
            cfg.iterations, cfg.lr_albedo, cfg.lr_roughness, cfg.smooth_albedo, cfg.smooth_roughness, batch_views=cfg.batch_views, seed=cfg.seed
        )  # fmt: skip
        closed_l1 = opt.image_l1(batches, albedo_cf, roughness_cf, opt.curve_views(batches))
        albedo, roughness, curve, snapshots = opt.optimize_maps(
            batches, graph, albedo, roughness, evidence.views > 0, highlights, settings,
            checkpoint=None if out is None else out / "optimize.npz", clock_offset=offset + time.perf_counter() - clock,
            held_roughness=held,
        )  # fmt: skip
        per_view = opt.view_l1(batches, albedo, roughness)
        measure = "image space, relative" + (f" ({len(opt.curve_views(batches))} of {len(batches)} views)" if batches.streamed else "")
        first = closed.loss_curve[0][2] if start is not None else "closed form"
        return FitResult(
            self.atlas.scatter(albedo.astype(np.float32), fill=DEFAULT_ALBEDO),
            self.atlas.scatter(roughness[:, None].astype(np.float32), fill=DEFAULT_ROUGHNESS),
            closed.observed_cameras,
            [(offset, closed_l1, first)] + [(t, data, label) for t, data, _, label in curve],
            per_view, measure, evidence, snapshots,
        )  # fmt: skip

    def _adam_start(self, graph: SurfaceGraph, closed: FitResult) -> tuple[np.ndarray, np.ndarray]:
        """The closed form's albedo (unobserved texels filled from their neighbours) and its median roughness."""
        observed = closed.observed_cameras > 0
        albedo_cf, roughness_cf = self.atlas.gather(closed.albedo), self.atlas.gather(closed.roughness)[:, 0]
        albedo = np.clip(graph.fill(albedo_cf, observed.astype(np.float64), ALBEDO_FILL_STRENGTH, DEFAULT_ALBEDO), 0.0, 1.0)
        r0 = float(np.median(roughness_cf[observed])) if observed.any() else DEFAULT_ROUGHNESS
        return albedo, np.full(self.atlas.num_texels, r0)

    def start_from(self, start: LevelStart) -> FitResult:
        """A finer level's starting point: the coarser level's roughness resampled onto this atlas, the albedo solved
        per texel at that roughness (one LED loop per view, the closed form's last step without its roughness grid:
        the finer texels' own detail), the coarse albedo where no camera sees a texel."""
        clock = time.perf_counter()
        views = self.gather_views()
        seen = self.cameras_seen(views)
        albedo_map, roughness_map = start.resampled(self.atlas)
        roughness = self.atlas.gather(roughness_map)[:, 0]
        albedo, _ = self._albedo_irls(views, roughness, [], clock, lambda **_: None)
        albedo = np.where(seen[:, None] > 0, albedo, self.atlas.gather(albedo_map))
        label, seconds = f"{start.resolution}² maps upsampled", start.seconds + time.perf_counter() - clock
        albedo_map = self.atlas.scatter(albedo.astype(np.float32), fill=DEFAULT_ALBEDO)
        return FitResult(albedo_map, roughness_map, seen, [(seconds, float("nan"), label)])

    def fit_closed_form(self, out: Path | None = None) -> FitResult:
        """Roughness grid with closed-form albedo per texel, then L1 by reweighting (checkpointed)."""
        cfg, start = self.config, time.perf_counter()
        checkpoint = None if out is None else out / "checkpoint.npz"
        state = read_checkpoint_npz(checkpoint) if checkpoint is not None and checkpoint.is_file() else {}
        curve: list[tuple[float, float, str]] = [tuple(x) for x in json.loads(str(state["curve"]))] if "curve" in state else []
        self.ranks.agree(sorted(state), f"{checkpoint}: what the closed form resumes from")

        def save(**arrays) -> None:
            state.update(arrays)
            if checkpoint is not None and self.ranks.main:
                with atomic_path(checkpoint) as tmp, open(tmp, "wb") as fh:
                    np.savez(fh, **{**state, "curve": json.dumps(curve)})

        views = self.gather_views()
        cameras_seen = self.cameras_seen(views)
        grid = np.linspace(0.0, 1.0, cfg.roughness_candidates)
        if "grid_error" not in state:
            save(grid_error=self.grid_error(views, grid))
        roughness = refine_on_grid(state["grid_error"], grid)
        roughness[cameras_seen == 0] = DEFAULT_ROUGHNESS
        curve.append((time.perf_counter() - start, float("nan"), "roughness grid"))
        albedo, per_view = self._albedo_irls(views, roughness, curve, start, save)
        albedo_map = self.atlas.scatter(albedo.astype(np.float32), fill=DEFAULT_ALBEDO)
        return FitResult(albedo_map, self.atlas.scatter(roughness[:, None], fill=DEFAULT_ROUGHNESS), cameras_seen, curve, per_view)

    def grid_error(self, views, grid: np.ndarray) -> np.ndarray:
        """(candidates, M) squared error of each roughness candidate with its closed-form (least-squares) albedo."""
        import mitsuba as mi

        sums = GridSums(self.atlas.num_texels, len(grid))
        for v in progress(views, description="roughness grid"):  # view by view: a streamed fit reads each once
            if v.count == 0:
                continue
            texels, o = self.observation(v)
            diffuse, specs = self.grid_parts(v, grid, texels)
            sums.add(mi.UInt32(texels.astype(np.uint32)), mi.Color3f(*o.T.astype(np.float32)), diffuse, specs)
        return sums.error(self.ranks)

    def _albedo_irls(self, views, roughness: np.ndarray, curve: list, start: float, save) -> tuple[np.ndarray, dict[str, float]]:
        """Albedo at the chosen roughness: least squares, then L1 by reweighting (each observation weighted by 1 / its
        residual at the previous albedo); and each view's mean L1."""

        self.store_parts(views, roughness)
        return self.solve_albedo(views, curve, start, lambda **arrays: save(**arrays, roughness=roughness))

    def store_parts(self, views, roughness: np.ndarray) -> None:
        """Each view's (D, S) at its observed texels for per-texel ``roughness``, kept in the view store."""
        for v in progress(views, description="albedo"):
            texels, _ = self.observation(v)
            d, s = self.parts(v, roughness, texels)
            self.store.put(f"parts:{v.name}", d=d, s=s)

    def solve_albedo(self, views, curve: list, start: float, save) -> tuple[np.ndarray, dict[str, float]]:
        """The albedo that explains the stored parts: least squares, then L1 by reweighting; and each view's mean L1."""
        m = self.atlas.num_texels
        albedo = None
        for it in range(self.config.irls_iterations + 1):
            num, den = np.zeros((m, 3)), np.zeros((m, 3))
            for v in views:
                texels, o, d, s = self.observation_parts(v)
                w = 1.0 if albedo is None else 1.0 / np.maximum(np.abs(o - (albedo[texels] * d + s)), L1_DELTA)
                np.add.at(num, texels, w * d * (o - s))
                np.add.at(den, texels, w * d * d)
            num, den = self.ranks.sum(num), self.ranks.sum(den)
            self.headroom = AlbedoHeadroom.of(num, den) if it == 0 else self.headroom  # before the clip hides a wrong scale
            with np.errstate(invalid="ignore", divide="ignore"):
                albedo = np.where(den > 0, np.clip(num / den, 0.0, 1.0), DEFAULT_ALBEDO)
            per_view = self._irls_residuals(views, albedo)
            total, count = sum(t for t, _ in per_view.values()), sum(c for _, c in per_view.values())
            curve.append((time.perf_counter() - start, total / max(count, 1), "least squares" if it == 0 else f"L1 reweighting {it}"))
            save(albedo=albedo)
        return albedo, {name: t / c if c else float("nan") for name, (t, c) in per_view.items()}

    def observation_parts(self, view: View) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        texels, observed = self.observation(view)
        parts = self.store.get(f"parts:{view.name}")
        return texels, observed.astype(np.float64), parts["d"], parts["s"]

    def _irls_residuals(self, views, albedo: np.ndarray) -> dict[str, tuple[float, int]]:
        """Per view: (Σ |residual|, number of values) at ``albedo``."""
        out = {}
        for v in views:
            texels, o, d, s = self.observation_parts(v)
            residual = np.abs(o - (albedo[texels] * d + s))
            out[v.name] = (float(residual.sum()), residual.size)
        return self.ranks.merged(out)


def run_fit(capture_dir: str | Path, out: str | Path, config: FitConfig, overwrite: bool = False) -> tuple[FitResult, Path | None]:
    """Fit ``config``'s maps to a capture into ``out`` (resumes a run of the same capture and config there; a folder
    made by another refuses, or with ``overwrite`` starts over); returns the result and the report's path. Under
    torchrun, the processes fit together (:mod:`gra_mi.fit.ranks`): rank 0 claims the folder and writes the outputs
    (the others return None for the report once every process has fitted, without waiting for it)."""

    config.validate()
    capture = Capture.load(capture_dir)
    capture.check_images()
    ensure_mitsuba()
    ranks = FitRanks.from_launcher()
    out = claim_output(out, "fit", {"capture": capture_dir}, config, overwrite=overwrite) if ranks.main else Path(out)
    ranks.barrier()  # the others start once the folder is claimed (or emptied by --overwrite)
    make_fitter = partial(MaterialFitter, ranks=ranks)
    if config.levels:
        fitter, result = fit_levels(capture, config, out, make_fitter)
    else:
        fitter = make_fitter(capture, config, cache_dir=out / "cache")
        result = fitter.fit(out)
    ranks.close()  # the outputs are rank 0's alone
    return result, write_fit_outputs(fitter, result, out, config) if ranks.main else None  # levels included
