"""Lens distortion (gra_mi/capture/lens.py) against OpenCV's own models: points, their inverse, whole images, and
what no model can give (the pixels past a fold)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from gra_mi.capture.lens import LensDistortion, held_fraction, pinhole_positions, undistort_image
from gra_mi.core.errors import GraMiInputError

OPENCV = np.array([-0.21, 0.07, 0.001, -0.0015, -0.01])  # k1 k2 p1 p2 k3, a wide-angle lens's size
FISHEYE = np.array([0.05, -0.01, 0.002, -0.0003])
# OpenCV's full model (CALIB_RATIONAL_MODEL | CALIB_THIN_PRISM_MODEL): k1 k2 p1 p2 k3, k4 k5 k6 dividing, s1…s4;
# rational calibrations come out with numerator and divisor of similar size, as here
FULL = np.array([0.62, -0.21, 0.001, -0.0015, 0.03, 0.85, -0.12, 0.05, 0.002, -0.001, -0.0015, 0.0008])
TILT = np.array([0.03, -0.05])  # τx, τy in radians: a Scheimpflug camera's sensor, a few degrees off square
K = np.array([[150.0, 0, 81.3], [0, 146.0, 58.7], [0, 0, 1]])  # gra-mi's pixel centres at +0.5


def _opencv_k(k: np.ndarray) -> np.ndarray:
    """The same camera in OpenCV's convention (pixel centres on integers)."""
    shifted = k.copy()
    shifted[:2, 2] -= 0.5
    return shifted


@pytest.fixture
def points():
    return np.random.default_rng(0).uniform(-0.6, 0.6, (2000, 2))


@pytest.mark.parametrize(
    "coefficients",
    [
        OPENCV,
        FULL[:8],
        FULL,
        np.concatenate([FULL, np.zeros(2)]),
        np.concatenate([FULL, TILT]),
        np.concatenate([OPENCV, np.zeros(7), TILT]),
    ],
    ids=["k1-k3 p1 p2", "rational", "rational + thin prism", "14 with the tilt zero", "14, a tilted sensor", "k1-k3 p1 p2, tilted"],
)
def test_radial_tangential_points_match_opencv(points, coefficients):
    lens = LensDistortion.opencv(coefficients, "intri.yml", "dist_01")
    ours = lens.distort(points)
    theirs, _ = cv2.projectPoints(np.concatenate([points, np.ones((len(points), 1))], 1), np.zeros(3), np.zeros(3), np.eye(3), coefficients)
    np.testing.assert_allclose(ours, theirs[:, 0], atol=1e-12)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 500, 1e-15)
    back = cv2.undistortPoints(ours[:, None], np.eye(3), coefficients, None, None, criteria=criteria)[:, 0]
    np.testing.assert_allclose(lens.undistort(ours), back, atol=1e-8)
    np.testing.assert_allclose(lens.undistort(ours), points, atol=1e-10)


def test_a_rational_divisors_pole_is_a_fold():
    """1 / (1 + q1 r²) with q1 < 0 sends r towards infinity at r = 1/√−q1: nothing past it is imaged."""
    lens = LensDistortion.opencv([0, 0, 0, 0, 0, -0.5, 0, 0], "intri.yml", "dist_01")
    assert lens.fold_radius() == pytest.approx(np.sqrt(2), rel=1e-4)
    assert "q1=-0.5" in lens.describe()


def test_fisheye_points_match_opencv(points):
    lens = LensDistortion.of("fisheye", "transforms.json", "frames[0]", **dict(zip(("k1", "k2", "k3", "k4"), FISHEYE, strict=True)))
    ours = lens.distort(points)
    np.testing.assert_allclose(ours, cv2.fisheye.distortPoints(points[:, None], np.eye(3), FISHEYE)[:, 0], atol=1e-12)
    back = cv2.fisheye.undistortPoints(ours[:, None], np.eye(3), FISHEYE)[:, 0]
    np.testing.assert_allclose(lens.undistort(ours), back, atol=1e-6)  # OpenCV's fisheye inverse stops at 1e-8 in θ
    np.testing.assert_allclose(lens.undistort(ours), points, atol=1e-10)


def test_nerfstudios_k4_is_the_r8_term():
    """nerfstudio's OPENCV k4 multiplies r⁸ (its radial_and_tangential_undistort), not OpenCV's rational divisor."""
    lens = LensDistortion.of("radial-tangential", "transforms.json", "frames[0]", k4=0.02)
    x, y = 0.3, -0.4
    r2 = x * x + y * y
    np.testing.assert_allclose(lens.distort(np.array([x, y])), np.array([x, y]) * (1 + 0.02 * r2**4), rtol=1e-15)


def test_an_image_undistorts_as_opencv_undistorts_it():
    rng = np.random.default_rng(1)
    image = cv2.GaussianBlur(rng.random((120, 160, 3)).astype(np.float32), (0, 0), 3)
    lens = LensDistortion.opencv(OPENCV, "intri.yml", "dist_01")
    ours = undistort_image(image, K, lens)
    theirs = cv2.undistort(image, _opencv_k(K), OPENCV)  # bilinear, with 5-bit interpolation weights
    np.testing.assert_allclose(ours[2:-2, 2:-2], theirs[2:-2, 2:-2], atol=2e-3)
    # and a source pixel's place in the pinhole image, OpenCV's undistortPoints of its centre
    x, y = pinhole_positions(K, lens, 160, 120)
    ref = cv2.undistortPoints(np.array([[[17.0, 9.0]]]), _opencv_k(K), OPENCV, P=_opencv_k(K))[0, 0]
    np.testing.assert_allclose([x[9, 17], y[9, 17]], ref, atol=1e-3)


def test_an_image_undistorts_as_opencv_undistorts_it_with_the_full_model():
    rng = np.random.default_rng(2)
    image = cv2.GaussianBlur(rng.random((120, 160, 3)).astype(np.float32), (0, 0), 3)
    ours = undistort_image(image, K, LensDistortion.opencv(FULL, "intri.yml", "dist_01"))
    theirs = cv2.undistort(image, _opencv_k(K), FULL)
    np.testing.assert_allclose(ours[2:-2, 2:-2], theirs[2:-2, 2:-2], atol=2e-3)


def test_an_image_through_a_tilted_sensor_undistorts_as_opencv_undistorts_it():
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.random((120, 160, 3)).astype(np.float32), (0, 0), 3)
    coefficients = np.concatenate([OPENCV, np.zeros(7), TILT])
    ours = undistort_image(image, K, LensDistortion.opencv(coefficients, "intri.yml", "dist_01"))
    theirs = cv2.undistort(image, _opencv_k(K), coefficients)
    held = ours[..., :3].max(axis=-1) > 0  # the tilt brings pixels from outside the source image into view
    inner = np.zeros_like(held)
    inner[4:-4, 4:-4] = True
    np.testing.assert_allclose(ours[held & inner], theirs[held & inner], atol=2e-3)
    assert (held & inner).mean() > 0.8


def test_pixels_past_the_fold_are_left_black_not_mirrored():
    """A strong barrel folds back (r·d(r) stops growing): cv2.undistort fills the pinhole pixels past it with the
    image folded back on itself; here they hold nothing, and the share the source holds is said."""
    lens = LensDistortion.opencv([-0.45, 0.0, 0, 0, 0], "intri.yml", "dist_01")
    assert lens.fold_radius() == pytest.approx(1 / np.sqrt(3 * 0.45), rel=1e-4)
    image = np.ones((120, 160, 1), np.float32)
    wide = np.array([[60.0, 0, 80], [0, 60.0, 60], [0, 0, 1]])  # corners at r = 1.67, past the fold at 0.86
    ours = undistort_image(image, wide, lens)[..., 0]
    x = (np.arange(160) + 0.5 - 80) / 60
    y = (np.arange(120) + 0.5 - 60) / 60
    past = np.hypot(x[None, :], y[:, None]) > lens.fold_radius()
    assert past.any() and (ours[past] == 0).all() and np.allclose(ours[~past & (np.hypot(x[None, :], y[:, None]) < 0.8)], 1, atol=1e-6)
    folded = cv2.undistort(image, _opencv_k(wide), np.array([-0.45, 0, 0, 0, 0]))
    assert (folded[past] > 0).mean() > 0.5  # what OpenCV leaves there: the image, folded back
    assert held_fraction(wide, lens, 160, 120) == pytest.approx(1 - past.mean(), abs=0.02)
    xs, _ = pinhole_positions(wide, lens, 160, 120)
    assert np.isnan(xs).any()  # source pixels past the lens's reach have no pinhole point


@pytest.mark.parametrize(
    "make, needles",
    [
        (lambda: LensDistortion.opencv([0.1, float("nan"), 0, 0, 0], "intri.yml", "dist_01"), ["finite"]),
        (lambda: LensDistortion.opencv([0.1, 0, 0], "intri.yml", "dist_01"), ["4, 5, 8"]),
        (lambda: LensDistortion.opencv([0.1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.9, 0], "intri.yml", "dist_01"), ["tilted", "45°"]),
        (lambda: LensDistortion.of("fisheye", "t.json", "frames[2]", k1=0.1, tau_x=0.01), ["fisheye", "tilt"]),
        (lambda: LensDistortion.opencv(["0.1", "a", 0, 0], "intri.yml", "dist_01"), ["numbers"]),
        (lambda: LensDistortion.of("fisheye", "t.json", "frames[2]", k1=0.1, p1=0.01), ["fisheye", "only radial"]),
        (lambda: LensDistortion.of("fisheye", "t.json", "frames[2]", k1=0.1, q1=0.01), ["fisheye", "only radial"]),
        (lambda: LensDistortion.of("radial-tangential", "t.json", "frames[2]", k1=-1e6), ["folds at the image centre"]),
    ],
)
def test_bad_lenses_are_named(make, needles):
    with pytest.raises(GraMiInputError) as info:
        make()
    for needle in needles:
        assert needle in str(info.value)
    assert "dist_01" in str(info.value) or "frames[2]" in str(info.value)


def test_no_distortion_is_no_lens():
    assert LensDistortion.opencv(np.zeros(5), "intri.yml", "dist_01") is None
    assert LensDistortion.opencv([], "intri.yml", "dist_01") is None
    assert LensDistortion.of("fisheye", "t.json", "frames[0]", k1=None, k2=0.0) is None


def test_a_mask_undistorts_to_coverage_not_to_a_dilated_mask():
    mask = np.zeros((120, 160, 1), bool)
    mask[40:80, 50:110] = True
    lens = LensDistortion.opencv(OPENCV, "intri.yml", "dist_01")
    out = undistort_image(mask, K, lens)
    assert out.dtype == np.float32 and ((out > 0) & (out < 1)).any()  # soft edges, not a dilated binary mask
    theirs = cv2.undistort(mask.astype(np.float32), _opencv_k(K), OPENCV)
    np.testing.assert_allclose(out[..., 0], theirs, atol=0.05)


def test_the_held_share_of_a_large_image_is_estimated_from_a_grid():
    """held_fraction samples about 256 pixels along the longer side: within half a per cent of the full map's share."""
    from gra_mi.capture.lens import _k_key, _source_positions

    lens = LensDistortion.opencv([-0.45, 0.0, 0, 0, 0], "intri.yml", "dist_01")
    k = np.array([[600.0, 0, 800], [0, 600.0, 600], [0, 0, 1]])  # a wide view: the fold cuts the corners
    full = float(_source_positions(lens, _k_key(k), 1600, 1200)[2].mean())
    assert 0.3 < full < 0.99 and held_fraction(k, lens, 1600, 1200) == pytest.approx(full, abs=0.005)
