"""Envmap I/O and validation, envmap→LED integration (energy), procedural envmap sets."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import read_exr, write_exr
from gra_mi.stage import envmap as em
from gra_mi.stage.envmap_library import (
    SkyParams,
    bake_room,
    bake_sunsky,
    envmap_from_seed,
    random_room,
    split_seeds,
    sun_direction,
    write_envmap_set,
)
from gra_mi.stage.lightstage import fibonacci_sphere

NORMALS = fibonacci_sphere(200)


def low_frequency_envmap(h: int = 64) -> np.ndarray:
    d = em.pixel_directions(h, 2 * h)
    base = 1.0 + 0.6 * d[..., 1:2] + 0.3 * d[..., 0:1] * d[..., 2:3] + 0.2 * d[..., 0:1]
    return (base * np.array([1.0, 0.8, 0.6])).astype(np.float32)


def total_flux(env):
    return (env * em.pixel_solid_angles(*env.shape[:2])[..., None]).sum(axis=(0, 1))


@pytest.mark.parametrize("cells", em.CELL_MODES)
def test_led_flux_equals_envmap_flux(default_stage, cells):
    # Energy conservation: Σ I / r² over LEDs equals ∫ L dω over the envmap.
    env = envmap_from_seed(4, 64)[0]
    lighting = em.envmap_to_leds(env, default_stage, normalize=False, cells=cells)
    led_flux = (lighting.radiant_intensity(default_stage) / default_stage.led_distances()[:, None] ** 2).sum(axis=0)
    np.testing.assert_allclose(led_flux, total_flux(env), rtol=1e-6)


def test_irradiance_matches_within_one_percent_for_every_normal(default_stage):
    env = low_frequency_envmap()
    lighting = em.envmap_to_leds(env, default_stage, normalize=False)
    e_env = em.envmap_irradiance(env, NORMALS)
    e_led = em.led_irradiance(default_stage, lighting.radiant_intensity(default_stage), NORMALS)
    assert np.max(np.abs(e_led - e_env) / e_env) < 0.01


def test_irradiance_of_procedural_maps(default_stage, llvm_variant):
    # Lights with sharp edges (lamps, the horizon) cannot be matched per normal by 331 LEDs; their error stays
    # within 1 % of the brightest irradiance, and the total is exact (see docs/accuracy.md).
    for env in (bake_room(random_room(np.random.default_rng(5)), 64), bake_sunsky(SkyParams(35, 120, 3, 0.2, sun_scale=0.0), 64)):
        lighting = em.envmap_to_leds(env, default_stage, normalize=False)
        e_env = em.envmap_irradiance(env, NORMALS)
        e_led = em.led_irradiance(default_stage, lighting.radiant_intensity(default_stage), NORMALS)
        assert np.max(np.abs(e_led - e_env) / e_env.max(axis=0)) < 0.02
        assert np.mean(np.abs(e_led - e_env) / e_env) < 0.02


def test_sun_keeps_its_direction_and_energy(default_stage, llvm_variant):
    params = SkyParams(40, 75, 2.5, 0.2, sky_scale=0.0)  # the sun alone (plus its ground bounce)
    env = bake_sunsky(params, 64)
    lighting = em.envmap_to_leds(env, default_stage, normalize=False)
    flux_dir = (
        lighting.radiant_intensity(default_stage).sum(axis=1)[:, None]
        * default_stage.led_directions()
        / default_stage.led_distances()[:, None] ** 2
    ).sum(axis=0)
    env_dir = (env.sum(axis=-1)[..., None] * em.pixel_solid_angles(64, 128)[..., None] * em.pixel_directions(64, 128)).sum(axis=(0, 1))
    cos = flux_dir @ env_dir / np.linalg.norm(flux_dir) / np.linalg.norm(env_dir)
    assert np.degrees(np.arccos(min(cos, 1.0))) < 0.5


def test_normalised_to_stage_maximum(default_stage):
    lighting = em.envmap_to_leds(low_frequency_envmap() * 1e6, default_stage)  # an HDR-bright map
    assert lighting.drive.max() == pytest.approx(default_stage.max_led_intensity)
    raw = em.envmap_to_leds(low_frequency_envmap() * 1e6, default_stage, normalize=False)
    np.testing.assert_allclose(lighting.drive, raw.drive * lighting.scale, rtol=1e-9)


def test_bad_pixels_rejected_or_repaired(caplog):
    env = low_frequency_envmap(16)
    env[2, 3, 0] = np.nan
    env[4, 5, 1] = np.inf
    env[6, 7, 2] = -1.0
    with pytest.raises(GraMiInputError, match="1 NaN and 1 Inf"):
        em.validate_envmap(env, "sky.exr")
    with caplog.at_level(logging.WARNING):
        fixed = em.validate_envmap(env, "sky.exr", repair=True)
    assert "repaired 1 NaN and 1 Inf" in caplog.text and "1 negative values" in caplog.text
    assert np.isfinite(fixed).all() and fixed.min() >= 0 and fixed[4, 5, 1] == np.nanmax(np.where(np.isinf(env), np.nan, env))


@pytest.mark.parametrize("shape", [(16, 16, 3), (16, 32, 2), (1, 2, 3), (8,)])
def test_wrong_shapes_rejected(shape):
    with pytest.raises(GraMiInputError):
        em.validate_envmap(np.ones(shape, np.float32), "x.exr")


def test_exr_round_trip(tmp_path):
    env = low_frequency_envmap(16) * 1e4
    write_exr(tmp_path / "e.exr", env)
    np.testing.assert_array_equal(read_exr(tmp_path / "e.exr"), env)
    rgba = np.random.default_rng(0).random((5, 7, 4)).astype(np.float32)
    write_exr(tmp_path / "a.exr", rgba)
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), rgba)
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(GraMiInputError, match="junk.exr"):
        read_exr(tmp_path / "junk.exr")


def test_procedural_sets_are_split_and_deterministic(tmp_path, llvm_variant):
    train, test = set(split_seeds("train", 100)), set(split_seeds("test", 100))
    assert not train & test
    a, meta = envmap_from_seed(7, 16)
    b, _ = envmap_from_seed(7, 16)
    np.testing.assert_array_equal(a, b)
    paths = write_envmap_set(tmp_path, "test", 3, height=16)
    assert [p.name for p in paths] == ["test_0000.exr", "test_0001.exr", "test_0002.exr"]
    index = json.loads((tmp_path / "test" / "index.json").read_text())
    assert {e["kind"] for e in index} <= {"sky", "room"} and all(
        (tmp_path / "test" / e["file"]).with_suffix(".png").exists() for e in index
    )
    for p in paths:
        env = em.load_envmap(p)
        assert env.shape == (16, 32, 3) and env.min() >= 0 and env.max() > 0


def test_sky_sun_flux_is_independent_of_azimuth(llvm_variant):
    a = bake_sunsky(SkyParams(30, 0, 3, 0.2), 32)
    b = bake_sunsky(SkyParams(30, 135, 3, 0.2), 32)
    np.testing.assert_allclose(total_flux(a), total_flux(b), rtol=5e-3)
    row, col = np.unravel_index(np.argmax(b.sum(-1)), b.shape[:2])
    u, v = em.direction_to_uv(sun_direction(SkyParams(30, 135, 3, 0.2)))
    assert abs(col - (u * 64 - 0.5)) <= 1 and abs(row - v * 31) <= 1


@pytest.mark.parametrize("positions", [[[0, 3, 0], [0, -1, 0]], [[2, 1, 0], [0, 1, 2], [-2, 1, 0], [0, 1, -2]]], ids=["two", "one-plane"])
def test_degenerate_rigs_map_envmaps_onto_nearest_leds(positions, default_stage, caplog):
    """Rigs whose LEDs span no convex hull (two LEDs; a ring in one plane) fall back to nearest-LED cells with a
    warning, and keep the map's flux, instead of stopping in Qhull."""
    from dataclasses import replace

    stage = replace(default_stage, led_positions=np.array(positions, np.float64), led_normals=None, led_gains=None)
    env = np.ones((16, 32, 3), np.float32)
    with caplog.at_level(logging.WARNING):
        lighting = em.envmap_to_leds(env, stage, normalize=False)
    assert "nearest-LED (Voronoi) cells" in caplog.text
    flux = (lighting.radiant_intensity(stage) / stage.led_distances()[:, None] ** 2).sum(axis=0)
    np.testing.assert_allclose(flux, 4 * np.pi, rtol=1e-6)  # a white sky of radiance 1 carries 4π W/m² in all
