"""How much light transport a stage that shades texels models: the paper's one bounce, or the light after it
(gra_mi.render.bounce). One config, nested in every command that shades texels (relight, fit, eval, eval-lighting,
relight-field, train-relightnet, view, bench), so the option reads the same everywhere."""

from __future__ import annotations

from dataclasses import dataclass

from gra_mi.core.config import changed_options
from gra_mi.core.errors import GraMiParameterError

MAX_BOUNCES = 8
DEFAULT_RAYS = 32  # docs/results/interreflection.md: bias, noise and cost against K on the demo's body
DEFAULT_SMOOTHING = 2  # texels: a 5 × 5 window (docs/results/bounce-noise.md: the fit and the perfect fit against K and radius)
MAX_SMOOTHING = 8
MAX_RAYS = 4096
BOUNCE_LEDS = 32
"""The light that bounces is computed from this many LEDs: the brightest, each other's flux moved to its nearest
(``LedLayout.brightest``). An OLAT or a pattern of fewer LEDs is exact; under an envmap every ray's LED loop then
walks ~10× fewer LEDs (docs/results/interreflection.md measures what it changes)."""


@dataclass(kw_only=True)
class LightTransport:
    bounces: int = 1
    """Bounces of light: 1 is the paper's one-bounce model; 2 adds the light the body reflects onto itself once (an
    armpit, the inner thighs, a hand by the hip; docs/accuracy.md, "Interreflections") and the light the scene's set
    (a floor, a wall) reflects onto it, 3 or more adds further diffuse bounces. Each extra bounce costs one texel-to-texel operator per frame, traced once and cached."""
    bounce_rays: int = DEFAULT_RAYS
    """Rays per texel of that operator (with --bounces >= 2): more rays, less noise in the light after the first
    bounce, a longer trace per new frame."""
    bounce_smoothing: int = DEFAULT_SMOOTHING
    """With --bounces >= 2: average the light each texel receives after the first bounce over its neighbours on the
    same surface within this many texels (near in space, facing alike), cutting the noise of its K-ray estimate;
    0 leaves each texel's own estimate."""

    def validate(self, fixed: bool = False) -> None:
        """Each field in range; ``fixed``: the bounces cannot change later (every command but the viewer, whose page
        has a control for them), so ray counts and smoothing given with one bounce would be ignored: refused."""
        if fixed and self.bounces == 1 and (given := changed_options(self, ("bounce_rays", "bounce_smoothing"))):
            raise GraMiParameterError(given[0], "takes effect with --bounces 2 or more only: add --bounces 2, or leave it out")
        if isinstance(self.bounces, bool) or not isinstance(self.bounces, int) or not 1 <= self.bounces <= MAX_BOUNCES:
            raise GraMiParameterError("bounces", f"expected an integer in [1, {MAX_BOUNCES}], got {self.bounces!r}")
        if isinstance(self.bounce_rays, bool) or not isinstance(self.bounce_rays, int) or not 1 <= self.bounce_rays <= MAX_RAYS:
            raise GraMiParameterError("bounce_rays", f"expected an integer in [1, {MAX_RAYS}], got {self.bounce_rays!r}")
        smoothing = self.bounce_smoothing
        if isinstance(smoothing, bool) or not isinstance(smoothing, int) or not 0 <= smoothing <= MAX_SMOOTHING:
            raise GraMiParameterError("bounce_smoothing", f"expected an integer in [0, {MAX_SMOOTHING}], got {smoothing!r}")

    @property
    def label(self) -> str:
        if self.bounces == 1:
            return "1 bounce"
        return f"{self.bounces} bounces ({self.bounce_rays} rays/texel, smoothing radius {self.bounce_smoothing})"
