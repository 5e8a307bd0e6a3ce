"""Variant fixtures in Mitsuba's style: llvm_ad_rgb always, cuda_ad_rgb only where a GPU works."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("GRA_MI_QUIET", "1")

REPO = Path(__file__).resolve().parent.parent
SCENES = REPO / "scenes"


def _variants() -> list:
    from gra_mi.core.runtime import cuda_available

    params = [pytest.param("llvm_ad_rgb", id="llvm_ad_rgb")]
    params.append(pytest.param("cuda_ad_rgb", id="cuda_ad_rgb", marks=pytest.mark.skipif(not cuda_available(), reason="no CUDA device")))
    return params


@pytest.fixture(params=_variants())
def variant(request):
    """Set a Mitsuba variant for the test; flush Dr.Jit's caches afterwards as Mitsuba's conftest does."""
    from gra_mi.core.runtime import choose_variant

    name = choose_variant(request.param)
    yield name
    import drjit as dr

    dr.flush_malloc_cache()
    dr.kernel_history_clear()


@pytest.fixture
def plugins(variant):
    """The variant's fixture with gra-mi's Mitsuba plugins (gra_microfacet, gra_onebounce) registered for it."""
    from gra_mi.render.plugins import register_plugins

    register_plugins()
    return variant


@pytest.fixture
def llvm_variant():
    """Only the CPU variant (for tests whose subject is file I/O or numpy, not the backend)."""
    from gra_mi.core.runtime import choose_variant

    return choose_variant("llvm_ad_rgb")


@pytest.fixture(scope="session")
def default_stage():
    from gra_mi.stage.lightstage import load_calibration

    return load_calibration(SCENES / "rigs" / "default" / "calibration.json")


@pytest.fixture(scope="module")
def onebounce_capture(tmp_path_factory):
    """The tiny preset captured with gra-mi's own one-bounce renderer (its model, no path-tracing noise)."""
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture
    from gra_mi.core.runtime import choose_variant

    choose_variant("llvm_ad_rgb")
    out = tmp_path_factory.mktemp("capture")
    generate_capture(out, CaptureConfig(preset="tiny", renderer="onebounce"))
    return out


@pytest.fixture(scope="session")
def path_traced_fit(tmp_path_factory):
    """The tiny preset's path-traced capture (``cap/``) and its material fit (``fit/``), shared by every module
    that scores against the physical truth (lighting models, the evaluation protocol)."""
    from gra_mi.capture.synthetic import CaptureConfig, generate_capture
    from gra_mi.core.runtime import choose_variant
    from gra_mi.fit.materials import FitConfig, run_fit

    choose_variant("llvm_ad_rgb")
    root = tmp_path_factory.mktemp("path_traced_fit")
    generate_capture(root / "cap", CaptureConfig(preset="tiny", measure_noise=False))
    run_fit(root / "cap", root / "fit", FitConfig())
    return root


def poison_optimizer_after(monkeypatch, updates: int) -> list:
    """Make every AdamW fill its parameters with NaN right after its ``updates``-th step (a diverging run, on cue).
    Returns the list that counts the steps taken."""
    import torch

    original, calls = torch.optim.AdamW.step, []

    def poisoned_step(self, *a, **k):
        result = original(self, *a, **k)
        calls.append(1)
        if len(calls) == updates:
            with torch.no_grad():
                for param in self.param_groups[0]["params"]:
                    param.fill_(float("nan"))
        return result

    monkeypatch.setattr(torch.optim.AdamW, "step", poisoned_step)
    return calls
