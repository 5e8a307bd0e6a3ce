"""Every preset runs: the capture presets shrunk to a few pixels (their schedules, test lightings and camera splits
are what is under test, not their size), and the demo's and bench's presets refer to things that exist."""

from __future__ import annotations

import dataclasses

import pytest

from gra_mi.capture.synthetic import PRESETS as CAPTURE_PRESETS


def shrunk(preset):
    """The preset's structure (clips, test lightings, held-out cameras) at a few pixels, on the tiny subject."""
    return dataclasses.replace(
        preset, subject="tiny", num_leds=24, num_cameras=3, eval_cameras=1, width=24, height=16, uv_resolution=16,
        envmap_height=8, spp=4, indirect_spp=4, frames_per_clip=2, test_frames_per_clip=2 if preset.test_frames_per_clip else None,
    )  # fmt: skip


@pytest.mark.parametrize("name", sorted(CAPTURE_PRESETS))
def test_every_capture_preset_runs_shrunk(name, tmp_path, monkeypatch, llvm_variant):
    from gra_mi.capture import synthetic
    from gra_mi.capture.dataset import Capture

    preset = shrunk(CAPTURE_PRESETS[name])
    monkeypatch.setitem(synthetic.PRESETS, name, preset)
    capture = synthetic.generate_capture(tmp_path / name, synthetic.CaptureConfig(preset=name, measure_noise=False))
    again = Capture.load(tmp_path / name)
    assert [f.kind for f in again.frames] == [f.kind for f in capture.frames]
    tests = [f for f in capture.frames if f.split == "test"]
    assert len(capture.eval_cameras) == 1 and all(capture.image_path(c, 0).is_file() for c in capture.train_cameras)
    if preset.static_olat:  # one pose: white, 2 gradients, the envmaps (test) and an OLAT per LED, every 10th test
        envmaps, olats = [f for f in tests if f.kind == "envmap"], [f for f in capture.frames if "olat_" in (f.pattern or "")]
        assert {f.mesh_frame for f in capture.frames} == {0} and len(envmaps) == preset.envmap_frames
        assert len(olats) == preset.num_leds and sum(f.split == "test" for f in olats) == preset.num_leds // 10
        return
    assert len({f.sequence for f in tests}) == len(preset.test_clips)
    assert [f.kind == "pattern" for f in tests if f.frame == min(g.frame for g in tests if g.sequence == f.sequence)] == [
        k == "olat" for k in preset.test_lightings()
    ]


def test_demo_and_bench_presets_refer_to_what_exists():
    from gra_mi.apps.bench import PRESETS as BENCH_PRESETS
    from gra_mi.apps.demo import PRESETS as DEMO_PRESETS
    from gra_mi.apps.demo import OlatDemoPreset
    from gra_mi.capture.synthetic import CaptureConfig

    for preset in DEMO_PRESETS.values():
        CaptureConfig(preset=preset.capture, renderer=preset.renderer).validate()
        if isinstance(preset, OlatDemoPreset):
            assert CAPTURE_PRESETS[preset.capture].static_olat and preset.synthesized_lightings >= 1000
            continue
        assert 0 < preset.refiner_scale <= 1 and preset.relightnet_steps > 0 and preset.refiner_steps > 0
    for preset in BENCH_PRESETS.values():
        assert max(preset.led_counts) <= 331 and all(r > 0 for r in preset.uv_resolutions)
