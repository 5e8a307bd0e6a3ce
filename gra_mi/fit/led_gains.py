"""Each LED's gain from the capture's own OLAT images, where the stage states none (HumanOLAT ships positions only).

A frame lit by one LED alone shows the subject under that LED times its gain g_l (RGB). With the one-bounce model,

    O_j = g_l ⊙ (a_t ⊙ D_j + S_j(r_t))

for an observation j of texel t in a view of LED l's frame. The albedo a and the gains g are found in turn, on the
closed form's observations (:class:`~gra_mi.fit.materials.MaterialFitter`, at a coarse UV resolution):

1. the roughness grid (once), then the per-texel albedo at the current gains (the fit's closed form);
2. each LED's gain times the ratio that best explains its views: the weighted median of O / P over its observations
   (P the prediction, weight P: the scale minimising Σ |O − s P|, so shadows the model misses and highlights do not
   drag it);
3. the stored parts of the LED's views rescaled by that ratio (D and S are linear in the frame's light), and again,
   until no gain changes by more than :data:`TOLERANCE`.

Only observations of texels that face their LED (:data:`MIN_LIGHT_COS`: grazing light is where the one-bounce BRDF
is most wrong) count, and a gain is measured on the texels another LED lights too: a texel one LED alone lights is
explained whatever that LED's gain (its albedo follows), so it only holds the ratio at 1. An LED without an OLAT
frame, or outside the largest group of LEDs joined by such texels, is not measured and keeps 1.

Gains are relative: each channel's mean over the measured LEDs is 1. A colour common to every LED cannot be told
apart from the subject's, and stays in the albedo; the LEDs' overall brightness is the import's --led-intensity.
Every OLAT frame is used, held-out ones included: one RGB number per LED comes from its training cameras' images.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.fit.grid import refine_on_grid
from gra_mi.fit.maps import DEFAULT_ROUGHNESS

logger = logging.getLogger(__name__)

RESOLUTION = 64  # UV resolution of the estimate's albedo: each LED is measured over many texels, not fine detail
ROUNDS = 50  # at most this many albedo / gain alternations
TOLERANCE = 1e-3  # stop once no gain changes by more than this (relative)
MIN_LIGHT_COS = 0.4  # observations of texels lit more obliquely are left out
MIN_OBSERVATIONS = 50  # observations of texels another LED lights too that an LED needs to be measured
MIN_SHARED_TEXELS = 10  # texels two LEDs both light for the one's gain to tie to the other's
SUSPECT_RESIDUAL, SUSPECT_FLOOR = 3.0, 0.3  # an LED whose relative L1 is above both (× the median; absolute) is named


@dataclass
class GainEstimate:
    gains: np.ndarray  # (L, 3) each channel's mean over the measured LEDs 1
    measured: np.ndarray  # (L,) LEDs whose gain the images measured (the others keep 1)
    changes: list[float] = field(default_factory=list)  # each round's largest relative change of a gain
    residual: list[float] = field(default_factory=list)  # relative L1 of the model before the first round and after each
    led_residual: np.ndarray | None = None  # (L,) each measured LED's relative L1 at the estimate (NaN: not measured)
    seconds: float = 0.0

    @property
    def suspect(self) -> np.ndarray:
        """(L,) LEDs whose OLATs the model explains far worse than the others' at their best gain: lit elsewhere than
        their position says (a mixed-up light order or positions)."""
        if self.led_residual is None or not self.measured.any():
            return np.zeros(self.measured.size, bool)
        typical = float(np.nanmedian(self.led_residual[self.measured]))
        return self.measured & (self.led_residual > max(SUSPECT_RESIDUAL * typical, SUSPECT_FLOOR))

    def summary(self) -> dict:
        return {
            "measured_leds": int(self.measured.sum()),
            "unmeasured_leds": [int(i) for i in np.flatnonzero(~self.measured)],
            "suspect_leds": [int(i) for i in np.flatnonzero(self.suspect)],
            "rounds": len(self.changes),
            "last_change": self.changes[-1] if self.changes else None,
            "relative_l1": {"equal gains": self.residual[0], "estimated": self.residual[-1]} if self.residual else None,
            "range": [float(self.gains[self.measured].min()), float(self.gains[self.measured].max())] if self.measured.any() else None,
            "seconds": round(self.seconds, 1),
        }


def olat_frames(capture, stage) -> dict[int, int]:
    """Frame number → the one LED lighting it, for the capture's frames lit by one LED alone."""
    out = {}
    for entry in capture.frames:
        if entry.kind != "pattern":
            continue
        lit = np.flatnonzero(capture.lighting(stage, entry).max(axis=1) > 0)
        if lit.size == 1:
            out[entry.frame] = int(lit[0])
    return out


def weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The value where the weights' running sum reaches half their total: the s minimising Σ w |v − s|."""
    order = np.argsort(values)
    running = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(running, 0.5 * running[-1])])


def estimate_led_gains(capture, resolution: int = RESOLUTION, rounds: int = ROUNDS, progress_bar: bool = True) -> GainEstimate:
    """The gains (:class:`GainEstimate`) of ``capture``'s LEDs from its OLAT frames seen by its training cameras."""
    clock = time.perf_counter()
    fitter, views, lit_by = _observations(capture, resolution, progress_bar)
    num_leds = fitter.stage.num_leds
    shared, measured = _links(fitter, views, lit_by, num_leds)
    estimate = GainEstimate(np.ones((num_leds, 3)), measured)
    by_led: dict[int, list] = {}
    for v in (v for v in views if measured[lit_by[v.frame]]):  # an LED whose gain is not measured would bias the albedo
        by_led.setdefault(lit_by[v.frame], []).append(v)
    views = [v for its_views in by_led.values() for v in its_views]
    for _ in range(rounds):
        albedo, _ = fitter.solve_albedo(views, [], clock, lambda **_: None)
        ratios, residual, _ = _ratios(fitter, by_led, albedo, shared)
        estimate.residual.append(residual)
        ratios /= (estimate.gains * ratios)[measured].mean(axis=0) / estimate.gains[measured].mean(axis=0)
        estimate.gains *= ratios
        estimate.changes.append(float(np.abs(ratios[measured] - 1.0).max()))
        for led, its_views in by_led.items():
            _rescale(fitter, its_views, ratios[led])
        if estimate.changes[-1] < TOLERANCE:
            break
    albedo, _ = fitter.solve_albedo(views, [], clock, lambda **_: None)
    _, last, estimate.led_residual = _ratios(fitter, by_led, albedo, shared)
    estimate.residual.append(last)
    gains = estimate.gains * fitter.stage.gains  # the capture's own gains, corrected
    estimate.gains = np.where(measured[:, None], gains / gains[measured].mean(axis=0), 1.0)
    estimate.seconds = time.perf_counter() - clock
    fitter.store.close()
    logger.info("LED gains: %s", estimate.summary())
    return estimate


def _observations(capture, resolution: int, progress_bar: bool):
    """(the closed form's fitter on the capture's OLAT frames, its views with their parts kept where the texel faces
    its camera and its LED, frame → its LED)."""
    from gra_mi.fit.materials import FitConfig, MaterialFitter

    stage = capture.load_scene().stage
    lit_by = olat_frames(capture, stage)
    if not lit_by:
        raise GraMiInputError(capture.folder / "capture.json", "has no frame lit by one LED alone: LED gains are measured on OLATs")
    frames = [f for f in capture.frames if f.frame in lit_by]
    config = FitConfig(solver="closed-form", resolution=min(resolution, capture.uv_resolution), calibrate_brightness=False)
    fitter = MaterialFitter(capture, config, frames=frames)
    views = [v for v in fitter.gather_views(progress_bar) if v.count > 0]
    grid = np.linspace(0.0, 1.0, config.roughness_candidates)
    roughness = refine_on_grid(fitter.grid_error(views, grid), grid)
    roughness[fitter.cameras_seen(views) == 0] = DEFAULT_ROUGHNESS
    fitter.store_parts(views, roughness)
    surfaces: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # pose → (positions, normals), converted once
    for v in views:
        if v.pose not in surfaces:
            geom = fitter.relighter.geometry(v.pose)
            surfaces[v.pose] = np.array(geom.position).T, np.array(geom.normal).T
        _keep_well_lit(fitter, v, fitter.stage.led_positions[lit_by[v.frame]], *surfaces[v.pose])
    return fitter, [v for v in views if v.count > 0], lit_by


def _links(fitter, views: list, lit_by: dict, num_leds: int) -> tuple[np.ndarray, np.ndarray]:
    """What ties the gains together: a texel seen under one LED alone explains itself whatever that LED's gain (its
    albedo follows), so only texels seen under several LEDs measure them. Returns (M,) those texels, (L,) the LEDs
    measured (the largest group joined by such texels, each with enough observations of them)."""
    from scipy.sparse.csgraph import connected_components

    under = np.zeros((num_leds, fitter.atlas.num_texels), bool)
    for v in views:
        under[lit_by[v.frame], fitter.observation(v)[0]] = True
    shared = under.sum(axis=0) >= 2
    observations = np.zeros(num_leds, np.int64)
    for v in views:
        observations[lit_by[v.frame]] += int(shared[fitter.observation(v)[0]].sum())
    both = under[:, shared].astype(np.int64)
    _, group = connected_components(both @ both.T >= MIN_SHARED_TEXELS, directed=False)
    enough = observations >= MIN_OBSERVATIONS
    if not enough.any():
        raise GraMiInputError(fitter.capture.folder, "no LED's light falls on texels another LED lights too: no gain can be measured")
    measured = enough & (group == np.bincount(group[enough]).argmax())
    return shared, measured


def _ratios(fitter, by_led: dict, albedo: np.ndarray, shared: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(L, 3) each LED's L1-best scale of its views' predictions at ``shared`` texels (1 for LEDs not in ``by_led``),
    the model's relative L1 there, and (L,) each LED's (NaN for LEDs not in ``by_led``)."""
    ratios, error, total = np.ones((fitter.stage.num_leds, 3)), 0.0, 0.0
    per_led = np.full(fitter.stage.num_leds, np.nan)
    for led, its_views in by_led.items():
        observed, predicted = [], []
        for v in its_views:
            texels, o, d, s = fitter.observation_parts(v)
            keep = shared[texels]
            observed.append(o[keep])
            predicted.append(albedo[texels[keep]] * d[keep] + s[keep])
        o, p = np.concatenate(observed), np.concatenate(predicted)
        ratios[led] = [_scale(o[:, c], p[:, c]) for c in range(3)]
        per_led[led] = float(np.abs(o - p).sum() / max(o.sum(), 1e-30))
        error, total = error + float(np.abs(o - p).sum()), total + float(o.sum())
    return ratios, error / max(total, 1e-30), per_led


def _keep_well_lit(fitter, view, led: np.ndarray, positions: np.ndarray, normals: np.ndarray) -> None:
    """Keep the view's observations of texels whose normal faces its LED (those it has face its camera)."""
    texels, observed, d, s = fitter.observation_parts(view)
    toward = led - positions[texels]
    keep = np.sum(normals[texels] * toward, axis=1) >= MIN_LIGHT_COS * np.linalg.norm(toward, axis=1)
    fitter.store.put(f"observed:{view.name}", texels=texels[keep], observed=observed[keep].astype(np.float32))
    fitter.store.put(f"parts:{view.name}", d=d[keep], s=s[keep])
    view.count = int(keep.sum())


def _scale(observed: np.ndarray, predicted: np.ndarray) -> float:
    """The s minimising Σ |O − s P| over the observations the model lights (1 where it lights none)."""
    lit = predicted > 1e-6 * predicted.max(initial=0.0)
    return weighted_median(observed[lit] / predicted[lit], predicted[lit]) if lit.any() else 1.0


def _rescale(fitter, views: list, ratio: np.ndarray) -> None:
    """The stored (D, S) of ``views`` under their LED's light scaled by ``ratio``."""
    for v in views:
        parts = fitter.store.get(f"parts:{v.name}")
        fitter.store.put(f"parts:{v.name}", d=parts["d"] * ratio, s=parts["s"] * ratio)
