"""The Dr.Jit → torch bridge and RelightNet: round trips, gradients, architecture, training, DDP, inference."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from gra_mi.core.shard import free_port
from gra_mi.relightnet.model import AttentionBlock, RelightNet, RelightNetConfig
from gra_mi.render.bridge import IN_CHANNELS

from .conftest import poison_optimizer_after
from .test_cli import run_cli


def test_bridge_round_trip_and_layout(variant):
    import drjit as dr
    import mitsuba as mi

    from gra_mi.render.atlas import UVAtlas
    from gra_mi.render.bridge import to_torch, uv_features
    from gra_mi.subject.sequence import tiny_subject

    t = mi.TensorXf(np.arange(24, dtype=np.float32).reshape(2, 3, 4))
    tt = to_torch(t)
    assert tt.shape == (2, 3, 4) and torch.equal(tt, torch.arange(24, dtype=torch.float32).reshape(2, 3, 4))
    back = mi.TensorXf(tt)
    assert np.array_equal(np.array(back), np.array(t))
    seq = tiny_subject(2)
    atlas = UVAtlas.build(seq.faces, seq.uvs, 32)
    m = atlas.num_texels
    parts = [np.full((m, 3), k, np.float32) for k in range(5)]
    features, mask = uv_features(atlas, parts[0], parts[1:4], parts[4])
    assert features.shape == (1, IN_CHANNELS, 32, 32) and mask.shape == (1, 1, 32, 32)
    inside = mask[0, 0] > 0
    for c, value in enumerate([0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 4]):
        assert torch.all(features[0, c][inside] == value)
    assert torch.all(features[0][:, ~inside] == 0)
    dr.eval()


def test_torch_loss_gradients_reach_the_textures(variant, tmp_path):
    import mitsuba as mi

    from gra_mi.render.bridge import torch_render
    from gra_mi.render.plugins import register_plugins

    from .test_onebounce import LEDS, make_scene

    register_plugins()
    scene = make_scene(tmp_path, "gra_microfacet", LEDS)
    params = mi.traverse(scene)
    keys = {"albedo": "subject.bsdf.albedo.data", "roughness": "subject.bsdf.roughness.data"}
    render = torch_render(scene, params, keys, mi.load_dict({"type": "gra_onebounce"}), spp=4)
    albedo = torch.tensor(np.array(params[keys["albedo"]]), requires_grad=True)
    rough = torch.tensor(np.array(params[keys["roughness"]]), requires_grad=True)
    image = render(albedo, rough)
    loss = image[..., :3].abs().mean()
    loss.backward()
    assert albedo.grad is not None and rough.grad is not None
    assert albedo.grad.abs().sum() > 0 and rough.grad.abs().sum() > 0
    # The albedo enters linearly: d loss / d (global scale) = loss_diffuse, checked by a finite difference.
    with torch.no_grad():
        eps = 1e-2
        up = render(albedo * (1 + eps), rough)[..., :3].abs().mean()
        down = render(albedo * (1 - eps), rough)[..., :3].abs().mean()
    fd = float((up - down) / (2 * eps))
    assert float((albedo.grad * albedo).sum().detach()) == pytest.approx(fd, rel=0.05)


def test_architecture_follows_the_paper():
    config = RelightNetConfig(resolution=256)
    model = RelightNet(config)
    levels = config.levels()
    assert levels == [128, 64, 32, 16], "the top level runs at R / patch"
    kinds = [isinstance(a, AttentionBlock) for a in model.down_attn]
    assert kinds == [r < 64 for r in levels], "attention exactly below 64²"
    assert all(a.cross_attn.num_heads == 4 for a in model.down_attn if isinstance(a, AttentionBlock))
    x = torch.rand(2, IN_CHANNELS, 256, 256)
    env = torch.rand(2, 3, 16, 32)
    y = model(x, env)
    assert y.shape == (2, 3, 256, 256)
    torch.testing.assert_close(y, x[:, :3], rtol=1e-6, atol=0), "zero-initialised head: at init RelightNet returns the coarse texture"
    with pytest.raises(ValueError):
        model(torch.randn(1, 12, 256, 256), env)


@pytest.mark.parametrize("patch", [1, 2, 4])
def test_exposure_invariant_and_non_negative(patch):
    """The same avatar under 10× the light gives 10× the texture, and no texel is ever negative, whatever the
    weights (random here, far from the identity)."""
    torch.manual_seed(patch)
    model = RelightNet(RelightNetConfig(resolution=64, patch=patch, lowest_resolution=8)).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.1)
    features = torch.cat([torch.rand(2, 3, 64, 64) * 2, torch.randn(2, 12, 64, 64)], dim=1)
    mask = (torch.rand(1, 1, 64, 64) > 0.3).float().expand(2, -1, -1, -1)
    env = torch.rand(2, 3, 16, 32) * torch.tensor([1.0, 1e4])[:, None, None, None]  # one with a sun-like range
    with torch.no_grad():
        y = model(features, env, mask)
        brighter = features.clone()
        brighter[:, :3] *= 10
        y10 = model(brighter, env * 10, mask)
    assert y.min() >= 0 and y10.min() >= 0
    assert (y > 0).float().mean() > 0.2, "the random network is not simply clamped to black"
    torch.testing.assert_close(y10, 10 * y, rtol=1e-3, atol=1e-4)  # atol: texels where the max(·, 0) cancels
    assert torch.all(y[mask.expand(-1, 3, -1, -1) == 0] == 0), "texels outside the atlas stay empty"


def test_every_input_reaches_the_output():
    """Each of the 15 channels and the envmap change the output of a trained-like (non-zero head) network."""
    torch.manual_seed(0)
    model = RelightNet(RelightNetConfig(resolution=64, lowest_resolution=8)).eval()
    with torch.no_grad():
        model.head.weight.normal_(0, 0.05)
    features = torch.cat([torch.rand(1, 3, 64, 64) + 0.1, torch.randn(1, 12, 64, 64)], dim=1).requires_grad_()
    env = (torch.rand(1, 3, 16, 32) + 0.1).requires_grad_()
    model(features, env).sum().backward()
    per_channel = features.grad.abs().sum(dim=(0, 2, 3))
    assert torch.all(per_channel > 0), per_channel
    assert env.grad.abs().sum() > 0


def test_weights_round_trip(tmp_path):
    model = RelightNet(RelightNetConfig(resolution=32, patch=1))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_()
    model.save(tmp_path)
    assert json.loads((tmp_path / "relightnet.json").read_text())["resolution"] == 32
    again = RelightNet.load(tmp_path)
    x, env = torch.rand(1, IN_CHANNELS, 32, 32), torch.rand(1, 3, 16, 32)
    model.eval()
    assert torch.allclose(model(x, env), again(x, env))


def test_weights_of_another_format_or_config_are_refused(tmp_path):
    from gra_mi.core.errors import GraMiInputError

    RelightNet(RelightNetConfig(resolution=32, patch=1)).save(tmp_path)
    config = json.loads((tmp_path / "relightnet.json").read_text())
    (tmp_path / "relightnet.json").write_text(json.dumps({k: v for k, v in config.items() if k not in ("format", "patch")}))
    with pytest.raises(GraMiInputError, match="format.*gra-mi-relightnet/2"):
        RelightNet.load(tmp_path)
    (tmp_path / "relightnet.json").write_text(json.dumps({**config, "base_channels": 8}))
    with pytest.raises(GraMiInputError, match="relightnet.safetensors.*cannot load"):
        RelightNet.load(tmp_path)
    (tmp_path / "relightnet.json").write_text(json.dumps({**config, "colour": 1}))
    with pytest.raises(GraMiInputError, match="unknown keys"):
        RelightNet.load(tmp_path)
    for gain in (float("nan"), -1.0, 0.0, "2"):
        (tmp_path / "relightnet.json").write_text(json.dumps({**config, "output_gain": gain}))
        with pytest.raises(GraMiInputError, match="output_gain"):
            RelightNet.load(tmp_path)


@pytest.fixture(scope="module")
def capture_and_fit(path_traced_fit):
    """The tiny path-traced capture (cap/) and its fit (fit/), shared with the other modules (tests/conftest.py)."""
    return path_traced_fit


def test_training_lowers_the_loss_validates_and_resumes(capture_and_fit, tmp_path):
    root = capture_and_fit
    out = run_cli(
        "train-relightnet",
        str(root / "cap"),
        "--fit",
        str(root / "fit"),
        "--out",
        str(tmp_path / "rn"),
        "--steps",
        "60",
        "--lr",
        "3e-3",
        "--checkpoint-every",
        "20",
    )
    assert out.returncode == 0, out.stderr
    rows = [line.split(",") for line in (tmp_path / "rn" / "train_log.csv").read_text().splitlines()[1:]]
    losses = [float(r[1]) for r in rows]
    assert np.mean(losses[-2:]) < losses[0], "the loss falls"
    report = json.loads((tmp_path / "rn" / "validation.json").read_text())
    summary = report["splits"]
    assert {"train", "novel view", "novel view (selection)", "novel lighting (envmap)"} <= set(summary)
    for split in summary.values():
        assert np.isfinite(split["relightnet"]["psnr"]) and 0 < split["relightnet"]["ssim"] <= 1
        assert np.isfinite(split["relightnet"]["brightness"])
    # Validated every 100 steps or at the end, from step 0 (the microfacet render) on; the kept weights score best.
    scores = {row["step"]: row["score"] for row in report["validation"]}
    assert sorted(scores) == [0, 60] and scores[report["kept_step"]] == min(scores.values())
    # One output gain gives the training views their total light back (L1 alone learns medians: a few % too dark).
    gain = json.loads((tmp_path / "rn" / "relightnet.json").read_text())["output_gain"]
    assert gain == report["output_gain"] and (0.5 < gain < 2.0) and (gain != 1.0 or report["kept_step"] == 0)
    if report["kept_step"] > 0:
        assert abs(summary["train"]["relightnet"]["brightness"]) < 0.02
    for name in ("relightnet.safetensors", "relightnet.json", "loss.png", "grid.png", "validation.md", "checkpoint.pt"):
        assert (tmp_path / "rn" / name).exists(), name
    assert (tmp_path / "rn" / "validation.png").exists() and (tmp_path / "rn" / "validation_log.csv").exists()
    # Other options into the same folder: refused, naming the folder's provenance and the option.
    other = run_cli("train-relightnet", str(root / "cap"), "--fit", str(root / "fit"), "--out", str(tmp_path / "rn"), "--steps", "70")
    assert other.returncode == 2 and "provenance.json" in other.stderr and "lr: 0.003 then" in other.stderr, other.stderr
    # Resume: more steps continue from the checkpoint (the log keeps its earlier rows).
    again = run_cli(
        "train-relightnet",
        str(root / "cap"),
        "--fit",
        str(root / "fit"),
        "--out",
        str(tmp_path / "rn"),
        "--steps",
        "70",
        "--lr",
        "3e-3",
        "--checkpoint-every",
        "20",
    )
    assert again.returncode == 0, again.stderr
    steps = [int(r.split(",")[0]) for r in (tmp_path / "rn" / "train_log.csv").read_text().splitlines()[1:]]
    assert steps[0] == 10 and steps[-1] == 70
    # Inference through gra-mi relight.
    r = run_cli(
        "relight", str(root / "cap" / "scene.xml"), "--frames", "0", "--olat", "5", "--stage", "relightnet", "--relightnet", str(tmp_path / "rn"),
        "--albedo", str(root / "fit" / "albedo.exr"), "--roughness", str(root / "fit" / "roughness.exr"), "--out", str(tmp_path / "relit"),
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "relit" / "olat005" / "cam00" / "frame_0000.exr").exists()


def test_a_run_that_makes_images_worse_ships_the_microfacet_render(capture_and_fit, tmp_path):
    """A learning rate far too high wrecks the network: it either gets worse or diverges to NaN (which of the two
    depends on the fit's last bits, which thread order moves). Either way validation keeps step 0, whose output is
    the coarse render, and a divergence is recorded with its step."""
    root = capture_and_fit
    args = ["--out", str(tmp_path / "bad"), "--steps", "20", "--lr", "0.5", "--weight-decay", "0", "--validate-every", "10"]
    out = run_cli("train-relightnet", str(root / "cap"), "--fit", str(root / "fit"), *args)
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "bad" / "validation.json").read_text())
    scores = {row["step"]: row["score"] for row in report["validation"]}
    assert all(np.isfinite(v) for v in scores.values()), "a non-finite validation is never logged as a score"
    if report["diverged"] is None:
        assert sorted(scores) == [0, 10, 20] and min(scores[10], scores[20]) > scores[0], "the run did make things worse"
    else:
        assert 0 < report["diverged"]["step"] <= 20 and "diverged" in out.stderr
        assert all(step < report["diverged"]["step"] for step in scores)
    assert report["kept_step"] == 0
    for split in report["splits"].values():
        assert split["relightnet"]["psnr"] == pytest.approx(split["microfacet"]["psnr"], abs=1e-3)
    assert "microfacet render itself" in (tmp_path / "bad" / "validation.md").read_text()


@pytest.mark.slow
def test_ddp_training_with_two_processes(capture_and_fit, tmp_path):
    root = capture_and_fit
    env = {**os.environ, "GRA_MI_QUIET": "1", "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", str(free_port()), "-m", "gra_mi.cli",
        "train-relightnet", str(root / "cap"), "--fit", str(root / "fit"), "--out", str(tmp_path / "ddp"), "--steps", "6", "--checkpoint-every", "3",
    ]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "ddp" / "relightnet.safetensors").exists() and (tmp_path / "ddp" / "validation.json").exists()


def test_divergence_stops_training_keeps_finite_weights_and_is_recorded(capture_and_fit, tmp_path, monkeypatch):
    """A run whose weights become NaN after the 6th update stops at step 6 (the loss is NaN there), keeps the best
    finite validation, records where it diverged (validation.json, validation.md, the checkpoint) and refuses to be
    continued with more steps."""
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.relightnet.model import RelightNet
    from gra_mi.relightnet.train import TrainConfig, train_relightnet

    calls = poison_optimizer_after(monkeypatch, 6)
    root, out = capture_and_fit, tmp_path / "nan"
    config = TrainConfig(steps=12, lr=1e-3, validate_every=4, checkpoint_every=4)
    train_relightnet(root / "cap", root / "fit", out, config)
    report = json.loads((out / "validation.json").read_text())
    assert report["diverged"] == {"step": 6, "what": "the training loss"}
    assert [row["step"] for row in report["validation"]] == [0, 4] and report["kept_step"] in (0, 4)
    assert len(calls) == 6, "no update after the non-finite loss"
    model = RelightNet.load(out)  # refuses non-finite weights
    assert all(bool(torch.isfinite(p).all()) for p in model.parameters())
    assert "Training diverged at step 6" in (out / "validation.md").read_text()
    assert torch.load(out / "checkpoint.pt", weights_only=False)["divergence"]["step"] == 6
    with pytest.raises(GraMiInputError, match="diverged at step 6"):
        train_relightnet(root / "cap", root / "fit", out, TrainConfig(steps=16, lr=1e-3, validate_every=4, checkpoint_every=4))


def test_training_views_are_held_up_to_a_quarter_of_the_memory():
    """The demo's 384 training views (2.3 GB) are held, not re-rendered at every draw; never less than 2 GiB."""
    import os

    from gra_mi.relightnet.train import held_training_bytes

    total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    assert held_training_bytes() == max(2 << 30, total // 4)


def test_the_views_eval_scores_never_choose_the_weights():
    """Selection views under the test lighting come from the training camera: the held-out cameras' test frames are
    `gra-mi eval`'s headline, so no training choice may look at them (novel views of training frames may)."""
    from gra_mi.relightnet.data import Sample
    from gra_mi.relightnet.train import mark_selection

    t = torch.zeros(1)
    views = [
        Sample(f"{cam}/frame_{f:04d}", split, t, t, t, t, t, t)
        for split, frames in (("novel view", range(0, 8)), ("novel lighting (envmap)", range(8, 16)))
        for f in frames
        for cam in ("cam00", "cam06", "cam07")
    ]
    mark_selection(views, 8, scored_cameras=("cam06", "cam07"))
    chosen = [(v.split, v.camera) for v in views if v.selection]
    lighting = [cam for split, cam in chosen if split == "novel lighting (envmap)"]
    assert lighting and set(lighting) == {"cam00"} and len(lighting) == 4  # at most half of the 8 candidates
    assert {cam for split, cam in chosen if split == "novel view"} >= {"cam06", "cam07"}


def test_the_display_loss_weighs_an_error_by_what_it_looks_like():
    """Equal linear errors: in a shadow (1/16 of the exposure) the display loss counts it ≈ 16^(1 − 1/2.2) ≈ 4.5×
    more than in the light (a display's tone curve is steeper in the dark, as the sRGB values the metrics compare),
    the linear loss the same; a perfect image scores 0 either way, and the loss is a mean over the subject's pixels."""
    from gra_mi.relightnet.train import normalised_l1

    pixels = torch.ones(1, 1, 1, 2)
    scale = torch.ones(1, 1, 1, 1)
    target = torch.tensor([1 / 16, 1.0]).reshape(1, 1, 1, 2).expand(1, 3, 1, 2)
    delta = 0.01
    shadow_error = target + torch.tensor([delta, 0.0]).reshape(1, 1, 1, 2)
    light_error = target + torch.tensor([0.0, delta]).reshape(1, 1, 1, 2)
    for encoding in ("display", "linear"):
        assert float(normalised_l1(target, target, pixels, scale, encoding)) == 0.0
    assert float(normalised_l1(shadow_error, target, pixels, scale, "linear")) == pytest.approx(delta / 2)
    assert float(normalised_l1(light_error, target, pixels, scale, "linear")) == pytest.approx(delta / 2)
    ratio = float(normalised_l1(shadow_error, target, pixels, scale, "display")) / float(
        normalised_l1(light_error, target, pixels, scale, "display")
    )
    curve = lambda x: x ** (1 / 2.2)  # noqa: E731 — the slope ratio, from finite differences of the curve itself
    expected = (curve(1 / 16 + delta) - curve(1 / 16)) / (curve(1 + delta) - curve(1.0))
    assert ratio == pytest.approx(expected, rel=0.02) and 4.0 < ratio < 5.0


def test_an_unknown_loss_encoding_is_refused():
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.relightnet.train import TrainConfig

    with pytest.raises(GraMiParameterError, match="loss"):
        TrainConfig(loss="perceptual").validate()


def test_training_on_fewer_lightings_keeps_every_uniformly_lit_frame():
    """`--training-lightings K`: the lit frames of K of the capture's lightings (evenly spaced), every camera of
    them, and every uniformly lit frame; more than the capture has is refused, naming the option."""
    from gra_mi.capture.dataset import FrameLighting
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.relightnet.train import of_lightings

    frames = [
        FrameLighting(t, "train", 0, "uniform" if t % 3 == 0 else "envmap", None if t % 3 == 0 else f"env/{t}.exr") for t in range(12)
    ]
    jobs = [(f, cam, "train") for f in frames for cam in ("cam00", "cam01")]
    assert of_lightings(jobs, None) == jobs
    kept = of_lightings(jobs, 2)
    assert {j[0].frame for j in kept if j[0].kind == "uniform"} == {0, 3, 6, 9}
    lit = sorted({j[0].envmap for j in kept if j[0].kind == "envmap"})
    assert lit == ["env/1.exr", "env/11.exr"] and len(kept) == 2 * (4 + 2)
    assert of_lightings(jobs, 8) == jobs
    with pytest.raises(GraMiParameterError, match="training_lightings"):
        of_lightings(jobs, 9)
