"""Relighting under environments against the physical truth: reference maps, the envmap truth, lighting models."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gra_mi.stage import envmap as em
from gra_mi.stage.envmap_library import REFERENCE_MAPS, reference_map


def flux(env: np.ndarray) -> np.ndarray:
    return (env.astype(np.float64) * em.pixel_solid_angles(*env.shape[:2])[..., None]).reshape(-1, 3)


def test_reference_maps_are_the_hard_cases():
    maps = {name: reference_map(name) for name in REFERENCE_MAPS}
    for name, env in maps.items():
        assert env.shape == (64, 128, 3) and np.isfinite(env).all() and env.min() >= 0, name
    # sun: a 2°-wide disc of 10⁴× the sky's mean radiance, splatted with its exact flux into a few pixels
    sun = maps["sun"]
    sky_mean = float(np.mean(sun[:32][sun[:32].mean(axis=-1) < 5]))
    per_pixel = flux(sun).mean(axis=1)
    top = np.sort(per_pixel)[::-1]
    expected_sun_flux = 1e4 * 0.95 * 2 * np.pi * (1 - np.cos(np.radians(1.0)))  # mean of the sun's colour ≈ 0.943
    assert top[:4].sum() == pytest.approx(expected_sun_flux * sky_mean, rel=0.05)
    assert top[:4].sum() / per_pixel.sum() > 0.4, "the sun carries about half of the light"
    # studio and interior: a handful of bright sources hold much of the light; night: dark, small warm sources
    for name in ("studio", "interior"):
        f = np.sort(flux(maps[name]).mean(axis=1))[::-1]
        assert f[: f.size // 50].sum() / f.sum() > 0.3, name
    night = maps["night"]
    assert np.median(night) < 0.01 and night[..., 0].max() > 3 * night[..., 2].max(), "dark, with warm lamps"
    with pytest.raises(ValueError, match="reference map"):
        reference_map("beach")


def test_envmap_truth_reads_maps_in_gras_convention(llvm_variant):
    """Mitsuba's ``envmap`` emitter (which renders the truth) looks a map up exactly as :func:`envmap.lookup` does."""
    import drjit as dr
    import mitsuba as mi

    env = reference_map("interior", 32)
    bitmap = mi.Bitmap(env.astype(np.float32))
    emitter = mi.load_dict({"type": "envmap", "bitmap": bitmap})
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
    si.wi = mi.Vector3f(*(-d.T).astype(np.float32))
    got = np.array(emitter.eval(si)).T
    np.testing.assert_allclose(got, em.lookup(env, d), rtol=2e-3, atol=1e-4)


def test_far_field_relights_environments_as_the_path_traced_truth(path_traced_fit):
    """The issue's goals on the tiny path-traced capture, against the true materials path-traced under each reference
    map at infinity: far field (the default for envmaps) beats near field on every map, keeps the subject's
    brightness within ±5 %, and never goes negative."""
    from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy

    root = path_traced_fit
    cameras = [f"cam{i:02d}" for i in range(8)]
    before = {p: p.stat().st_mtime_ns for p in (root / "cap").rglob("*") if p.name != ".gra-mi.lock"}
    rows = envmap_accuracy(root / "cap", root / "fit", root / "acc", config=EnvmapAccuracyConfig(spp=64, cameras=cameras))
    after = {p: p.stat().st_mtime_ns for p in (root / "cap").rglob("*") if p.name != ".gra-mi.lock"}
    assert after == before, "scoring writes nothing into the capture it scores (a read-only capture works)"
    by = {(r["map"], r["method"]): r for r in rows}
    for name in REFERENCE_MAPS:
        near, far = by[(name, "near field")], by[(name, "far field")]
        assert far["psnr"] > near["psnr"] + 0.5, name
        assert abs(far["brightness"]) < 0.05, (name, far["brightness"])
        assert far["negative_pixels"] == 0
    summary = json.loads((root / "acc" / "accuracy.json").read_text())["summary"]
    assert summary["far field"]["median_psnr"] > 25.0
    assert summary["far field"]["median_psnr"] > summary["near field"]["median_psnr"] + 1.5
    assert (root / "acc" / "contact_sheet.png").is_file() and "| sun |" in (root / "acc" / "accuracy.md").read_text()
    # The truth is cached with what made it: a second run renders nothing new and scores the same.
    again = envmap_accuracy(root / "cap", root / "fit", root / "acc", config=EnvmapAccuracyConfig(spp=64, cameras=cameras, maps=["sun"]))
    assert again[1]["psnr"] == pytest.approx(by[("sun", "far field")]["psnr"])


def test_envmap_truth_has_the_captures_wrinkles_and_writes_nothing_into_it(path_traced_fit, tmp_path):
    """The truth under an environment poses the same wrinkle normal map for a frame as the capture's own images (it
    once indexed the cloth mask twice and rendered flat cloth, 4 % brighter and up to 4.4 dB easier); the map tilts
    cloth normals by the frame's slope and leaves skin flat; loading it writes nothing into the capture."""
    import mitsuba as mi

    from gra_mi.capture.dataset import Capture
    from gra_mi.capture.truth import load_envmap_truth
    from gra_mi.capture.wrinkles import REST_SLOPE, capture_wrinkles, pose_wrinkles
    from gra_mi.core.io import read_exr, write_exr
    from gra_mi.stage.scene import LightstageScene

    def tilt(normal_map):
        normals = 2.0 * normal_map.astype(np.float64) - 1.0
        return np.hypot(normals[..., 0], normals[..., 1]) / normals[..., 2]

    capture = Capture.load(path_traced_fit / "cap")
    before = sorted(p.name for p in capture.folder.iterdir())
    num_frames = int(np.load(capture.folder / "subject" / "sequence.npz")["vertices"].shape[0])
    frame = num_frames - 1
    write_exr(tmp_path / "env.exr", reference_map("studio", 16))
    truth = mi.traverse(load_envmap_truth(capture, tmp_path / "env.exr", frame))
    key = next(k for k in truth.keys() if k.endswith("normalmap.data"))
    cloth = read_exr(capture.folder / "gt" / "cloth.exr")
    source = LightstageScene.load(capture.folder / "scene_gt.xml")  # as `gra-mi capture` poses its own images
    source.set_frame(frame)
    pose_wrinkles(source.params, capture_wrinkles(capture.folder, frame))
    truth_map = np.array(truth[key])
    np.testing.assert_array_equal(truth_map, np.array(source.params[key]))
    on_cloth = cloth[..., 0] > 0.5
    assert on_cloth.sum() > 100
    # The tiny subject moves rigidly (an arm swinging at a fixed torso): its cloth keeps the drape's slope (how
    # compression deepens it: test_wrinkles.py).
    assert tilt(truth_map)[on_cloth].max() == pytest.approx(REST_SLOPE, rel=0.02)
    assert tilt(truth_map)[~on_cloth].max() < 1e-6, "skin stays flat"
    assert sorted(p.name for p in capture.folder.iterdir()) == before


def test_fit_calibrates_the_training_views_total_light(path_traced_fit):
    """After the L1 fit, the albedo gain restores the captured total light of the training views (the one-bounce
    model leaves interreflections out, and L1 fits medians): renders of them are within 2 % of the capture."""
    from gra_mi.capture.dataset import Capture, load_observation
    from gra_mi.core.metrics import subject_mask
    from gra_mi.fit.fitted import fitted_relighter

    root = path_traced_fit
    fit = json.loads((root / "fit" / "fit.json").read_text())
    assert fit["albedo_gain"] is not None and all(1.0 <= g < 1.3 for g in fit["albedo_gain"]), "one-sided missing light"
    capture, relighter = fitted_relighter(root / "cap", root / "fit")
    total_render, total_truth = 0.0, 0.0
    for entry in [f for f in capture.frames if f.split == "train"][:3]:
        for cam in capture.train_cameras:
            truth = load_observation(Capture.load(root / "cap"), cam, entry.frame)
            mask = subject_mask(truth)
            image = relighter.render(entry.frame, cam, capture.lighting(relighter.ls.stage, entry)).image
            total_render += image[mask, :3].sum()
            total_truth += truth[mask, :3].sum()
    assert total_render / total_truth == pytest.approx(1.0, abs=0.03)


def test_relight_picks_the_lighting_model_by_intent(tmp_path, llvm_variant):
    """auto: envmaps far field (an environment at infinity), OLATs near field (the stage's LEDs, as captured)."""
    from gra_mi.apps.relight import RelightConfig, collect_lights, relight_batch
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.core.io import read_exr
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(Path(__file__).parents[1] / "scenes" / "tiny_lightstage.xml")
    lights = collect_lights(ls.stage, {"sun": reference_map("sun", 16)}, [4], {})
    images = {}
    for model in ("auto", "near", "far"):
        relight_batch(
            ls, tmp_path / model, lights, frames=[1], cameras=["cam00"], config=RelightConfig(uv_resolution=32, lighting_model=model)
        )
        images[model] = {name: read_exr(tmp_path / model / name / "cam00" / "frame_0001.exr") for name in ("sun", "olat004")}
    np.testing.assert_array_equal(images["auto"]["sun"], images["far"]["sun"])
    np.testing.assert_array_equal(images["auto"]["olat004"], images["near"]["olat004"])
    assert np.abs(images["near"]["sun"] - images["far"]["sun"]).max() > 1e-3, "the two models differ on a 1.2 m rig"
    assert not (tmp_path / "auto" / "envmap_fidelity.json").exists(), "the fidelity check runs only when asked"
    with pytest.raises(GraMiParameterError, match="lighting_model"):
        RelightConfig(lighting_model="infinite").validate()


def test_far_field_lobes_are_widened_to_the_led_spacing(llvm_variant, monkeypatch):
    """Glossy texels under a sun: without widening, the few texels whose lobe happens to catch one of the sun's LEDs
    spike (sparkles) and the total depends on where texel centres fall; widened to the LEDs' spacing, the highlight
    is smooth and its light the same for any low roughness."""
    import gra_mi.render.relighter as relighter_module
    from gra_mi.render.relighter import Relighter
    from gra_mi.stage.envmap import envmap_to_leds
    from gra_mi.stage.scene import LightstageScene

    ls = LightstageScene.load(Path(__file__).parents[1] / "scenes" / "tiny_lightstage.xml")
    sun = envmap_to_leds(reference_map("sun", 32), ls.stage).radiant_intensity(ls.stage)

    def render(roughness: float):
        view = Relighter(ls, 64, roughness=np.full((64, 64, 1), roughness, np.float32)).render(2, 0, sun, far_field=True)
        spec = view.shading.specular.mean(axis=1)
        return view.image[..., :3].mean(axis=-1).max(), spec.sum(), np.sort(spec)[::-1][: spec.size // 100].sum() / spec.sum()

    widened = {r: render(r) for r in (0.03, 0.08, 0.15)}
    monkeypatch.setattr(relighter_module, "led_cell_roughness", lambda roughness, num_leds: roughness)
    sharp = render(0.08)
    assert sharp[0] > 3 * widened[0.08][0], "a sparkle: one pixel far brighter than the widened highlight"
    assert sharp[2] > 0.8 and widened[0.08][2] < 0.5, "the top 1 % of texels hold the sharp highlight's light"
    totals = [w[1] for w in widened.values()]
    assert max(totals) < 1.05 * min(totals), "the widened highlight's light does not depend on texel sampling"


def test_eval_lighting_refuses_bad_frames_and_cameras(path_traced_fit):
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy

    root = path_traced_fit
    for config, field in (
        (EnvmapAccuracyConfig(frame=999, spp=4), "frame"),
        (EnvmapAccuracyConfig(cameras=["cam99"], spp=4), "cameras"),
        (EnvmapAccuracyConfig(maps=["beach"], spp=4), "maps"),
    ):
        with pytest.raises(GraMiParameterError, match=field):
            envmap_accuracy(root / "cap", root / "fit", root / "bad", config=config)


def test_eval_lighting_shards_split_the_truths_and_the_last_scores(path_traced_fit, tmp_path):
    """``--shard``: each shard path-traces its maps' truths; the one that finds every truth done scores them all, as
    one process does."""
    from gra_mi.core.shard import Shard
    from gra_mi.eval.lighting import EnvmapAccuracyConfig, envmap_accuracy

    root = path_traced_fit
    config = EnvmapAccuracyConfig(spp=16, cameras=["cam07"], maps=["sun", "night"])
    whole = envmap_accuracy(root / "cap", root / "fit", tmp_path / "whole", config=config)
    first = envmap_accuracy(root / "cap", root / "fit", tmp_path / "shards", config=config, shard=Shard(0, 2))
    assert first == [] and (tmp_path / "shards" / "truth" / "sun" / "cam07.exr").is_file()
    assert not (tmp_path / "shards" / "truth" / "night").exists() and not (tmp_path / "shards" / "accuracy.json").exists()
    last = envmap_accuracy(root / "cap", root / "fit", tmp_path / "shards", config=config, shard=Shard(1, 2))
    assert [(r["map"], r["method"]) for r in last] == [(r["map"], r["method"]) for r in whole]
    for a, b in zip(last, whole, strict=True):
        assert a["psnr"] == pytest.approx(b["psnr"], abs=1e-6), (a["map"], a["method"])
    assert (tmp_path / "shards" / "accuracy.json").is_file()
