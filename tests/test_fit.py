"""Synthetic captures and the material fit: recovery of known maps, resume, unseen texels, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from gra_mi.core.errors import GraMiInputError

from .test_cli import run_cli


@pytest.fixture(scope="module")
def onebounce_capture(tmp_path_factory):
    from gra_mi.capture.synthetic import generate_capture
    from gra_mi.core.runtime import choose_variant

    choose_variant("llvm_ad_rgb")
    out = tmp_path_factory.mktemp("capture")
    generate_capture(out, "tiny", "onebounce")
    return out


def test_capture_layout(onebounce_capture):
    from gra_mi.capture.dataset import Capture

    capture = Capture.load(onebounce_capture)
    train = [f for f in capture.frames if f.split == "train"]
    test = [f for f in capture.frames if f.split == "test"]
    assert [f.kind for f in train] == ["uniform", "envmap"] * (len(train) // 2), "interleaved uniform and relit frames"
    relit = [f.envmap for f in train if f.kind == "envmap"]
    assert len(set(relit)) == len(relit), "a different training envmap on each relit frame"
    assert all(f.envmap.startswith("envmaps/test/") for f in test) and test
    assert capture.eval_cameras and not set(capture.eval_cameras) & set(capture.train_cameras)
    for cam in capture.train_cameras + capture.eval_cameras:
        for f in capture.frames:
            assert capture.image_path(cam, f.frame).is_file()
    for name in ("albedo.exr", "roughness.exr"):
        assert (onebounce_capture / "gt" / name).is_file()


def test_fit_recovers_known_maps(onebounce_capture, tmp_path):
    from gra_mi.core.io import read_exr
    from gra_mi.fit.materials import FitConfig, run_fit

    result, report = run_fit(onebounce_capture, tmp_path / "fit", FitConfig(roughness_candidates=21))
    metrics = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert report.is_file() and (tmp_path / "fit" / "convergence.png").is_file()
    # Texels seen by at least three cameras: albedo within 2 % and roughness within 0.05 (medians).
    from gra_mi.render.atlas import UVAtlas
    from gra_mi.subject.sequence import load_sequence

    seq = load_sequence(onebounce_capture / "subject")
    atlas = UVAtlas.build(seq.faces, seq.uvs, result.albedo.shape[0])
    seen = result.observed_cameras >= 3
    assert seen.sum() > 100
    true_albedo = atlas.gather(read_exr(onebounce_capture / "gt" / "albedo.exr")[..., :3])[seen]
    true_rough = atlas.gather(read_exr(onebounce_capture / "gt" / "roughness.exr"))[seen, 0]
    fit_albedo = atlas.gather(result.albedo)[seen]
    fit_rough = atlas.gather(result.roughness)[seen, 0]
    assert np.median(np.abs(fit_albedo - true_albedo) / true_albedo) < 0.02
    assert np.median(np.abs(fit_rough - true_rough)) < 0.05
    assert metrics["never_observed"] == int(np.sum(result.observed_cameras == 0))
    # The L1 falls through the stages.
    losses = [c[1] for c in result.loss_curve if np.isfinite(c[1])]
    assert losses[-1] <= losses[0]


def test_fit_cli_resumes_from_checkpoint(onebounce_capture, tmp_path):
    out = run_cli("fit", str(onebounce_capture), "--out", str(tmp_path / "fit"), "--roughness-candidates", "5", "--irls-iterations", "1")
    assert out.returncode == 0, out.stderr
    assert (tmp_path / "fit" / "checkpoint.npz").is_file()
    first = (tmp_path / "fit" / "albedo.exr").read_bytes()
    again = run_cli("fit", str(onebounce_capture), "--out", str(tmp_path / "fit"), "--roughness-candidates", "5", "--irls-iterations", "1")
    assert again.returncode == 0
    assert (tmp_path / "fit" / "albedo.exr").read_bytes() == first


def test_unseen_texels_keep_defaults(onebounce_capture, tmp_path):
    from gra_mi.capture.dataset import Capture
    from gra_mi.fit.materials import DEFAULT_ALBEDO, DEFAULT_ROUGHNESS, FitConfig, MaterialFitter

    capture = Capture.load(onebounce_capture)
    capture.train_cameras = capture.train_cameras[:1]  # one camera sees only one side
    fitter = MaterialFitter(capture, FitConfig(roughness_candidates=3, irls_iterations=0))
    result = fitter.fit()
    unseen = result.observed_cameras == 0
    assert unseen.sum() > 0.3 * unseen.size
    np.testing.assert_allclose(fitter.atlas.gather(result.albedo)[unseen], DEFAULT_ALBEDO)
    np.testing.assert_allclose(fitter.atlas.gather(result.roughness)[unseen], DEFAULT_ROUGHNESS)


def test_bad_capture_folder(tmp_path):
    from gra_mi.capture.dataset import Capture

    with pytest.raises(GraMiInputError, match="not found"):
        Capture.load(tmp_path)
    (tmp_path / "capture.json").write_text("{")
    with pytest.raises(GraMiInputError, match="malformed JSON"):
        Capture.load(tmp_path)
    out = run_cli("fit", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"))
    assert out.returncode == 2 and "capture.json" in out.stderr


def test_path_traced_capture_and_fit(tmp_path):
    # The richer ground truth (path tracing, principled + sheen, wrinkles): the fit runs and explains most of it.
    out = run_cli("capture", "--preset", "tiny", "--out", str(tmp_path / "cap"))
    assert out.returncode == 0, out.stderr
    fit = run_cli("fit", str(tmp_path / "cap"), "--out", str(tmp_path / "fit"), "--roughness-candidates", "5")
    assert fit.returncode == 0, fit.stderr
    report = (tmp_path / "fit" / "fit_report.md").read_text()
    assert "albedo_mae" in report
    metrics = json.loads((tmp_path / "fit" / "fit.json").read_text())["metrics"]
    assert metrics["albedo_mae"] < 0.15
