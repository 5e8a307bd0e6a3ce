"""`gra-mi eval`: the metrics against known values, flicker correction, platform composites, the protocol end to end."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from gra_mi.core.color import to_display
from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.metrics import compare, flip, temporal_error

EXPOSURE = 1.0


def from_display(display: np.ndarray, exposure: float = EXPOSURE) -> np.ndarray:
    """Linear radiance that :func:`to_display` shows as ``display`` (the sRGB decode, independent of metrics.py)."""
    d = np.asarray(display, np.float64)
    return (np.where(d <= 0.04045, d / 12.92, (np.maximum(d + 0.055, 0) / 1.055) ** 2.4) / exposure).astype(np.float64)


def moving_video(frames: int = 8, h: int = 32, w: int = 48) -> list[np.ndarray]:
    """Display frames in [0.2, 0.8]: a pattern sliding one pixel per frame (so the truth itself changes)."""
    y, x = np.mgrid[0:h, 0:w]
    return [np.stack([0.5 + 0.3 * np.sin(0.4 * (x - t) + c) * np.cos(0.3 * y) for c in (0.0, 1.0, 2.0)], -1) for t in range(frames)]


# --------------------------------------------------------------------------------------------------------------
# Metrics against known values
# --------------------------------------------------------------------------------------------------------------


def test_display_psnr_of_a_known_shift():
    """A uniform display offset δ on every subject pixel is PSNR −20·log10 δ; identical images are inf."""
    truth_display = 0.5 + 0.1 * (moving_video(1)[0] - 0.5)  # little contrast: nothing clips at the display exposure
    truth = np.concatenate([from_display(truth_display), np.ones((*truth_display.shape[:2], 1))], -1)
    # the truth's display exposure is p99 → 0.8; shift in that display space
    from gra_mi.core.color import display_exposure
    from gra_mi.core.metrics import subject_mask

    exposure = display_exposure(truth, subject_mask(truth))
    shown = to_display(truth, exposure)
    assert shown.max() < 0.95  # nothing clips, so the offset survives
    for delta in (0.01, 0.05):
        shifted = from_display(shown + delta, exposure)
        assert compare(shifted, truth)["psnr"] == pytest.approx(-20 * math.log10(delta), abs=1e-6)
    assert compare(truth, truth)["psnr"] == float("inf") and compare(truth, truth)["ssim"] == pytest.approx(1.0)


def _flip_uniform_reference(a: tuple, b: tuple) -> float:
    """LDR-ꟻLIP of two uniform sRGB images, written from the paper (Andersson et al. 2020, Sec. 3), float64.

    On a uniform image the CSF filters (normalised) change nothing and the feature detectors see no edge or point,
    so ꟻLIP is the colour pipeline alone: sRGB → linear → L*a*b* (D65) → Hunt-adjusted a*, b* (× 0.01·L*) → HyAB
    distance → ^0.7 → the piecewise remap with p_c = 0.4, p_t = 0.95 against the green–blue maximum."""

    def lab(rgb):
        c = np.asarray(rgb, np.float64)
        lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
        m = np.array([[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]])
        xyz = m @ lin / (m @ np.ones(3))  # relative to the D65 white (1, 1, 1)
        f = np.where(xyz > (6 / 29) ** 3, np.cbrt(xyz), xyz / (3 * (6 / 29) ** 2) + 4 / 29)
        L, A, B = 116 * f[1] - 16, 500 * (f[0] - f[1]), 200 * (f[1] - f[2])
        return np.array([L, 0.01 * L * A, 0.01 * L * B])

    def hyab(p, q):
        d = p - q
        return abs(d[0]) + math.hypot(d[1], d[2])

    cmax = hyab(lab((0, 1, 0)), lab((0, 0, 1))) ** 0.7
    e = hyab(lab(a), lab(b)) ** 0.7
    pc, pt = 0.4, 0.95
    return e / (pc * cmax) * pt if e < pc * cmax else pt + (e - pc * cmax) / (cmax - pc * cmax) * (1 - pt)


@pytest.mark.parametrize(
    "a, b",
    [((0, 0, 0), (1, 1, 1)), ((0.5, 0.5, 0.5), (0.6, 0.6, 0.6)), ((0.8, 0.2, 0.1), (0.2, 0.6, 0.9)), ((0.3, 0.3, 0.3), (0.3, 0.3, 0.4))],
)
def test_flip_of_uniform_images_matches_the_papers_colour_pipeline(a, b):
    """The flip-evaluator package through gra-mi's masked mean, against an independent float64 reference."""
    import flip_evaluator

    ref, test = np.full((24, 24, 3), a, np.float32), np.full((24, 24, 3), b, np.float32)
    _, mean, _ = flip_evaluator.evaluate(ref, test, "LDR", applyMagma=False)
    assert mean == pytest.approx(_flip_uniform_reference(a, b), abs=2e-3)
    # through gra-mi: linear images whose display (exposure 0.8 at the 99th percentile) is the same pair
    truth = np.concatenate([from_display(ref), np.ones((24, 24, 1))], -1)
    from gra_mi.core.color import display_exposure

    exposure = display_exposure(truth)
    image = from_display(test, exposure) * 1.0
    shown_truth = to_display(truth, exposure)
    expected = _flip_uniform_reference(tuple(shown_truth[0, 0]), tuple(to_display(image, exposure)[0, 0]))
    assert flip(image, truth) == pytest.approx(expected, abs=3e-3)


def test_flip_is_zero_for_equal_images_and_grows_with_noise():
    rng = np.random.default_rng(0)
    truth = np.concatenate([from_display(np.stack(moving_video(1), 0)[0]), np.ones((32, 48, 1))], -1)
    assert flip(truth, truth) == 0.0
    errors = [flip(truth * (1 + s * rng.standard_normal(truth.shape)), truth) for s in (0.02, 0.1, 0.3)]
    assert 0 < errors[0] < errors[1] < errors[2] < 1


def test_temporal_error_of_a_synthetic_flicker_of_known_amplitude():
    """A video alternating by ±a around the truth (in display values) scores 2a; a constant offset scores 0."""
    shown = moving_video()
    truths = [from_display(d) for d in shown]
    masks = [np.ones(d.shape[:2], bool) for d in shown]
    for a in (0.01, 0.04):
        flicker = [from_display(d + a * (-1) ** t) for t, d in enumerate(shown)]
        assert temporal_error(flicker, truths, masks, EXPOSURE) == pytest.approx(2 * a, abs=1e-9)
    offset = [from_display(d + 0.05) for d in shown]
    assert temporal_error(offset, truths, masks, EXPOSURE) == pytest.approx(0.0, abs=1e-9)
    assert math.isnan(temporal_error(truths[:1], truths[:1], masks[:1], EXPOSURE))
    # only pixels the subject covers in both frames of a pair count
    half = [np.zeros_like(m) for m in masks]
    for m in half:
        m[:, :24] = True
    flicker = [
        from_display(np.where(np.arange(48)[None, :, None] < 24, d + 0.02 * (-1) ** t, d + 0.3 * (-1) ** t)) for t, d in enumerate(shown)
    ]
    assert temporal_error(flicker, truths, half, EXPOSURE) == pytest.approx(0.04, abs=1e-9)
    # a gap in the capture: no pair across it (a jump of 0.1 there, a flicker of ±0.01 elsewhere)
    jumped = [from_display(d + 0.01 * (-1) ** t + (0.1 if t >= 4 else 0.0)) for t, d in enumerate(shown)]
    assert temporal_error(jumped, truths, masks, EXPOSURE, breaks={4}) == pytest.approx(0.02, abs=1e-9)
    assert temporal_error(jumped, truths, masks, EXPOSURE) > 0.025


def test_frechet_distance_of_an_affine_map_is_analytic():
    """b = s·a + t: the Fréchet distance is |t + (s − 1)μa|² + (s − 1)²·tr Σa, with the samples' own statistics."""
    from gra_mi.eval.perceptual import frechet_distance

    a = np.random.default_rng(1).normal(size=(300, 5)) @ np.diag([1.0, 2.0, 0.5, 1.5, 1.0])
    s, t = 1.7, np.array([0.3, -1.0, 0.0, 2.0, 0.5])
    expected = np.sum((t + (s - 1) * a.mean(axis=0)) ** 2) + (s - 1) ** 2 * np.trace(np.cov(a, rowvar=False))
    assert frechet_distance(a, s * a + t) == pytest.approx(expected, rel=1e-6)
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-6)


# --------------------------------------------------------------------------------------------------------------
# LPIPS and FVD weights: loaded from disk in every layout, refused when they are not what the flag says
# --------------------------------------------------------------------------------------------------------------


def _lpips_files(folder: Path) -> tuple[Path, Path, dict]:
    """A torchvision-layout AlexNet checkpoint and an lpips-layout heads file with non-negative heads (as trained)."""
    from gra_mi.eval.perceptual import LPIPS

    torch.manual_seed(0)
    state = LPIPS().state_dict()
    backbone = {k: v for k, v in state.items() if k.startswith("features.")}
    backbone["classifier.1.weight"] = torch.zeros(4, 4)  # torchvision's classifier is there and ignored
    heads = {f"lin{i}.model.1.weight": state[f"heads.{i}.weight"].abs() for i in range(5)}
    folder.mkdir(parents=True, exist_ok=True)
    torch.save(backbone, folder / "alexnet-owt.pth")
    torch.save(heads, folder / "alex.pth")
    return folder / "alexnet-owt.pth", folder / "alex.pth", {**backbone, **heads}


def test_lpips_loads_every_layout_and_measures_a_difference(tmp_path):
    from gra_mi.eval.perceptual import load_lpips, lpips_distance

    backbone, heads, _ = _lpips_files(tmp_path / "w")
    a = from_display(moving_video(1)[0])
    mask = np.ones(a.shape[:2], bool)
    model = load_lpips([backbone, heads])
    assert lpips_distance(model, a, a, mask, EXPOSURE) == 0.0
    d1 = lpips_distance(model, from_display(np.clip(moving_video(1)[0] + 0.05, 0, 1)), a, mask, EXPOSURE)
    d2 = lpips_distance(model, from_display(np.clip(moving_video(1)[0] + 0.2, 0, 1)), a, mask, EXPOSURE)
    assert 0 < d1 < d2
    # a folder holding both, and one full lpips.LPIPS state dict (net.sliceK.N.*, linK.model.1.weight)
    assert lpips_distance(load_lpips([tmp_path / "w"]), a, a * 0.5, mask, EXPOSURE) == pytest.approx(
        lpips_distance(model, a, a * 0.5, mask, EXPOSURE)
    )
    full = {}
    for key, value in torch.load(backbone).items():
        if key.startswith("features."):
            index = int(key.split(".")[1])
            k = next(i for i, end in enumerate((2, 5, 8, 10, 12), start=1) if index < end)
            full[f"net.slice{k}.{index}.{key.split('.')[2]}"] = value
    full.update(torch.load(heads))
    torch.save(full, tmp_path / "lpips_alex.pth")
    assert lpips_distance(load_lpips([tmp_path / "lpips_alex.pth"]), a, a * 0.5, mask, EXPOSURE) == pytest.approx(
        lpips_distance(model, a, a * 0.5, mask, EXPOSURE)
    )


def test_lpips_and_i3d_refuse_files_that_are_not_what_the_flag_says(tmp_path):
    from gra_mi.eval.perceptual import load_i3d, load_lpips

    backbone, heads, _ = _lpips_files(tmp_path / "w")
    with pytest.raises(GraMiInputError, match="linear heads"):
        load_lpips([backbone])
    with pytest.raises(GraMiInputError, match="backbone"):
        load_lpips([heads])
    (tmp_path / "junk.pth").write_text("not weights")
    with pytest.raises(GraMiInputError, match="junk.pth.*not a PyTorch weights file"):
        load_lpips([tmp_path / "junk.pth", heads])
    wrong = torch.load(backbone)
    wrong["features.0.weight"] = torch.zeros(64, 3, 3, 3)
    torch.save(wrong, tmp_path / "vgg.pth")
    with pytest.raises(GraMiInputError, match=r"features.0.weight.*shape"):
        load_lpips([tmp_path / "vgg.pth", heads])
    with pytest.raises(GraMiInputError, match="not found"):
        load_lpips([tmp_path / "nothing.pth"])
    with pytest.raises(GraMiInputError, match="not a TorchScript model"):
        load_i3d(backbone)


class _FakeI3D(torch.nn.Module):
    """The calling convention of i3d_torchscript.pt: (clips, rescale, resize, return_features) → (N, D)."""

    def __init__(self):
        super().__init__()
        self.proj = torch.nn.Linear(3, 8)

    def forward(self, x: torch.Tensor, rescale: bool = False, resize: bool = False, return_features: bool = True) -> torch.Tensor:
        return self.proj(x.mean(dim=(2, 3, 4)))


def test_fvd_through_a_torchscript_feature_network(tmp_path):
    from gra_mi.eval.perceptual import frechet_distance, i3d_features, load_i3d

    torch.jit.script(_FakeI3D()).save(str(tmp_path / "i3d.pt"))
    model = load_i3d(tmp_path / "i3d.pt")
    rng = np.random.default_rng(0)
    clips = [rng.uniform(0, 1, (17, 16, 16, 3)) for _ in range(4)]
    real = i3d_features(model, clips)
    assert real.shape == (4, 8)
    assert frechet_distance(real, i3d_features(model, clips)) == pytest.approx(0.0, abs=1e-6)
    assert frechet_distance(real, i3d_features(model, [np.clip(c + 0.3, 0, 1) for c in clips])) > 1e-3


# --------------------------------------------------------------------------------------------------------------
# Flicker correction
# --------------------------------------------------------------------------------------------------------------


def _flickering_refinement(frames: int = 10):
    """truth: a sliding pattern with fine detail; stable: its low frequencies only (a coarse render: no detail, no
    flicker); refined: the truth with a low-frequency brightness wobble of ±15 % alternating frame to frame."""
    from scipy.ndimage import gaussian_filter

    h, w = 48, 64
    y, x = np.mgrid[0:h, 0:w]
    truths, stable, refined = [], [], []
    for t in range(frames):
        base = np.stack([0.35 + 0.15 * np.sin(0.08 * (x - t)) * np.cos(0.06 * y) + 0.05 * c for c in range(3)], -1)
        detail = 0.06 * np.sign(np.sin(1.3 * (x - t)) * np.sin(1.1 * y))[..., None]
        truth = from_display(np.clip(base + detail, 0, 1))
        truths.append(truth)
        stable.append(from_display(np.stack([gaussian_filter(np.clip(base + detail, 0, 1)[..., c], 3) for c in range(3)], -1)))
        wobble = 1 + 0.15 * (-1) ** t * (0.5 + 0.5 * np.cos(0.05 * x))[..., None]
        refined.append(truth * wobble)
    return truths, stable, refined


def test_deflicker_removes_a_synthetic_flicker_and_keeps_the_detail():
    from gra_mi.core.metrics import psnr
    from gra_mi.refiner.deflicker import DeflickerConfig, deflicker_frame

    truths, stable, refined = _flickering_refinement()
    masks = [np.ones(t.shape[:2], bool) for t in truths]
    corrected = [deflicker_frame(r, s, EXPOSURE, DeflickerConfig()) for r, s in zip(refined, stable, strict=True)]
    before, after = temporal_error(refined, truths, masks, EXPOSURE), temporal_error(corrected, truths, masks, EXPOSURE)
    assert after < 0.35 * before, (before, after)

    def mean_psnr(video):
        return np.mean([psnr(to_display(v, EXPOSURE), to_display(t, EXPOSURE), peak=1.0) for v, t in zip(video, truths, strict=True)])

    assert mean_psnr(corrected) > mean_psnr(refined) - 0.2
    assert mean_psnr(corrected) > mean_psnr(stable) + 3.0, "the refined frame's detail is kept, not the coarse render"
    # strength 0 is the identity (up to the display round trip); a size mismatch is refused
    same = deflicker_frame(refined[0], stable[0], EXPOSURE, DeflickerConfig(strength=0.0))
    np.testing.assert_allclose(same, refined[0], rtol=1e-4, atol=1e-6)
    with pytest.raises(GraMiParameterError, match="stable"):
        deflicker_frame(refined[0], stable[0][:10], EXPOSURE)
    for bad in (DeflickerConfig(filter_radius=0), DeflickerConfig(filter_eps=float("nan")), DeflickerConfig(strength=2.0)):
        with pytest.raises(GraMiParameterError):
            bad.validate()


def test_deflicker_cli_on_folders(tmp_path, capsys):
    from gra_mi.cli import main
    from gra_mi.core.io import read_exr, write_exr

    truths, stable, refined = _flickering_refinement(4)
    for i, (r, s) in enumerate(zip(refined, stable, strict=True)):
        write_exr(tmp_path / "refined" / f"frame_{i:04d}.exr", r.astype(np.float32))
        write_exr(tmp_path / "stable" / f"f{i:02d}.exr", s.astype(np.float32))
    frames, stable_dir = str(tmp_path / "refined"), str(tmp_path / "stable")
    assert main(["deflicker", frames, "--stable", stable_dir, "--out", str(tmp_path / "out"), "--exposure", "1"]) == 0
    assert (tmp_path / "out" / "deflickered.mp4").is_file() and read_exr(tmp_path / "out" / "frame_0003.exr").shape == (48, 64, 3)
    capsys.readouterr()
    (tmp_path / "stable" / "f03.exr").unlink()
    assert main(["deflicker", frames, "--stable", stable_dir, "--out", str(tmp_path / "o2")]) == 2
    assert "3 frames" in capsys.readouterr().err
    write_exr(tmp_path / "stable" / "f03.exr", stable[3][:20].astype(np.float32))
    assert main(["deflicker", frames, "--stable", stable_dir, "--out", str(tmp_path / "o3")]) == 2
    err = capsys.readouterr().err
    assert "f03.exr" in err and "64×20" in err and "Traceback" not in err
    assert main(["deflicker", frames, "--stable", stable_dir, "--filter-radius", "0"]) == 2
    assert "--filter-radius" in capsys.readouterr().err
    write_exr(tmp_path / "stable" / "f03.exr", stable[3].astype(np.float32))
    for radius, said in (("48", "at most 47"), ("100000", "past the 64×48 frame's borders")):  # it once asked for 160 GB
        assert main(["deflicker", frames, "--stable", stable_dir, "--filter-radius", radius, "--out", str(tmp_path / "o4")]) == 2
        assert said in capsys.readouterr().err and not (tmp_path / "o4").exists()
    assert main(["deflicker", frames, "--stable", stable_dir, "--filter-radius", "47", "--out", str(tmp_path / "o4")]) == 0


# --------------------------------------------------------------------------------------------------------------
# Platform composites
# --------------------------------------------------------------------------------------------------------------


def test_platform_layer_is_lit_by_the_environment_and_shadowed_by_the_subject(llvm_variant):
    """Under a uniform environment of radiance L, the platform's top away from the subject is ρ·L (it sees the
    whole upper hemisphere: irradiance πL, Lambertian radiance ρ/π·πL). Under a low sun from +x, the subject's shadow
    darkens the −x side of the platform, not the +x side."""
    from gra_mi.render.composite import PlatformConfig, composite_on_platform, platform_layer
    from gra_mi.stage.envmap import pixel_directions
    from gra_mi.stage.lightstage import Camera
    from gra_mi.subject.sequence import tiny_subject

    seq = tiny_subject(num_frames=2)
    v = seq.vertices.reshape(-1, 3)
    top, centre = float(v[:, 1].min()), v.mean(axis=0)
    size = 128
    eye = np.array([centre[0], float(v[:, 1].max()) + 1.0, centre[2]])

    def looking_down(f: float):
        """A camera above the subject looking straight down, and each pixel's ground point (x, z)."""
        c2w = np.eye(4)
        c2w[:3, :3] = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]).T  # OpenCV x → +x, y (down the image) → +z, z → −y
        c2w[:3, 3] = eye
        ys, xs = np.mgrid[0:size, 0:size]
        height = eye[1] - top
        return (
            Camera("top", size, size, f, f, size / 2, size / 2, c2w),
            eye[0] + (xs + 0.5 - size / 2) / f * height,
            eye[2] + (ys + 0.5 - size / 2) / f * height,
        )

    # uniform sky, a wide platform, scored far from the subject (which hides < 1 % of the sky from there)
    cam, gx, gz = looking_down(25.0)
    r = np.hypot(gx - centre[0], gz - centre[2])
    L, rho = 0.7, 0.5
    layer = platform_layer(
        seq, 0, cam, np.full((32, 64, 3), L, np.float32), PlatformConfig(radius=3.0, thickness=0.05, reflectance=rho, spp=64)
    )
    ring = (r > 2.3) & (r < 2.9)
    assert ring.sum() > 500 and (layer[ring, 3] > 0.99).all()
    assert np.median(layer[ring, :3]) == pytest.approx(rho * L, rel=0.02)
    assert (layer[r > 3.1, 3] == 0).all(), "the environment is hidden: alpha 0 off the platform"

    # a low sun from +x: the subject's shadow falls on the −x side
    cam, gx, gz = looking_down(120.0)
    r = np.hypot(gx - centre[0], gz - centre[2])
    sun = np.array([np.cos(np.radians(30)), np.sin(np.radians(30)), 0.0])
    env = np.full((32, 64, 3), 0.05, np.float32)
    env[pixel_directions(32, 64) @ sun > np.cos(np.radians(8))] = 50.0
    config = PlatformConfig(radius=1.0, thickness=0.05, reflectance=rho, spp=64)
    lit = platform_layer(seq, 0, cam, env, config)
    open_ground = (r > 0.45) & (r < 0.95) & (np.abs(gz - centre[2]) < 0.15)
    shadow_side = lit[open_ground & (gx < centre[0]), :3].mean()
    sun_side = lit[open_ground & (gx > centre[0]), :3].mean()
    assert shadow_side < 0.5 * sun_side, (shadow_side, sun_side)
    layer, ring = lit, (r > 0.8) & (r < 0.95)

    # the composite: the plate where the layer is not, the layer (+ the subject's own light) where it is
    plate = np.full((size, size, 3), 2.0, np.float32)
    subject = np.zeros((size, size, 3), np.float32)
    out = composite_on_platform(subject, layer, plate)
    np.testing.assert_allclose(out[r > 1.05], 2.0)
    np.testing.assert_allclose(out[ring], layer[ring, :3], rtol=1e-6)
    with pytest.raises(GraMiParameterError, match="sizes"):
        composite_on_platform(subject[:10], layer, plate)
    with pytest.raises(GraMiParameterError, match="reflectance"):
        PlatformConfig(reflectance=1.5).validate()


def test_relight_composite_puts_the_subject_on_a_platform(tmp_path, llvm_variant, capsys):
    import imageio.v3 as iio

    from gra_mi.cli import main
    from gra_mi.core.io import write_exr
    from tests.test_cli import TINY

    write_exr(tmp_path / "sky.exr", np.full((16, 32, 3), 0.8, np.float32))
    common = ["relight", str(TINY), "--frames", "0:2", "--envmap", str(tmp_path / "sky.exr"), "--uv-resolution", "64", "--exposure", "0.01"]
    assert main([*common, "--background", "--out", str(tmp_path / "plain")]) == 0
    assert main([*common, "--composite", "--platform-spp", "8", "--out", str(tmp_path / "platform")]) == 0
    a = iio.imread(tmp_path / "plain" / "sky" / "cam00" / "frame_0001.png").astype(float)
    b = iio.imread(tmp_path / "platform" / "sky" / "cam00" / "frame_0001.png").astype(float)
    assert a.max() < 250, "not saturated: the comparison means something"
    changed = np.abs(a - b).max(axis=-1) > 8
    assert changed.mean() > 0.01, "the platform and its shadow change the background"
    assert not changed[:16, :20].any() and not changed[:16, -20:].any(), "the top corners (sky, off the subject) are the plate in both"
    capsys.readouterr()
    assert main([*common, "--composite", "--platform-reflectance", "2", "--out", str(tmp_path / "x")]) == 2
    assert "--platform-reflectance" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------------------------
# The protocol end to end on a tiny run
# --------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny_run(path_traced_fit, tmp_path_factory):
    """A run folder as the demo lays it out: the tiny path-traced capture and its fit, a RelightNet, the
    refiner's data, and a refined sequence that is the truth with an alternating ±20 % flicker (a stand-in for a
    refiner whose frames are good but flicker), corrected by ``gra-mi refine``'s own filter."""
    import os

    from gra_mi.core.io import atomic_write_text, write_exr
    from gra_mi.core.runtime import choose_variant
    from gra_mi.refiner.data import CaptureSequencesConfig, dataset_from_capture
    from gra_mi.refiner.dataset import RefinerDataset
    from gra_mi.refiner.deflicker import DeflickerConfig, deflicker_frame
    from gra_mi.relightnet.model import RelightNet, RelightNetConfig

    choose_variant("llvm_ad_rgb")
    run = tmp_path_factory.mktemp("evalrun")
    os.symlink(path_traced_fit / "cap", run / "capture")
    os.symlink(path_traced_fit / "fit", run / "fit")
    # an untrained RelightNet: the protocol is under test here, not the network (tests/test_relightnet.py trains it)
    torch.manual_seed(0)
    from gra_mi.core.io import read_exr

    RelightNet(RelightNetConfig(resolution=read_exr(run / "fit" / "albedo.exr").shape[0])).save(run / "relightnet")
    dataset_from_capture(
        run / "capture",
        run / "fit",
        run / "refiner" / "data",
        relightnet_dir=run / "relightnet",
        config=CaptureSequencesConfig(scale=0.25, test_length=20),
    )
    data = RefinerDataset(run / "refiner" / "data")
    name = data.names("test")[0]
    coarse = [data.delivered(name, i, "coarse") for i in range(20)]  # the whole frames (the refiner sees a subject crop)
    target = [data.delivered(name, i, "target") for i in range(20)]
    folder = run / "refiner" / "refined" / name
    for i in range(20):
        refined = (target[i] * (1 + 0.2 * (-1) ** i)).astype(np.float32)
        write_exr(folder / "frames" / f"frame_{i:04d}.exr", refined)
        write_exr(folder / "deflickered" / f"frame_{i:04d}.exr", deflicker_frame(refined, coarse[i], data.exposure, DeflickerConfig()))
    atomic_write_text(folder / "refine.json", json.dumps({"sequence": name, "frames": 20, "frames_per_second": 2.0}))
    return run


def test_eval_scores_every_stage_with_one_protocol(tiny_run, tmp_path):
    from gra_mi.eval.protocol import EvalConfig, EvalInputs, evaluate, frame_selection

    report = evaluate(EvalInputs.from_run(tiny_run), tmp_path / "eval", EvalConfig(composite=True))
    stages = report["stages"]
    assert all(stages[s]["status"] == "done" for s in ("microfacet", "RelightNet", "refined", "deflickered")), stages
    split = next(iter(report["protocol"]["splits"]))
    assert report["protocol"]["splits"][split]["scored"] == [0, 10] == frame_selection(20, "every10")
    assert report["protocol"]["resolution"] == [80, 60] and report["problems"] == []
    least, most = report["protocol"]["splits"][split]["subject_pixels"]  # rows the truth's mask spans, scored frames
    assert 0 < least <= most <= 60
    refined, deflickered = stages["refined"]["splits"][split], stages["deflickered"]["splits"][split]
    # the stand-in flickers by ±20 %: its temporal error is far above the renders'; flicker correction removes most
    assert refined["temporal"] > 3 * stages["RelightNet"]["splits"][split]["temporal"]
    assert deflickered["temporal"] < 0.5 * refined["temporal"]
    assert deflickered["psnr"] > refined["psnr"] - 0.2
    for s in ("microfacet", "RelightNet"):
        m = stages[s]["splits"][split]
        assert m["psnr"] > 25 and 0 < m["flip"] < 0.3 and m["frames_scored"] == 2
    text = (tmp_path / "eval" / "eval.md").read_text()
    assert "| + flicker correction |" in text and "every 10th frame (the paper's protocol)" in text
    assert "pixels tall" in text
    for rel in ("eval.csv", "eval.json", f"contact_{split}.png", f"videos/{split}.mp4", f"videos/{split}_composite.mp4"):
        assert (tmp_path / "eval" / rel).is_file(), rel
    rows = (tmp_path / "eval" / "eval.csv").read_text().splitlines()
    assert rows[0].startswith("stage,split,status,psnr") and len(rows) == 5


def test_refiner_data_trains_on_relit_frames_and_passes_highlights_through(tiny_run):
    """The refiner's training sequences hold the capture's relit frames only (never a uniformly lit tracking frame),
    its selection sequence the held-out lighting on a training camera; a refiner that returns what it was shown (the
    crop clipped at its video range's white) delivers the stored whole frame exactly, highlights above that white
    included, and so does flicker correction of a frame that needs none."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.refiner.dataset import RefinerDataset

    data = RefinerDataset(tiny_run / "refiner" / "data")
    capture = Capture.load(tiny_run / "capture")
    kinds = {f.frame: f.kind for f in capture.frames}
    assert "uniform" in kinds.values()
    for entry in data.meta["sequences"]:
        if entry["split"] == "train":
            assert {kinds[f] for f in entry["capture_frames"]} <= {"envmap", "pattern"}, entry["name"]
    # the mix is chosen on the held-out lighting seen by the first training camera: not trained on, not evaluated
    held_out = {f.frame for f in capture.frames if f.split == "test"}
    (selection,) = [e for e in data.meta["sequences"] if e["split"] == "selection"]
    assert selection["camera"] == capture.train_cameras[0] and set(selection["capture_frames"]) <= held_out
    name = data.names("test")[0]
    stored = data.linear_frames(name, "coarse", 3, 4)[0].numpy()
    lit = stored.max(axis=-1) > 0
    data.exposure = 1.0 / float(np.median(stored[lit]))  # half the subject above white: many clipped pixels
    shown = np.clip(stored, 0.0, 1.0 / data.exposure)
    assert (stored > shown).mean() > 0.05
    np.testing.assert_allclose(data.delivered(name, 3, "coarse", shown), data.delivered(name, 3, "coarse"), atol=1e-6)
    # flicker correction passes them through too: a frame that is its own stable render comes back as it was
    from gra_mi.refiner.deflicker import DeflickerConfig, deflicker_frame

    np.testing.assert_allclose(deflicker_frame(stored, stored, data.exposure, DeflickerConfig()), stored, rtol=1e-5, atol=1e-6)


def test_eval_says_what_it_skipped_and_why(tiny_run, tmp_path, capsys):
    """Missing stages are skipped and named; a folder the user pointed to that cannot be scored is exit 2 with one
    line naming the file, while the other stages are still scored."""
    import shutil

    from gra_mi.cli import main
    from gra_mi.core.io import write_exr

    run = tiny_run
    assert main(["eval", "--capture", str(run / "capture"), "--fit", str(run / "fit"), "--out", str(tmp_path / "a")]) == 0
    table = (tmp_path / "a" / "eval.md").read_text()
    assert "| microfacet (fitted maps) | " in table and "+ RelightNet: skipped: --relightnet: no relightnet.json" in table

    # refined frames of another size: one line naming the file, exit 2, the other stages scored
    broken = tmp_path / "refined"
    shutil.copytree(run / "refiner" / "refined", broken)
    name = next(p.name for p in broken.iterdir())
    write_exr(broken / name / "frames" / "frame_0007.exr", np.zeros((30, 40, 3), np.float32))
    capsys.readouterr()
    assert main(["eval", str(run), "--refined", str(broken), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    errors = [line for line in err.splitlines() if "error" in line]
    assert len(errors) == 1 and "frame_0007.exr" in errors[0] and "40×30" in errors[0] and "Traceback" not in err
    report = json.loads((tmp_path / "b" / "eval.json").read_text())
    assert report["stages"]["RelightNet"]["splits"] and "skipped" in report["stages"]["refined"]["splits"][name]

    # LPIPS weights that are not LPIPS weights: named, exit 2, before any work (nothing evaluated, nothing written)
    (tmp_path / "w.pth").write_text("junk")
    assert main(["eval", str(run), "--lpips-weights", str(tmp_path / "w.pth"), "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "w.pth" in err and "--lpips-weights" in err
    assert not (tmp_path / "c").exists()
    assert main(["eval", str(run), "--frames", "every3"]) == 2
    assert "--frames" in capsys.readouterr().err
    assert main(["eval", "--fit", str(run / "fit")]) == 2
    assert "--capture" in capsys.readouterr().err


def test_refiner_data_shards_write_what_one_process_writes(tiny_run, tmp_path):
    """``--shard``: each shard makes its cameras' sequences; the last one writes the dataset, the same files as one
    process (the dataset-wide exposure and subject boxes included)."""
    from gra_mi.core.provenance import different_outputs
    from gra_mi.core.shard import Shard
    from gra_mi.refiner.data import CaptureSequencesConfig, dataset_from_capture

    def shard(i: int):
        return dataset_from_capture(
            tiny_run / "capture", tiny_run / "fit", tmp_path / "shards", relightnet_dir=tiny_run / "relightnet",
            config=CaptureSequencesConfig(scale=0.25, test_length=20), shard=Shard(i, 2), cache_dir=tmp_path / "cache",
        )  # fmt: skip

    assert shard(0) is None and not (tmp_path / "shards" / "dataset.json").exists()
    assert shard(1) is not None and not (tmp_path / "shards" / "parts").exists()
    one = tiny_run / "refiner" / "data"
    skip = lambda p: "cache" in p.parts  # noqa: E731
    assert not different_outputs(one, tmp_path / "shards", ignore=skip)


def test_refiner_data_of_a_capture_with_gaps_says_what_it_left_out(path_traced_fit, tmp_path):
    """A held-out camera that lost a frame mid-sequence: its refiner sequence is the longest unbroken run of the
    frames it has and dataset.json names the frames left out; a camera without the gap keeps every frame."""
    from gra_mi.capture.dataset import Capture
    from gra_mi.refiner.data import CaptureSequencesConfig, dataset_from_capture

    cap = tmp_path / "cap"
    shutil.copytree(path_traced_fit / "cap", cap)
    capture = Capture.load(cap)
    camera, test = capture.eval_cameras[0], [f.frame for f in capture.frames if f.split == "test"]
    lost = test[len(test) // 3]
    data = json.loads((cap / "capture.json").read_text())
    for entry in data["frames"]:
        entry["missing"] = [camera] if entry["frame"] == lost else []
    (cap / "capture.json").write_text(json.dumps(data))
    capture.image_path(camera, lost).unlink()
    config = CaptureSequencesConfig(scale=0.25, test_length=4, train_length=4)
    dataset = dataset_from_capture(cap, path_traced_fit / "fit", tmp_path / "data", config=config, cache_dir=tmp_path / "cache")
    entry = {e["name"]: e for e in dataset.meta["sequences"]}[f"test_{camera}"]
    after, before = test[test.index(lost) + 1 :], test[: test.index(lost)]
    run = after if len(after) > len(before) else before
    assert entry["left_out_frames"] == sorted(set(test) - set(run)) and set(entry["capture_frames"]) == set(run)
    other = {e["name"]: e for e in dataset.meta["sequences"]}[f"selection_{capture.train_cameras[0]}"]  # the same lighting
    assert "left_out_frames" not in other and set(other["capture_frames"]) == set(test)


def test_a_stage_that_delivers_its_input_is_marked_as_such():
    # The refiner at mix 0 and flicker correction of a steady video deliver their input: the headline table says so
    # in the row and in a note, instead of showing the input's numbers as the stage's own result.
    from gra_mi.eval.protocol import same_frames
    from gra_mi.eval.report import UNCHANGED, eval_table

    rng = np.random.default_rng(0)
    frames = [rng.uniform(0.1, 1.0, (8, 8, 4)).astype(np.float32) for _ in range(3)]
    assert same_frames(frames, [f.copy() for f in frames])
    assert same_frames([f * (1 + UNCHANGED / 2) for f in frames], frames)
    assert not same_frames([f * 1.01 for f in frames], frames) and not same_frames(frames[:2], frames)
    row = {"psnr": 30.0, "ssim": 0.99, "brightness": 0.0, "flip": 0.09, "temporal": 0.1, "frames_scored": 3}
    stages = {
        "microfacet": {"status": "done", "splits": {"cam06": dict(row)}},
        "RelightNet": {"status": "done", "splits": {"cam06": row | {"psnr": 31.0}}},
        "refined": {"status": "done", "splits": {"cam06": row | {"psnr": 31.0, "unchanged_from": "RelightNet"}}},
        "deflickered": {"status": "skipped: none", "splits": {}},
    }
    report = {"protocol": {"splits": {"cam06": {}}, "fvd": False, "lpips": False}, "stages": stages, "problems": []}
    lines, notes = eval_table(report)
    refined = next(line for line in lines if line.startswith("| + video refiner"))
    assert "= its input, unchanged" in refined
    assert not any("unchanged" in line for line in lines if line.startswith("| + RelightNet"))
    assert any("delivered its input (+ RelightNet) unchanged" in n and "mix is 0" in n for n in notes)
