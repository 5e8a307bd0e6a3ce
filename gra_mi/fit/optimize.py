"""Dr.Jit optimisation of the UV albedo and roughness maps (paper Eq. 3), with a surface prior.

    loss = Σ_views w_v Σ_pixels |Σ_t∈footprint ω_pt (a_t ⊙ D_t + S_t(r_t)) − O_p| / (3 N)  +  λ_a E(a)  +  λ_r E(r)

- the data term is the paper's L1 between the one-bounce render and every fully covered training pixel, predicted
  as the average of the texels its footprint covers (:func:`~gra_mi.fit.footprints.pixel_footprints`), each view weighted by 1 / its mean
  observed radiance so that a dim envmap frame counts as much as a bright uniformly lit one;
- E is the mean squared difference across the edges of the :class:`~gra_mi.fit.prior.SurfaceGraph` (smoothness on
  the body, across seams, not across chart boundaries); roughness gets the stronger weight, as its evidence is
  sparse (highlights) where albedo's is dense (every observation);
- D (diffuse per unit albedo) does not depend on the material and is computed once per view; S and ∂S/∂r come
  from the same LED loop as every other renderer (cached per-LED visibility, LEDs that are off skipped), with the
  analytic roughness derivative; Dr.Jit's reverse-mode AD carries the rest (gathers, the loss, the prior) back to
  the textures;
- texels without highlight evidence (and, for albedo, texels no view saw) are not moved by Adam: they take the
  prior's harmonic interpolation of their neighbours (:meth:`~gra_mi.fit.prior.SurfaceGraph.filler`), refreshed
  every checkpoint;
- Dr.Jit's Adam (``drjit.opt.Adam``, its moments checkpointed so that a resumed run ends where an uninterrupted one
  does), with the learning rate decaying to a tenth; full batch (every view each step, all held in memory), or
  minibatches of views read from scratch files with their gradients accumulated (:mod:`gra_mi.fit.views`), whose
  memory does not grow with the capture;
- a step's views are joined (:meth:`ViewBatch.join`, :meth:`~gra_mi.render.shading.TexelLedLoop.concat`): one LED
  loop, one footprint average and one backward pass for up to :data:`BATCH_ENTRIES` entries, not one per view;
- on several processes (:mod:`gra_mi.fit.ranks`) each holds the views of its frames, indexed among every process's;
  the data term, its gradient, the evidence and the per-view errors are summed or gathered across them, and the prior's
  gradient counts once (rank 0's).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_path, read_checkpoint_npz
from gra_mi.core.progress import progress
from gra_mi.core.runtime import columns, concat, opaque
from gra_mi.fit.footprints import view_footprints
from gra_mi.fit.views import batch_at, curve_sample
from gra_mi.render.shading import TexelLedLoop

FILL_STRENGTH = 0.1  # harmonic fill: highlight texels (confidence 1) move little, the others interpolate them
HIGHLIGHT_CHANGE = 0.05  # an observation is a highlight if roughness ± 0.1 changes it by at least 5 %
CURVE_VIEWS = 32  # a streamed fit measures its convergence curve on this many evenly spaced views
# Footprint entries per joined batch of views: one LED-loop kernel shades them all (one per view was dominated by
# launches and host work), and the memory of a step's AD graph stays bounded (a few hundred MB).
BATCH_ENTRIES = 1 << 23


@dataclass
class ViewBatch:
    """Training views shaded together: their fully covered pixels, the texels they see, and everything that stays
    fixed while the maps change. A pixel's prediction is its footprint's average of texel radiance (``entry_*``:
    which lane, which pixel, what weight), as the camera integrates it; comparing pixels with single texels instead
    blurs highlights on curved parts (a pixel spans up to ~25° of normal on an arm at 256 × 135) into wrong
    roughness. One view's batch is built from its footprints; a step's views are joined (:meth:`join`) so that one
    LED-loop kernel shades them all: lanes, pixels and entries one view after another."""

    names: list[str]  # the views, in order
    count: int  # lanes of the LED loop (each view's texels)
    texels: mi.UInt32  # (count,) valid-texel index of each lane
    pixels: int
    observed: mi.Color3f  # (pixels,)
    pixel_weight: mi.Float  # (pixels,) its view's weight: 1 / the view's mean observed radiance
    view_lanes: np.ndarray  # (views,) lanes of each view
    view_pixels: np.ndarray  # (views,) pixels of each view
    weights: np.ndarray  # (views,) each view's weight
    entry_lane: mi.UInt32
    entry_pixel: mi.UInt32
    entry_weight: mi.Float
    loop: TexelLedLoop

    @classmethod
    def join(cls, parts: list[ViewBatch]) -> ViewBatch:
        """The views of ``parts`` as one batch (their lanes, pixels and entries one after another)."""
        if len(parts) == 1:
            return parts[0]
        lane_start = np.cumsum([0] + [b.count for b in parts[:-1]])
        pixel_start = np.cumsum([0] + [b.pixels for b in parts[:-1]])

        def shifted(name: str, starts) -> mi.UInt32:
            return concat(mi.UInt32, [getattr(b, name) + dr.opaque(mi.UInt32, int(s)) for b, s in zip(parts, starts, strict=True)])

        def joined(name: str):
            return concat(type(getattr(parts[0], name)), [getattr(b, name) for b in parts])

        batch = cls(
            [n for b in parts for n in b.names], int(sum(b.count for b in parts)), joined("texels"), int(sum(b.pixels for b in parts)),
            joined("observed"), joined("pixel_weight"), *(np.concatenate([getattr(b, k) for b in parts]) for k in ("view_lanes", "view_pixels", "weights")),
            shifted("entry_lane", lane_start), shifted("entry_pixel", pixel_start), joined("entry_weight"),
            TexelLedLoop.concat([b.loop for b in parts]),
        )  # fmt: skip
        return batch

    @property
    def entries(self) -> int:
        return dr.width(self.entry_lane)

    def lane_weights(self) -> np.ndarray:
        """(count,) each lane's view weight."""
        return np.repeat(self.weights, self.view_lanes)

    def per_view(self, pixel_values: np.ndarray) -> list[np.ndarray]:
        """(pixels, ...) values split into each view's."""
        return np.split(pixel_values, np.cumsum(self.view_pixels)[:-1])

    def shade(self, roughness: mi.Float) -> tuple[mi.Color3f, mi.Color3f, mi.Color3f]:
        """(D per unit albedo, S, ∂S/∂r) at the batch's lanes for their roughness: one LED loop."""
        return self.loop.run(roughness, roughness_derivative=True)

    def to_pixels(self, radiance: mi.Color3f) -> mi.Color3f:
        """Lane radiance (count,) → the pixels' footprint averages (pixels,)."""
        value = dr.gather(mi.Color3f, radiance, self.entry_lane) * self.entry_weight
        out = dr.zeros(mi.Color3f, self.pixels)
        dr.scatter_reduce(dr.ReduceOp.Add, out, value, self.entry_pixel)
        return out


@dataclass(frozen=True)
class ViewKey:
    name: str  # camera/frame_NNNN
    frame: int  # the capture's frame: its image and lighting
    pose: int  # the subject's mesh frame
    camera: str


class TrainingViews:
    """The Adam stage's training views, in the capture's frame-major order. Held: the views built once and kept,
    joined into batches of about :data:`BATCH_ENTRIES` (full batch; fastest on a small capture). Streamed (``store``
    on disk): each view's footprint arrays written once, and the views a step uses rebuilt from them (and their
    frames' cached visibility) and joined, so memory holds the views of one step, not all."""

    def __init__(self, fitter, min_view_cos: float = 0.0, store=None, progress_bar: bool = True):
        self.fitter, self.store, self.ranks = fitter, store, fitter.ranks
        self._held: list[ViewBatch] = []
        local: list[tuple[ViewKey, int]] = []
        pending: list[ViewBatch] = []
        jobs = [(f.frame, f.mesh_frame, cam) for f in fitter.train for cam in fitter.train_cameras if fitter.capture.has_image(cam, f)]
        for frame, pose, cam in progress(jobs, description="pixel footprints") if progress_bar else jobs:
            arrays = view_footprints(fitter, frame, pose, cam, min_view_cos)
            if arrays is None:
                continue
            key = ViewKey(f"{cam}/frame_{frame:04d}", frame, pose, cam)
            local.append((key, int(arrays["observed"].shape[0])))
            if self.streamed:
                store.put(f"footprints:{key.name}", **arrays)
                continue
            pending.append(self._build(key, arrays))
            if sum(b.entries for b in pending) >= BATCH_ENTRIES:
                self._held.append(ViewBatch.join(pending))
                pending = []
        if pending:
            self._held.append(ViewBatch.join(pending))
        self._index_views(local)

    def _index_views(self, local: list[tuple[ViewKey, int]]) -> None:
        """Every process's views in the capture's frame-major order (names, pixels), and where this one's sit."""
        frame_order = {f.frame: k for k, f in enumerate(self.fitter.all_train)}
        camera_order = {c: k for k, c in enumerate(self.fitter.train_cameras)}
        place = {key.name: ((frame_order[key.frame], camera_order[key.camera]), pixels) for key, pixels in local}
        every = sorted(self.ranks.merged(place).items(), key=lambda item: item[1][0])
        self.names: list[str] = [name for name, _ in every]
        self.pixels: list[int] = [pixels for _, (_, pixels) in every]
        index = {name: k for k, name in enumerate(self.names)}
        self.keys: dict[int, ViewKey] = {index[key.name]: key for key, _ in local}  # this process's, by that index

    @property
    def streamed(self) -> bool:
        return self.store is not None and self.store.on_disk

    @property
    def n_obs(self) -> int:
        return sum(self.pixels)

    def __len__(self) -> int:
        """Every process's views (the fit's, whichever process holds them)."""
        return len(self.names)

    def in_batches(self, views: np.ndarray | None = None):
        """The :class:`ViewBatch` es that shade this process's share of ``views`` (indices among every process's
        views, default all), in order. Held views are shaded all together; a subset (a minibatch) needs them
        streamed."""
        views = np.arange(len(self)) if views is None else np.asarray(views, np.int64)
        if not self.streamed:
            if not np.array_equal(views, np.arange(len(self))):
                raise ValueError("held training views are shaded all together (full batch); minibatches need them streamed")
            return iter(self._held)
        return self._streamed_batches(views)

    def _streamed_batches(self, views: np.ndarray):
        """Joined as a step's are: at most the fit's views per step (its memory's bound) and BATCH_ENTRIES at once."""
        at_once = self.fitter.config.batch_views or len(self)
        pending: list[ViewBatch] = []
        for k in (int(k) for k in views if int(k) in self.keys):
            key = self.keys[k]
            pending.append(self._build(key, self.store.get(f"footprints:{key.name}")))
            if len(pending) >= at_once or sum(b.entries for b in pending) >= BATCH_ENTRIES:
                yield ViewBatch.join(pending)
                pending = []
        if pending:
            yield ViewBatch.join(pending)

    def _build(self, key: ViewKey, a: dict[str, np.ndarray]) -> ViewBatch:
        f = self.fitter
        loop = TexelLedLoop.build(
            f.relighter.geometry(key.pose), f.relighter.visibility(key.pose, False), a["lanes"], f.relighter.leds(False),
            f._lighting[key.frame], f.stage.camera(key.camera).position, f.frozen_indirect(key.frame, key.pose, key.camera),
        )  # fmt: skip
        pixels, weight = int(a["observed"].shape[0]), float(a["weight"])
        return ViewBatch(
            [key.name], loop.count, mi.UInt32(a["lanes"]), pixels, mi.Color3f(*a["observed"].T), dr.opaque(mi.Float, weight, pixels),
            np.array([loop.count]), np.array([pixels]), np.array([weight]),
            mi.UInt32(a["entry_lane"]), mi.UInt32(a["entry_pixel"]), mi.Float(a["entry_weight"]), loop,
        )  # fmt: skip


def build_batches(fitter, min_view_cos: float = 0.0, progress_bar: bool = True, store=None) -> TrainingViews:
    """The :class:`TrainingViews` of a :class:`~gra_mi.fit.materials.MaterialFitter` (held, or streamed through
    ``store``)."""
    return TrainingViews(fitter, min_view_cos, store, progress_bar)


def _predict(b: ViewBatch, albedo: mi.Color3f, roughness: mi.Float) -> mi.Color3f:
    diffuse, spec, _ = b.shade(dr.gather(mi.Float, roughness, b.texels))
    return b.to_pixels(dr.gather(mi.Color3f, albedo, b.texels) * diffuse + spec)


def image_l1(batches: TrainingViews, albedo: np.ndarray, roughness: np.ndarray, views: np.ndarray | None = None) -> float:
    """The optimiser's data term (weighted mean L1 over the pixels of ``views``, default all) for (M, 3) albedo and
    (M,) roughness."""
    a, r = mi.Color3f(*np.asarray(albedo, np.float32).T), mi.Float(np.asarray(roughness, np.float32))
    views = np.arange(len(batches)) if views is None else views
    total = 0.0
    for b in batches.in_batches(views):
        residual = np.abs(columns(_predict(b, a, r) - b.observed))
        total += sum(float(part.sum()) * w for part, w in zip(b.per_view(residual), b.weights, strict=True))
    return batches.ranks.total(total) / (3.0 * max(sum(batches.pixels[int(k)] for k in views), 1))


def curve_views(batches: TrainingViews) -> np.ndarray:
    """The views the convergence curve is measured on: all, or (streamed) an evenly spaced sample."""
    return curve_sample(len(batches), CURVE_VIEWS) if batches.streamed else np.arange(len(batches))


def view_l1(batches: TrainingViews, albedo: np.ndarray, roughness: np.ndarray) -> dict[str, float]:
    """Mean absolute L1 over each view's pixels (radiance units), by view name in the views' order."""
    a, r = mi.Color3f(*np.asarray(albedo, np.float32).T), mi.Float(np.asarray(roughness, np.float32))
    out = {}
    for b in batches.in_batches():
        parts = b.per_view(np.abs(columns(_predict(b, a, r) - b.observed)))
        out |= {name: float(part.mean()) for name, part in zip(b.names, parts, strict=True)}
    every = batches.ranks.merged(out)
    return {name: every[name] for name in batches.names}


@dataclass
class Evidence:
    """What the training views say about each texel (the confidence map)."""

    views: np.ndarray  # (M,) observations (camera × frame)
    highlights: np.ndarray  # (M,) observations whose radiance roughness ± 0.1 changes by ≥ HIGHLIGHT_CHANGE
    information: np.ndarray  # (M,) Σ (w ∂S/∂r)²: Fisher information of roughness under relative noise


def gather_evidence(batches: TrainingViews, albedo: np.ndarray, roughness: np.ndarray) -> Evidence:
    """Per texel: in how many views it appears, in how many of them its radiance depends on roughness enough to
    count as a highlight (at the given maps), and the Fisher information of its roughness."""
    m = roughness.shape[0]
    views, highlights, information = np.zeros(m), np.zeros(m), np.zeros(m)
    a_all, r_all = mi.Color3f(*albedo.T.astype(np.float32)), mi.Float(roughness.astype(np.float32))
    for b in batches.in_batches():
        diffuse, spec, dspec = b.shade(dr.gather(mi.Float, r_all, b.texels))
        pred = dr.gather(mi.Color3f, a_all, b.texels) * diffuse + spec
        pred, dspec = columns(pred), columns(dspec)
        texels = np.array(b.texels).astype(np.int64)
        change = 0.1 * np.abs(dspec).mean(axis=1) / np.maximum(pred.mean(axis=1), 1e-8)
        np.add.at(views, texels, 1)
        np.add.at(highlights, texels, change >= HIGHLIGHT_CHANGE)
        np.add.at(information, texels, np.sum(np.square(b.lane_weights()[:, None] * dspec), axis=1))
    return Evidence(*batches.ranks.sum(np.stack([views, highlights, information])))


@dataclass
class OptimizeSettings:
    iterations: int
    lr_albedo: float
    lr_roughness: float
    smooth_albedo: float
    smooth_roughness: float
    checkpoint_every: int = 10
    batch_views: int = 0  # views per step (0: all)
    seed: int = 0  # of the minibatch order


OPTIMIZER = "drjit.opt.Adam"  # part of a checkpoint's settings: one of another optimiser is refused, not resumed


def optimize_maps(
    batches: TrainingViews,
    graph,
    albedo: np.ndarray,
    roughness: np.ndarray,
    observed: np.ndarray,
    has_highlight: np.ndarray,
    settings: OptimizeSettings,
    checkpoint: Path | None = None,
    progress_bar: bool = True,
    clock_offset: float = 0.0,
    held_roughness: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[tuple[float, float, float, str]], list[tuple[float, np.ndarray, np.ndarray]]]:
    """Adam on the (M, 3) albedo of ``observed`` texels and the (M,) roughness of those ``has_highlight``; the others
    take the prior's interpolation of their neighbours (refreshed at every checkpoint). Returns the maps, the curve
    (seconds, data L1, total loss, label) and the maps at each checkpoint (seconds, albedo, roughness), for
    time-to-error curves.

    ``checkpoint`` (an .npz) is written every ``checkpoint_every`` iterations and at the end, with Adam's moments; a
    run finding one resumes from it. With ``settings.batch_views``, each step uses that many views
    (:func:`~gra_mi.fit.views.batch_at`), and the curve is measured on a fixed sample of views (``curve_views``).
    ``held_roughness``: texels whose roughness a coarser level measured and this one cannot (no highlight at this
    resolution): kept as given, and anchors of the fill.
    """

    run = MapOptimizer(batches, graph, observed, has_highlight, settings, held_roughness)
    run.set_maps(albedo, roughness)
    first = run.resume(checkpoint, roughness.shape[0]) if checkpoint is not None and checkpoint.is_file() else 0
    batches.ranks.agree(first, f"{checkpoint}: the Adam step it resumes from")
    run.start = time.perf_counter() - (run.curve[-1][0] if run.curve else clock_offset)
    if not run.curve:
        run.record("initial")
    iterations = range(first, settings.iterations)
    for it in progress(list(iterations), description="optimise maps") if progress_bar else iterations:
        run.step(it)
        done = it + 1
        if done % settings.checkpoint_every == 0 or done == settings.iterations:
            run.record(f"Adam {done}")
            if checkpoint is not None and batches.ranks.main:
                run.save(checkpoint, done)
    albedo_now, roughness_now = run.maps()
    return albedo_now, roughness_now, run.curve, run.snapshots


class MapOptimizer:
    """The loss of :func:`optimize_maps` and Dr.Jit's Adam on the two maps (``mask_updates``: a texel without a
    gradient keeps its moments), with the texels the data does not constrain held at the prior's fill. Each view's
    part of the loss is differentiated as soon as it is computed (gradients accumulate on the maps), so that one
    view's graph is alive at a time: the paper's gradient accumulation, with a step's views as its batch."""

    def __init__(self, batches: TrainingViews, graph, observed, has_highlight, settings: OptimizeSettings, held_roughness=None):
        if 0 < settings.batch_views < len(batches) and not batches.streamed:
            raise ValueError(f"minibatches of {settings.batch_views} views need the training views streamed (a store on disk)")
        self.batches, self.settings, self.observed, self.has_highlight = batches, settings, observed, has_highlight
        self.anchors = has_highlight if held_roughness is None else has_highlight | held_roughness
        self.n_obs = batches.n_obs
        self.curve_views = curve_views(batches)
        self.ei, self.ej = mi.UInt32(graph.i.astype(np.uint32)), mi.UInt32(graph.j.astype(np.uint32))
        self.n_edges = max(graph.num_edges, 1)
        self.gate_all = mi.Float(has_highlight.astype(np.float32))
        # Texels the data does not constrain (no highlight: roughness; never seen: albedo) are not moved by Adam, whose
        # normalised steps would make them wander on the prior's tiny gradient; they take the harmonic interpolation
        # of their neighbours, refreshed as the others move.
        self.fill_roughness = graph.filler(self.anchors.astype(np.float64), FILL_STRENGTH)
        self.fill_albedo = graph.filler(observed.astype(np.float64), FILL_STRENGTH)
        self.free = {"albedo": mi.Bool(observed), "roughness": mi.Bool(has_highlight)}
        self.adam = dr.opt.Adam(lr=1.0, mask_updates=True)
        self.settings_json = json.dumps({**asdict(settings), "optimizer": OPTIMIZER}, sort_keys=True)
        self.curve: list[tuple[float, float, float, str]] = []
        self.snapshots: list[tuple[float, np.ndarray, np.ndarray]] = []
        self.start = time.perf_counter()

    def set_maps(self, albedo: np.ndarray, roughness: np.ndarray) -> None:
        self.adam["albedo"] = mi.Color3f(*np.asarray(albedo, np.float32).reshape(-1, 3).T)
        self.adam["roughness"] = mi.Float(np.asarray(roughness, np.float32))

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        return np.array(self.adam["albedo"]).T.reshape(-1, 3), np.array(self.adam["roughness"])

    def data_term(self, views: np.ndarray, with_grad: bool) -> float:
        """The weighted L1 of ``views``, scaled by (all views / these) so that a minibatch estimates the whole
        capture's term and keeps its balance with the prior; with its gradient accumulated on the maps."""
        a, r = self.adam["albedo"], self.adam["roughness"]
        if not with_grad:
            a, r = dr.detach(a), dr.detach(r)
        share = len(self.batches) / max(len(views), 1) if with_grad else 1.0
        pixels = self.n_obs if with_grad else sum(self.batches.pixels[k] for k in views)
        total = 0.0
        for b in self.batches.in_batches(views):
            r_t = dr.gather(mi.Float, r, b.texels)
            diffuse, spec, dspec = b.shade(dr.detach(r_t))
            # S(r) to first order around the current roughness: the value S, the derivative ∂S/∂r (the LED loop's
            # analytic one) for texels with highlight evidence, 0 for the others.
            gate = dr.gather(mi.Float, self.gate_all, b.texels)
            radiance = dr.gather(mi.Color3f, a, b.texels) * diffuse + spec + dspec * (gate * (r_t - dr.detach(r_t)))
            residual = dr.abs(b.to_pixels(radiance) - b.observed)
            # the scale as a kernel input: as a literal it would compile a new kernel for every batch
            term = dr.sum((residual.x + residual.y + residual.z) * b.pixel_weight) * opaque(mi.Float, share / (3.0 * pixels))
            if with_grad:
                dr.backward(term)
            total += float(dr.detach(term)[0])
        return self.batches.ranks.total(total)

    def prior_term(self, with_grad: bool) -> float:
        a, r = self.adam["albedo"], self.adam["roughness"]
        s, ei, ej = self.settings, self.ei, self.ej
        prior = s.smooth_roughness * dr.sum(dr.square(dr.gather(mi.Float, r, ei) - dr.gather(mi.Float, r, ej)))
        prior += s.smooth_albedo * dr.sum(dr.squared_norm(dr.gather(mi.Color3f, a, ei) - dr.gather(mi.Color3f, a, ej)))
        prior = prior / self.n_edges
        if with_grad and self.batches.ranks.main:  # every process has the same prior: its gradient counts once
            dr.backward(prior)
        return float(dr.detach(prior)[0])

    def loss(self, with_grad: bool, views: np.ndarray | None = None) -> tuple[float, float]:
        """(data L1, total loss) on ``views`` (default: the curve's views); with the gradient on the maps for Adam's
        next step."""
        data = self.data_term(self.curve_views if views is None else views, with_grad)
        return data, data + self.prior_term(with_grad)

    def step(self, iteration: int) -> None:
        """One Adam step on the iteration's views, the learning rate decaying to a tenth over the run; values clipped
        to [0, 1], and the texels Adam does not move kept."""
        s = self.settings
        self.loss(with_grad=True, views=batch_at(iteration, len(self.batches), s.batch_views, s.seed))
        self._sum_gradients()
        decay = 0.1 ** (iteration / max(s.iterations - 1, 1))
        self.adam.set_learning_rate({"albedo": s.lr_albedo * decay, "roughness": s.lr_roughness * decay})
        before = {k: dr.detach(self.adam[k]) for k in self.free}
        self.adam.step()
        for key, free in self.free.items():
            self.adam[key] = dr.select(free, dr.clip(dr.detach(self.adam[key]), 0.0, 1.0), before[key])
        dr.eval(self.adam["albedo"], self.adam["roughness"])

    def _sum_gradients(self) -> None:
        """Each process's gradient is of its views' share of the loss: the step takes their sum."""
        ranks = self.batches.ranks
        if ranks.single:
            return
        for key, kind in (("albedo", mi.Color3f), ("roughness", mi.Float)):
            value = self.adam[key]
            total = ranks.sum(np.array(dr.grad(value))).astype(np.float32)
            dr.set_grad(value, kind(*total) if total.ndim == 2 else kind(total))

    def refill(self) -> None:
        albedo, roughness = self.maps()
        ranks = self.batches.ranks  # the processes' maps, made bit-identical again (their devices may round apart)
        albedo, roughness = ranks.from_main(albedo), ranks.from_main(roughness)
        observed, anchors = self.observed, self.anchors
        if anchors.any() and not anchors.all():
            filled = np.clip(self.fill_roughness(roughness, float(np.median(roughness[anchors])))[:, 0], 0.0, 1.0)
            roughness = np.where(anchors, roughness, filled)
        if observed.any() and not observed.all():
            filled = np.clip(self.fill_albedo(albedo, float(np.median(albedo[observed]))), 0.0, 1.0)
            albedo = np.where(observed[:, None], albedo, filled)
        self.set_maps(albedo, roughness)  # same shapes: Adam's moments are kept

    def record(self, label: str) -> None:
        """Refill, then a point of the curve and a snapshot of the maps."""
        self.refill()
        data, loss = self.loss(with_grad=False)
        self.curve.append((time.perf_counter() - self.start, data, loss, label))
        albedo, roughness = self.maps()
        self.snapshots.append((self.curve[-1][0], albedo.astype(np.float32), roughness.astype(np.float32)))

    def save(self, checkpoint: Path, iteration: int) -> None:
        albedo, roughness = self.maps()
        arrays = {"albedo": albedo, "roughness": roughness, "snapshot_times": np.array([t for t, _, _ in self.snapshots])}
        for k, (_, a, r) in enumerate(self.snapshots):
            arrays[f"snapshot_albedo_{k}"], arrays[f"snapshot_roughness_{k}"] = a, r
        for key in self.free:
            t, m, v, _ = self.adam.state[key][3]
            arrays |= {f"adam_t_{key}": np.array(t), f"adam_m_{key}": np.array(m), f"adam_v_{key}": np.array(v)}
        with atomic_path(checkpoint) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays, iteration=np.array(iteration), curve=json.dumps(self.curve), settings=self.settings_json)

    def resume(self, checkpoint: Path, texels: int) -> int:
        """The maps, Adam's moments, curve and snapshots of ``checkpoint``; returns the iteration to continue from."""
        state = read_checkpoint_npz(checkpoint)
        if str(state.get("settings", "")) != self.settings_json or state["roughness"].shape[0] != texels:
            raise GraMiInputError(
                checkpoint,
                f"this fit was started with {state.get('settings', 'other settings')} on {state['roughness'].shape[0]} texels, "
                f"not {self.settings_json} on {texels}: rerun with those options, or use a new --out folder",
                field="settings",
            )
        self.set_maps(state["albedo"], state["roughness"])
        for key, kind in (("albedo", mi.Color3f), ("roughness", mi.Float)):
            value, promoted, lr, (_, _, _, v_max) = self.adam.state[key]
            moments = (mi.UInt32(state[f"adam_t_{key}"]), kind(state[f"adam_m_{key}"]), kind(state[f"adam_v_{key}"]), v_max)
            self.adam.state[key] = (value, promoted, lr, moments)
        self.curve = [tuple(c) for c in json.loads(str(state["curve"]))]
        times = state["snapshot_times"]
        self.snapshots = [(float(t), state[f"snapshot_albedo_{k}"], state[f"snapshot_roughness_{k}"]) for k, t in enumerate(times)]
        return int(state["iteration"])
