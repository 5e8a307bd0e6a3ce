"""The one sRGB transfer and display exposure (gra_mi.core.color), against colour-science's implementation of
IEC 61966-2-1 and on the values a renderer produces that a display cannot show (NaN, ±Inf, negatives, > 1)."""

from __future__ import annotations

import colour
import numpy as np
import pytest
import torch

from gra_mi.core.color import display_exposure, srgb_decode, srgb_encode, to_display
from gra_mi.core.io import to_srgb8

GRID = np.concatenate([np.linspace(0.0, 0.01, 201), np.linspace(0.01, 1.0, 991)])


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_srgb_matches_colour_science_and_round_trips(backend):
    as_array = (lambda x: x) if backend == "numpy" else (lambda x: torch.from_numpy(x))
    back = (lambda x: x) if backend == "numpy" else (lambda x: x.numpy())
    np.testing.assert_allclose(back(srgb_encode(as_array(GRID))), colour.cctf_encoding(GRID, function="sRGB"), atol=1e-12)
    np.testing.assert_allclose(back(srgb_decode(as_array(GRID))), colour.cctf_decoding(GRID, function="sRGB"), atol=1e-12)
    np.testing.assert_allclose(back(srgb_decode(srgb_encode(as_array(GRID)))), GRID, atol=1e-12)


def test_every_8_and_16_bit_level_decodes_as_colour_science_decodes_it():
    """The table an import decodes 8- and 16-bit images through: each level's value from colour-science's sRGB curve,
    and the same float32 as decoding ``level / top`` directly."""
    from gra_mi.core.color import srgb_decode_levels

    for dtype, top in ((np.uint8, 255), (np.uint16, 65535)):
        levels = np.arange(top + 1, dtype=dtype)
        table = srgb_decode_levels(levels)
        assert table.dtype == np.float32
        np.testing.assert_allclose(table, colour.cctf_decoding(levels / top, function="sRGB"), rtol=1e-6, atol=1e-9)
        np.testing.assert_array_equal(table, srgb_decode(levels.astype(np.float32) / top).astype(np.float32))
    with pytest.raises(ValueError, match="8- or 16-bit"):
        srgb_decode_levels(np.zeros(3, np.float32))


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_values_a_display_cannot_show_go_to_the_nearest_end(backend):
    values = np.array([np.nan, np.inf, -np.inf, -0.5, 1.5])
    x = values if backend == "numpy" else torch.from_numpy(values)
    got = np.asarray(srgb_encode(x) if backend == "numpy" else srgb_encode(x).numpy())
    np.testing.assert_allclose(got, [0.0, 1.0, 0.0, 0.0, 1.0], atol=1e-12)


def test_previews_and_metrics_show_the_same_values():
    """The 8-bit preview is the display image quantised: +Inf white in both (one mapped it to black before)."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 2, (6, 7, 3)).astype(np.float32)
    image[0, 0] = [np.inf, np.nan, -1.0]
    shown = to_display(image, 0.7)
    np.testing.assert_allclose(to_srgb8(image, 0.7)[..., :3] / 255.0, shown, atol=0.5 / 255 + 1e-9)
    np.testing.assert_array_equal(to_srgb8(image, 0.7)[0, 0], [255, 0, 0])


def test_display_exposure_puts_the_99th_percentile_at_0_8():
    image = np.zeros((10, 100, 3))
    image[..., :] = np.arange(1000).reshape(10, 100, 1) + 1.0  # luminance 1 … 1000
    image[0, 0] = np.nan  # not counted
    top = np.percentile(np.arange(1, 1001)[1:], 99.0)
    assert display_exposure(image) == pytest.approx(0.8 / top)
    mask = np.zeros((10, 100), bool)
    mask[0, 1:11] = True  # luminance 2 … 11
    assert display_exposure(image, mask) == pytest.approx(0.8 / np.percentile(np.arange(2, 12), 99.0))
    assert display_exposure(np.zeros((4, 4, 3))) == 1.0
