"""The video refiner: diffusers' WAN2.1-VACE + LoRA + atemporal envmap attention, training and rollouts (issue 7)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gra_mi.core.errors import GraMiInputError, GraMiParameterError
from gra_mi.core.shard import free_port
from gra_mi.refiner.conditioning import latent_frames
from gra_mi.refiner.config import TRANSFORMER_CONFIGS, RefinerConfig
from gra_mi.refiner.dataset import RefinerDataset, env_to_video, image_to_video, video_to_image
from gra_mi.refiner.flow import noisy_latent, recycling_residuals, sampling_sigmas, velocity_target
from gra_mi.refiner.model import AtemporalCrossAttention, VideoRefiner
from gra_mi.refiner.synthetic import synthetic_dataset
from gra_mi.refiner.train import ErrorBank, RefinerTrainConfig, augment, pan_zoom, train_refiner, validation_loss

from .conftest import poison_optimizer_after

torch.set_num_threads(2)


def _inputs(model: VideoRefiner, frames: int = 17, size: int = 32, seeded: int = 0, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    video = torch.rand(1, 3, frames, size, size, generator=g) * 2 - 1
    mask = torch.ones(1, 1, frames, size, size)
    mask[:, :, :seeded] = 0
    ref = torch.rand(1, 3, size, size, generator=g) * 2 - 1
    control = model.control(video, mask, ref)
    env = model.env_tokens(
        model.env_latents(torch.rand(1, 3, frames, 16, 32, generator=g) * 2 - 1, torch.rand(1, 3, 16, 32, generator=g) * 2 - 1)
    )
    latents = torch.randn(1, 16, *control.shape[2:], generator=g)
    return latents, control, env, (video, mask, ref)


@pytest.fixture(scope="module")
def model():
    return VideoRefiner(RefinerConfig(prior=False))  # random DiT weights, seeded: the stock model is rebuilt below


# A stand-in for Wan2.1's VAE with the tiny transformer's layout (4× in space, so 16 + 16 + 4 × 4 VACE channels).
WAN_VAE_STANDIN = dict(
    base_dim=8, z_dim=16, dim_mult=[1, 1, 1], num_res_blocks=1, attn_scales=[], temperal_downsample=[True, True], scale_factor_spatial=4
)


# --------------------------------------------------------------------------------------------------------------
# Model structure
# --------------------------------------------------------------------------------------------------------------


def test_stock_equivalence_at_init(model):
    """Zero-initialised envmap attention and LoRA: the refiner equals diffusers' stock transformer, bit for bit."""
    from diffusers import WanVACETransformer3DModel

    torch.manual_seed(model.config.seed)
    stock = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"]).eval()  # same seed: the same random weights
    latents, control, env, _ = _inputs(model)
    sigma = torch.tensor([0.7])
    with torch.no_grad():
        ours = model(latents, sigma, control, env)
        theirs = stock(latents, sigma * 1000, model.prompt_embeds, control_hidden_states=control, return_dict=False)[0]
    assert torch.equal(ours, theirs)
    # ...and the envmap really enters once the attention has weights
    with torch.no_grad():
        for attn in model.env_attention.values():
            attn.to_out.weight.normal_(std=0.1)
        changed = model(latents, sigma, control, env)
        for attn in model.env_attention.values():
            attn.to_out.weight.zero_()
    assert (changed - ours).abs().max() > 1e-4


def test_lora_and_trainable_parts(model):
    names = {n for n, p in model.named_parameters() if p.requires_grad}
    assert any(n.startswith("transformer.blocks.") and "lora_A" in n for n in names)
    assert not any(n.startswith("transformer.vace_blocks.") and "lora_" in n for n in names), "LoRA must not wrap the VACE blocks"
    assert any(n.startswith("transformer.vace_blocks.") for n in names), "the VACE adapter is fully trainable"
    assert any(n.startswith("env_attention.") for n in names) and any(n.startswith("env_mlp.") for n in names)
    frozen = {n for n, p in model.named_parameters() if not p.requires_grad}
    assert any(n.endswith("attn1.to_q.base_layer.weight") for n in frozen), "the main DiT weights stay frozen"
    assert not any(n.startswith("vae.") for n in names)
    lora = [m for n, m in model.named_modules() if n.endswith("blocks.0.attn1.to_q")][0]
    assert lora.r["default"] == 32


def test_atemporal_attention_layer():
    torch.manual_seed(0)
    attn = AtemporalCrossAttention(24, 2)
    torch.nn.init.normal_(attn.to_out.weight, std=0.2)
    frames, n, m = 5, 6, 4
    tokens = torch.randn(1, frames * n, 24)
    env = torch.randn(1, frames, m, 24)
    base = attn(tokens, env)
    env2 = env.clone()
    env2[:, 2] += torch.randn(m, 24)
    diff = (attn(tokens, env2) - base).abs().view(frames, n, 24).amax(dim=(1, 2))
    assert diff[2] > 1e-3
    assert torch.all(diff[[0, 1, 3, 4]] == 0), diff


def test_atemporal_in_the_model():
    """With envmap attention after the last block only, a change of envmap latent frame k changes output frame k only."""
    model = VideoRefiner(RefinerConfig(env_blocks=[3]))
    with torch.no_grad():
        model.env_attention["3"].to_out.weight.normal_(std=0.2)
    latents, control, env, _ = _inputs(model)
    with torch.no_grad():
        base = model(latents, torch.tensor([0.5]), control, env)
        env2 = env.clone()
        env2[:, 3] += 1.0
        out = model(latents, torch.tensor([0.5]), control, env2)
    per_frame = (out - base).abs().amax(dim=(0, 1, 3, 4))
    assert per_frame[3] > 1e-4
    assert torch.all(per_frame[[0, 1, 2, 4, 5]] == 0), per_frame


def test_prepared_for_inference_is_the_same_network(tmp_path):
    """Folding a trained LoRA into the DiT changes nothing but rounding; a prepared model refuses to be saved."""
    model = VideoRefiner(RefinerConfig())
    with torch.no_grad():
        for name, param in model.named_parameters():
            if "lora_B" in name or (name.startswith("env_attention.") and name.endswith("to_out.weight")):
                param.normal_(std=0.05)
    latents, control, env, _ = _inputs(model)
    sigma = torch.tensor([0.6])
    with torch.no_grad():
        trained = model(latents, sigma, control, env)
        model.transformer.disable_adapters()
        without_lora = model(latents, sigma, control, env)
        model.transformer.enable_adapters()
        prepared = model.prepare_for_inference(fuse_lora=True)(latents, sigma, control, env)
    assert (trained - without_lora).abs().max() > 1e-3, "the LoRA must matter for this test to mean anything"
    torch.testing.assert_close(prepared, trained, atol=2e-5, rtol=1e-4)  # float32: folding is exact up to rounding
    assert all(m.merged for n, m in model.transformer.named_modules() if hasattr(m, "merged") and "lora" not in n)
    with pytest.raises(RuntimeError, match="prepared for inference"):
        model.save(tmp_path / "m")


def test_envmap_layers_run_in_the_dits_dtype():
    """Real sizes run the DiT in bfloat16 while the new layers train in float32: the residual comes back in the DiT's dtype."""
    attn = AtemporalCrossAttention(24, 2)
    torch.nn.init.normal_(attn.to_out.weight, std=0.2)
    tokens, env = torch.randn(1, 10, 24), torch.randn(1, 2, 3, 24)
    out32 = attn(tokens, env)
    out16 = attn(tokens.bfloat16(), env)
    assert out16.dtype == torch.bfloat16
    torch.testing.assert_close(out16.float(), out32, atol=0.05, rtol=0.05)
    attn.bfloat16()
    assert attn(tokens.bfloat16(), env).dtype == torch.bfloat16


def test_control_and_mask_layout_match_diffusers_pipeline():
    """On a diffusers AutoencoderKLWan of the tiny transformer's layout (the pipeline reads its config)."""
    from diffusers import AutoencoderKLWan, FlowMatchEulerDiscreteScheduler, WanVACEPipeline, WanVACETransformer3DModel

    torch.manual_seed(0)
    backbone = (WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"]), AutoencoderKLWan(**WAN_VAE_STANDIN))
    model = VideoRefiner(RefinerConfig(prior=False), backbone=backbone)

    pipe = WanVACEPipeline(
        tokenizer=None, text_encoder=None, vae=model.vae, scheduler=FlowMatchEulerDiscreteScheduler(), transformer=model.transformer
    )
    for seeded in (0, 5):
        _, control, _, (video, mask, ref) = _inputs(model, seeded=seeded, seed=seeded)
        mask3 = mask.expand(1, 3, *mask.shape[2:])
        expected = torch.cat(
            [pipe.prepare_video_latents(video, mask3, [[ref[0]]], None, torch.device("cpu")), pipe.prepare_masks(mask3, [[ref[0]]])], dim=1
        )
        assert control.shape == expected.shape == (1, 48, 6, 8, 8)
        torch.testing.assert_close(control, expected, atol=1e-5, rtol=1e-5)
        # the reference is latent frame 0 with a zero mask; 5 seed frames leave one latent mask frame inactive (nearest-exact)
        frame_mask = control[0, 32:].amax(dim=(0, 2, 3))
        assert frame_mask.tolist() == ([0, 1, 1, 1, 1, 1] if seeded == 0 else [0, 0, 1, 1, 1, 1])


# --------------------------------------------------------------------------------------------------------------
# Conventions
# --------------------------------------------------------------------------------------------------------------


def test_flow_sign_conventions():
    g = torch.Generator().manual_seed(1)
    z1, z0 = torch.randn(2, 3, generator=g), torch.randn(2, 3, generator=g)  # paper: z1 data, z0 noise
    sigma = torch.tensor(0.3)
    s = 1 - sigma
    assert torch.allclose(noisy_latent(z1, z0, sigma), (1 - s) * z0 + s * z1)  # paper's linear path
    assert torch.allclose(velocity_target(z1, z0), -(z1 - z0))  # Wan's v = ε − x₀ is minus the paper's target
    # residuals: the paper's literal definitions (Eq. 13-14) equal the Wan-form shortcut
    v_hat_wan = torch.randn(2, 3, generator=g)
    z_s = noisy_latent(z1, z0, sigma)
    v_rcy, v_hat = z1 - z0, -v_hat_wan
    e0 = (z_s - s * v_hat) - (z_s - s * v_rcy)
    e1 = (z_s + (1 - s) * v_hat) - (z_s + (1 - s) * v_rcy)
    e_noise, e_data = recycling_residuals(v_hat_wan, velocity_target(z1, z0), sigma)
    assert torch.allclose(e_noise, e0) and torch.allclose(e_data, e1)


def test_euler_sampler_matches_diffusers_scheduler_and_reaches_the_data():
    from diffusers import FlowMatchEulerDiscreteScheduler

    from gra_mi.refiner.flow import euler_sample

    for steps, shift in ((10, 1.0), (20, 3.0), (7, 5.0)):
        sched = FlowMatchEulerDiscreteScheduler(num_train_timesteps=1000, shift=shift)
        sched.set_timesteps(steps)
        torch.testing.assert_close(sampling_sigmas(steps, shift).float(), sched.sigmas.float(), atol=1e-6, rtol=1e-6)

    class Exact(torch.nn.Module):  # the exact velocity field of a single data point x₀: v = (x − x₀)/σ
        def __init__(self, x0):
            super().__init__()
            self.x0 = x0

        device = torch.device("cpu")

        def __call__(self, x, sigma, control, env):
            return (x - self.x0) / sigma

    x0 = torch.randn(1, 16, 2, 2, 2)
    out = euler_sample(Exact(x0), x0.shape, None, None, steps=8, shift=3.0, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(out, x0, atol=1e-5, rtol=1e-5)


def test_pinned_latents_follow_their_exact_flow_path():
    """Given latents (reference, seed frames) are fed to the model on the straight path (1 − σ)·z + σ·ε and come out
    exactly; a model that already reproduces them exactly sees the same inputs pinned or not."""
    from gra_mi.refiner.flow import euler_sample

    x0 = torch.randn(1, 16, 5, 2, 2)
    seen = []

    class Exact(torch.nn.Module):
        device = torch.device("cpu")

        def __call__(self, x, sigma, control, env):
            seen.append((x.clone(), float(sigma)))
            return (x - x0) / sigma

    noise = torch.randn(x0.shape, generator=torch.Generator().manual_seed(3))
    known = torch.randn(1, 16, 2, 2, 2)  # not what the model would produce: pinning must win
    out = euler_sample(Exact(), x0.shape, None, None, steps=6, shift=3.0, generator=torch.Generator().manual_seed(3), known=known)
    torch.testing.assert_close(out[:, :, :2], known)
    torch.testing.assert_close(out[:, :, 2:], x0[:, :, 2:], atol=1e-5, rtol=1e-5)
    for x, sigma in seen:
        torch.testing.assert_close(x[:, :, :2], (1 - sigma) * known + sigma * noise[:, :, :2])
    seen.clear()
    euler_sample(Exact(), x0.shape, None, None, steps=6, shift=3.0, generator=torch.Generator().manual_seed(3))
    free = list(seen)
    seen.clear()
    euler_sample(Exact(), x0.shape, None, None, steps=6, shift=3.0, generator=torch.Generator().manual_seed(3), known=x0[:, :, :2])
    for (x_free, _), (x_pinned, _) in zip(free, seen, strict=True):
        torch.testing.assert_close(x_pinned, x_free, atol=1e-5, rtol=1e-5)


def test_tone_mapping_round_trip():
    x = torch.linspace(0, 1.2, 50)
    back = video_to_image(image_to_video(x, 1.0), 1.0)
    torch.testing.assert_close(back[x <= 1], x[x <= 1], atol=1e-5, rtol=1e-4)
    assert env_to_video(torch.tensor([0.0, 1e9]), 1.0).tolist() == [-1.0, 1.0]


# --------------------------------------------------------------------------------------------------------------
# Training pieces
# --------------------------------------------------------------------------------------------------------------


def test_error_bank_bounds():
    bank = ErrorBank(levels=5, per_level=3)
    rng = np.random.default_rng(0)
    shape = torch.Size([1, 16, 3, 4, 4])
    for i in range(100):
        bank.add(i % 5, torch.full(shape, float(i)), rng)
    assert len(bank) == 15 and all(len(v) <= 3 for v in bank.entries.values())
    assert bank.nbytes() <= bank.max_nbytes(shape) == 5 * 3 * int(np.prod(shape)) * 2
    assert all(t.dtype == torch.float16 for v in bank.entries.values() for t in v)
    only = ErrorBank(levels=50, per_level=2)
    only.add(40, torch.ones(shape), rng)
    assert torch.equal(only.sample(3, shape, rng), torch.ones(shape))  # the nearest filled level
    assert only.sample(3, torch.Size([1, 16, 2, 4, 4]), rng) is None  # never a residual of another shape


def test_augmentations():
    rng = np.random.default_rng(0)
    video = torch.rand(3, 9, 16, 16) * 2 - 1
    torch.testing.assert_close(pan_zoom(video, 1.0, (0.0, 0.0)), video, atol=1e-5, rtol=0)
    moved = pan_zoom(video, 1.2, (0.1, 0.0))
    torch.testing.assert_close(moved[:, 0], video[:, 0], atol=1e-5, rtol=0)  # the move grows from the first frame
    assert (moved[:, -1] - video[:, -1]).abs().mean() > 0.05
    window = {
        "coarse": video,
        "target": video.clone(),
        "env": torch.rand(3, 9, 4, 8),
        "reference": video[:, 0],
        "reference_env": torch.rand(3, 4, 8),
    }
    config = RefinerTrainConfig(static_clip_prob=1.0, static_motion_prob=1.0)
    out, what = augment(window, config, rng)
    assert what == "static+pan/zoom"
    torch.testing.assert_close(out["coarse"], out["target"])  # the same move on input and ground truth
    assert torch.equal(out["env"][:, 0], out["env"][:, -1])  # a static clip: one frame's lighting throughout


# --------------------------------------------------------------------------------------------------------------
# Training, adaptation and rollouts on synthetic clips
# --------------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("refiner")
    data = synthetic_dataset(root / "data", {0: (3, 1), 1: (10, 0)}, frames=17, height=32, width=32, env_height=16, test_frames=41)
    only_a = root / "data_a"
    meta = json.loads((root / "data" / "dataset.json").read_text())
    meta_a = dict(meta, sequences=[s for s in meta["sequences"] if s["subject"] == "synthetic0"])
    meta_b = dict(meta, sequences=[s for s in meta["sequences"] if s["subject"] == "synthetic1"])
    for folder, m in ((only_a, meta_a), (root / "data_b", meta_b)):
        folder.mkdir()
        (folder / "sequences").symlink_to(root / "data" / "sequences")
        (folder / "dataset.json").write_text(json.dumps(m))
    start = validation_loss(VideoRefiner(RefinerConfig()), RefinerDataset(only_a))
    config = RefinerTrainConfig(steps=300, lr=5e-3, checkpoint_every=1000, log_every=25, static_clip_prob=0, dynamic_motion_prob=0)
    train_refiner(only_a, root / "model", config)
    return {"root": root, "data": data, "a": RefinerDataset(only_a), "b": RefinerDataset(root / "data_b"), "start": start}


def test_tiny_model_overfits_a_tiny_clip_set(trained):
    model = VideoRefiner.load(trained["root"] / "model")
    end = validation_loss(model, trained["a"])
    assert end < 0.8 * trained["start"], (trained["start"], end)  # from the prior: 1.97 → 1.50 measured
    summary = json.loads((trained["root"] / "model" / "train.json").read_text())
    bank = summary["error_bank"]
    assert 0 < bank["residuals"] <= 2 * 50 * 32  # both banks, bounded by levels × per level
    assert (trained["root"] / "model" / "loss.png").is_file()


def test_rollout_of_three_windows(trained):
    from gra_mi.refiner.infer import Joins, refine_to_folder, rollout, window_starts

    assert window_starts(41, 17, 5) == [0, 12, 24]
    assert window_starts(17, 17, 5) == [0]
    model = VideoRefiner.load(trained["root"] / "model")
    frames = list(rollout(model, trained["a"], "s0_test00", steps=4, frames=30))  # the last window is padded, then cut
    assert [f.index for f in frames] == list(range(30)) and [f.window for f in frames][-1] == 2
    out = trained["root"] / "refined"
    summary = refine_to_folder(trained["root"] / "model", trained["root"] / "data_a", "s0_test00", out, steps=6)
    assert summary["frames"] == 41 and summary["windows"] == 3
    assert len(list((out / "frames").glob("*.exr"))) == 41 and (out / "refined.mp4").stat().st_size > 0
    # The seam measures in refine.json are what the frames show (same seed → same frames).
    frames = list(rollout(model, trained["a"], "s0_test00", steps=6))
    video = torch.stack([f.video for f in frames])
    change = ((video[1:] - video[:-1]).abs().mean(dim=(1, 2, 3)) / 2).numpy()  # change[i - 1]: into frame i
    firsts = [i for i in range(1, len(frames)) if frames[i].window != frames[i - 1].window]
    assert firsts == [12, 24]  # the cross-faded hand-off frames belong to the new window
    join = [i + j for i in firsts for j in range(6)]
    assert summary["seam_jump"] == pytest.approx(float(np.mean(change[np.array(firsts) - 1])), abs=2e-3)
    assert summary["join_frame_change"] == pytest.approx(float(np.mean(change[np.array(join) - 1])), abs=2e-3)
    inner = np.delete(change, np.array(join) - 1)
    assert summary["inner_frame_change"] == pytest.approx(float(np.mean(inner)), abs=2e-3)
    # Continuous seams: entering a new window and passing its hand-off change the picture no more than the frames
    # inside a window change. The ablation of every join mechanism (independent windows, cut) jumps: the measure
    # can fail.
    assert summary["seam_jump"] < summary["inner_frame_change"], summary
    assert summary["join_frame_change"] < 1.2 * summary["inner_frame_change"], summary
    cut = refine_to_folder(
        trained["root"] / "model",
        trained["root"] / "data_a",
        "s0_test00",
        trained["root"] / "cut",
        steps=6,
        write_exr_frames=False,
        vae_round_trip_psnr=False,
        joins=Joins(handoff=False, pin=False, crossfade=False),
    )
    # (the tiny size's residual flow anchors independent windows to the same input, so they jump less than latent
    # flow's would; the measure still sees it)
    assert cut["seam_jump"] > cut["inner_frame_change"] and cut["seam_jump"] > summary["seam_jump"], (cut, summary)
    assert np.isfinite(summary["psnr_refined"])
    assert np.isfinite(summary["psnr_vae_round_trip"])


def test_handoff_frames_are_the_previous_windows_output(trained, monkeypatch):
    """The next window's seed frames are the previous window's decoded last frames (mask 0); shown, they cross-fade
    from that version to the next window's; without the cross-fade the previous window's version is shown."""
    import gra_mi.refiner.infer as infer

    model = VideoRefiner.load(trained["root"] / "model")
    seen, decoded = [], []
    real_conditioning, real_decode = model.conditioning, model.decode_output

    def spy(coarse, mask, *rest):
        seen.append((coarse.clone(), mask.clone()))
        return real_conditioning(coarse, mask, *rest)

    def decode(*args):  # each window's refined video
        decoded.append(real_decode(*args))
        return decoded[-1]

    monkeypatch.setattr(model, "conditioning", spy)
    monkeypatch.setattr(model, "decode_output", decode)
    frames = list(infer.rollout(model, trained["a"], "s0_test00", steps=2, frames=29))
    assert len(seen) == 2 and len(decoded) == 2 and [f.index for f in frames] == list(range(29))
    second_coarse, second_mask = seen[1]
    torch.testing.assert_close(second_coarse[:, :5], decoded[0][:, 12:])
    assert second_mask[0, 0, :5].max() == 0 and second_mask[0, 0, 5:].min() == 1
    for i in range(5):
        alpha = (i + 1) / 6
        torch.testing.assert_close(frames[12 + i].video, (1 - alpha) * decoded[0][:, 12 + i] + alpha * decoded[1][:, i])
    torch.testing.assert_close(frames[17].video, decoded[1][:, 5])

    cut = list(infer.rollout(model, trained["a"], "s0_test00", steps=2, frames=29, joins=infer.Joins(crossfade=False)))
    torch.testing.assert_close(torch.stack([f.video for f in cut[12:17]], dim=1), decoded[2][:, 12:])


def test_a_zero_residual_returns_the_input_exactly(trained, monkeypatch):
    """Tiny size (residual flow): the refined window is the input plus the decoded change from what the input's own
    latents decode to, so a sampler that finds no residual returns the input itself, not its VAE round trip — over
    a hand-off too, where the seed frames are given."""
    import gra_mi.refiner.infer as infer

    model = VideoRefiner.load(trained["root"] / "model")
    monkeypatch.setattr(infer, "euler_sample", lambda model, shape, *rest: torch.zeros(shape))
    frames = list(infer.rollout(model, trained["a"], "s0_test00", steps=2, frames=29))  # two windows
    coarse = trained["a"].window("s0_test00", 0, 29)["coarse"]
    torch.testing.assert_close(torch.stack([f.video for f in frames], dim=1), coarse.clamp(-1, 1), atol=1e-5, rtol=0)
    roundtrip = model.decode(model.encode(coarse[None, :, :17]))[0]
    assert (roundtrip - coarse[:, :17]).abs().mean() > 1e-3  # the VAE alone would not have returned it


def test_mix_blends_the_refiners_change_and_zero_samples_nothing(trained, monkeypatch):
    """Mix s delivers input + s·(refined − input) (the model's own mix by default); mix 0 delivers the
    input exactly without sampling, and refine.json says which mix it used."""
    import gra_mi.refiner.infer as infer

    model = VideoRefiner.load(trained["root"] / "model")
    assert model.config.mix == 1.0  # trained on data without a selection sequence
    coarse = trained["a"].window("s0_test00", 0, 41)["coarse"]
    full = torch.stack([f.video for f in infer.rollout(model, trained["a"], "s0_test00", steps=2, frames=17)], dim=1)
    half = torch.stack([f.video for f in infer.rollout(model, trained["a"], "s0_test00", steps=2, frames=17, mix=0.5)], dim=1)
    torch.testing.assert_close(half, coarse[:, :17] + 0.5 * (full - coarse[:, :17]))
    model.config.mix = 0.5
    own = torch.stack([f.video for f in infer.rollout(model, trained["a"], "s0_test00", steps=2, frames=17)], dim=1)
    torch.testing.assert_close(own, half)

    def no_sampling(*args, **kwargs):
        raise AssertionError("mix 0 must not sample")

    monkeypatch.setattr(infer, "euler_sample", no_sampling)
    none = list(infer.rollout(model, trained["a"], "s0_test00", mix=0.0))
    assert [f.index for f in none] == list(range(41))
    torch.testing.assert_close(torch.stack([f.video for f in none], dim=1), coarse, atol=0, rtol=0)
    summary = infer.refine_to_folder(
        trained["root"] / "model",
        trained["root"] / "data_a",
        "s0_test00",
        trained["root"] / "s0",
        mix=0.0,
        frames=5,
        vae_round_trip_psnr=False,
    )
    assert summary["mix"] == 0.0 and summary["psnr_refined"] == pytest.approx(summary["psnr_coarse"], abs=1e-3)
    with pytest.raises(GraMiParameterError, match="mix"):
        list(infer.rollout(model, trained["a"], "s0_test00", mix=1.5))


def test_mix_choice_follows_the_refined_videos_goal():
    """A mix qualifies with PSNR at most 0.4 dB below the input's and ꟻLIP and temporal error no worse; the
    qualifying one with the lowest ꟻLIP is kept (ties: the smaller); the input itself always qualifies."""
    from gra_mi.refiner.mix import MixScore as S
    from gra_mi.refiner.mix import choose_mix

    base = S(0.0, 30.0, 0.10, 0.020)
    assert choose_mix([base, S(0.5, 29.9, 0.11, 0.019), S(1.0, 31.0, 0.09, 0.030)]).mix == 0  # ꟻLIP / temporal worse
    assert choose_mix([base, S(0.5, 29.7, 0.09, 0.019), S(1.0, 29.5, 0.08, 0.018)]).mix == 0.5  # 1 gives up 0.5 dB
    assert choose_mix([base, S(0.25, 30.1, 0.09, 0.02), S(0.5, 30.2, 0.09, 0.02)]).mix == 0.25
    one_frame = [S(0.0, 30.0, 0.10, float("nan")), S(1.0, 30.0, 0.09, float("nan"))]  # no temporal error to compare
    assert choose_mix(one_frame).mix == 1.0 and choose_mix(one_frame[:1]).mix == 0.0
    with pytest.raises(ValueError, match="mix 0"):
        choose_mix([S(1.0, 30.0, 0.1, 0.02)])


def test_mix_scores_a_perfect_and_a_noisy_refiner(tmp_path, monkeypatch):
    """On the selection sequence, a stand-in refiner that returns the truth is kept at mix 1 and one that adds
    noise to its input at 0; the mix-0 row is the input's own PSNR against the truth."""
    from types import SimpleNamespace

    import gra_mi.refiner.infer as infer
    from gra_mi.core.metrics import compare
    from gra_mi.refiner.mix import MIXES, choose_mix, mix_scores

    data = synthetic_dataset(tmp_path / "data", {0: (1, 0, 1)}, frames=17, height=32, width=32, env_height=16, test_frames=17)
    name = data.names("selection")[0]
    window = data.window(name, 0, 17)
    model = SimpleNamespace(config=SimpleNamespace(window=17))

    def stand_in(video):
        def rollout(model, dataset, sequence, **options):
            assert options["mix"] == 1.0 and options["frames"] == 17
            return (infer.RefinedFrame(i, video[:, i], 0) for i in range(17))

        return rollout

    monkeypatch.setattr(infer, "rollout", stand_in(window["target"]))
    perfect = mix_scores(model, data, [name], steps=2, shift=3.0)
    assert [s.mix for s in perfect] == list(MIXES) and choose_mix(perfect).mix == 1.0
    truth = [data.delivered(name, i, "target") for i in range(17)]
    coarse = [data.delivered(name, i, "coarse") for i in range(17)]
    masks = [infer._subject(c, t) for c, t in zip(coarse, truth, strict=True)]
    unchanged = np.mean([compare(c, t, m)["psnr"] for c, t, m in zip(coarse, truth, masks, strict=True)])
    assert perfect[0].psnr == pytest.approx(unchanged, abs=1e-3) and perfect[-1].psnr > unchanged + 10
    noise = torch.randn(window["coarse"].shape, generator=torch.Generator().manual_seed(0))
    monkeypatch.setattr(infer, "rollout", stand_in((window["coarse"] + 0.1 * noise).clamp(-1, 1)))
    assert choose_mix(mix_scores(model, data, [name], steps=2, shift=3.0)).mix == 0.0


def test_training_chooses_the_mix_on_the_selection_sequences(tmp_path):
    """Training with a selection sequence scores every mix on it and keeps the choice in refiner.json (which
    `refine` then uses), train.json and mix.md; the selection sequence is not trained on."""
    from gra_mi.refiner.mix import MIXES
    from gra_mi.refiner.train import _windows

    data = synthetic_dataset(tmp_path / "data", {0: (2, 1, 1)}, frames=17, height=32, width=32, env_height=16, test_frames=17)
    assert data.names("selection") == ["s0_selection00"]
    assert {n for n, _ in _windows(data, 17, "train")} == {"s0_train00", "s0_train01"}
    config = RefinerTrainConfig(steps=2, checkpoint_every=1000, selection_steps=2)
    train_refiner(data.folder, tmp_path / "model", config, RefinerConfig(lora_rank=4))
    summary = json.loads((tmp_path / "model" / "train.json").read_text())["mix"]
    assert [s["mix"] for s in summary["scores"]] == list(MIXES) and summary["sequences"] == ["s0_selection00"]
    assert summary["chosen"] in MIXES
    assert VideoRefiner.load(tmp_path / "model").config.mix == summary["chosen"]
    assert (tmp_path / "model" / "mix.md").is_file() and (tmp_path / "model" / "mix.png").is_file()
    off = RefinerTrainConfig(steps=2, checkpoint_every=1000, choose_mix=False)
    train_refiner(data.folder, tmp_path / "off", off, RefinerConfig(lora_rank=4))
    assert json.loads((tmp_path / "off" / "train.json").read_text())["mix"] == {"chosen": 1.0, "why": "switched off"}
    with pytest.raises(GraMiInputError, match="mix"):
        VideoRefiner.load(tmp_path / "model", mix=2.0)


def test_mean_estimate_error_against_the_input(trained, monkeypatch):
    """A flow that predicts a zero residual (velocity = the noise) estimates the input's latents: ratio exactly 1; one
    that predicts the target's residual exactly: ratio 0. The trained model's ratio is finite and positive."""
    from gra_mi.refiner.train import encode_window, mean_estimate_error

    model = VideoRefiner.load(trained["root"] / "model")
    measured = mean_estimate_error(model, trained["a"], "test", max_windows=2)
    assert measured["windows"] == 2 and measured["input"] > 0 and 0 < measured["ratio"] < 100
    monkeypatch.setattr(model, "forward", lambda x, sigma, control, env: x)
    assert mean_estimate_error(model, trained["a"], "test", max_windows=2)["ratio"] == pytest.approx(1.0, abs=1e-6)
    targets = {}  # the exact residual of each window, looked up by its control
    for begin in (0, 12):
        enc = encode_window(model, trained["a"].window("s0_test00", begin, 17), 0)
        targets[float(enc.control.sum())] = model.to_flow(enc.clean, enc.control, enc.given)
    monkeypatch.setattr(model, "forward", lambda x, sigma, control, env: x - targets[float(control.sum())])
    exact = mean_estimate_error(model, trained["a"], "test", max_windows=2)
    assert exact["estimate"] < 1e-8 * exact["input"]


@pytest.mark.slow
def test_data_curve_script_runs_and_writes_its_table(tmp_path):
    """pipelines/refiner_data_curve.py end to end on one tiny size: the CSV, the plot and the table."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parent.parent / "pipelines" / "refiner_data_curve.py"
    args = ["--work", str(tmp_path), "--sequences", "2", "--steps", "2", "--resolution", "32", "--test-frames", "17", "--sample-steps", "2"]
    done = subprocess.run([sys.executable, str(script), *args], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = (tmp_path / "curve.csv").read_text().splitlines()
    header = "sequences,ratio,psnr_input,flip_input,temporal_input,psnr_refined,flip_refined,temporal_refined,minutes"
    assert rows[0] == header and len(rows) == 2
    assert all(np.isfinite(float(v)) for v in rows[1].split(","))
    assert (tmp_path / "curve.png").is_file() and "| 2 |" in (tmp_path / "curve.md").read_text()


def test_few_shot_identity_adaptation(trained):
    """A refiner trained on subject A, fine-tuned on ten 17-frame clips of subject B, fits B better than before."""
    before = validation_loss(VideoRefiner.load(trained["root"] / "model"), trained["b"])
    train_refiner(
        trained["root"] / "data_b",
        trained["root"] / "adapted",
        RefinerTrainConfig(steps=150, lr=5e-3, checkpoint_every=1000, static_clip_prob=0, dynamic_motion_prob=0),
        init=trained["root"] / "model",
    )
    after = validation_loss(VideoRefiner.load(trained["root"] / "adapted"), trained["b"])
    assert after < 0.95 * before, (before, after)


def test_resume_equals_an_uninterrupted_run(tmp_path):
    data = synthetic_dataset(tmp_path / "data", {0: (2, 0)}, frames=17, height=32, width=32)
    config = dict(lr=3e-3, checkpoint_every=3, log_every=1, static_clip_prob=0.5)
    train_refiner(data.folder, tmp_path / "straight", RefinerTrainConfig(steps=6, **config))
    train_refiner(data.folder, tmp_path / "resumed", RefinerTrainConfig(steps=3, **config))  # "interrupted" after 3
    train_refiner(data.folder, tmp_path / "resumed", RefinerTrainConfig(steps=6, **config))
    a = VideoRefiner.load(tmp_path / "straight").trainable_state()
    b = VideoRefiner.load(tmp_path / "resumed").trainable_state()
    for name in a:
        torch.testing.assert_close(a[name], b[name], atol=1e-6, rtol=1e-5)


def test_divergence_keeps_the_last_finite_weights_and_is_recorded(tmp_path, monkeypatch):
    """Weights poisoned with NaN after the 4th update: the loss at step 4 is NaN, training stops there, the weights
    of the last finite snapshot (step 3, the checkpoint cadence) are saved and loadable, train.json says where, and the
    mix is chosen on a finite refiner."""
    data = synthetic_dataset(tmp_path / "data", {0: (2, 1, 1)}, frames=17, height=32, width=32, env_height=16, test_frames=17)
    calls = poison_optimizer_after(monkeypatch, 4)
    config = RefinerTrainConfig(steps=8, checkpoint_every=3, log_every=1, selection_steps=2)
    train_refiner(data.folder, tmp_path / "model", config, RefinerConfig(lora_rank=4))
    summary = json.loads((tmp_path / "model" / "train.json").read_text())
    assert summary["diverged"]["step"] == 4 and summary["diverged"]["kept_step"] == 3 and len(calls) == 4
    model = VideoRefiner.load(tmp_path / "model")
    assert all(bool(torch.isfinite(t).all()) for t in model.trainable_state().values())
    assert all(np.isfinite(s["psnr"]) for s in summary["mix"]["scores"])


def test_non_finite_refiner_scores_never_qualify():
    from gra_mi.refiner.mix import MixScore, choose_mix

    scores = [
        MixScore(0.0, 30.0, 0.1, 0.02),
        MixScore(0.5, float("nan"), float("nan"), float("nan")),
        MixScore(1.0, 31.0, float("nan"), 0.01),
    ]
    assert choose_mix(scores).mix == 0.0


def test_weights_with_nan_are_refused_by_name(tmp_path):
    from safetensors.torch import save_file

    model = VideoRefiner(RefinerConfig(lora_rank=4))
    model.save(tmp_path / "m")
    state = {k: v.clone() for k, v in model.state_dict().items()}
    next(v for v in state.values() if v.is_floating_point()).fill_(float("nan"))
    save_file({k: v.contiguous() for k, v in state.items()}, str(tmp_path / "m" / "refiner.safetensors"))
    with pytest.raises(GraMiInputError, match="non-finite"):
        VideoRefiner.load(tmp_path / "m")
    (tmp_path / "m" / "refiner.safetensors").write_bytes(b"")
    with pytest.raises(GraMiInputError, match="unreadable"):
        VideoRefiner.load(tmp_path / "m")


# --------------------------------------------------------------------------------------------------------------
# Real sizes and inputs
# --------------------------------------------------------------------------------------------------------------


def test_real_sizes_need_weights_on_disk(tmp_path):
    with pytest.raises(GraMiInputError, match="weights on disk"):
        VideoRefiner(RefinerConfig(size="1.3B"))
    with pytest.raises(GraMiInputError, match="not found"):
        VideoRefiner(RefinerConfig(size="14B", weights=str(tmp_path / "nowhere")))
    (tmp_path / "wan").mkdir()
    with pytest.raises(GraMiInputError, match="transformer/config.json"):
        VideoRefiner(RefinerConfig(size="1.3B", weights=str(tmp_path / "wan")))


def _local_wan_folder(folder, text_dim: int = 32):
    """A WAN2.1-VACE diffusers folder as a user has one (transformer/, vae/, tokenizer/, text_encoder/), tiny sizes."""
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel
    from tokenizers import Tokenizer, models, pre_tokenizers
    from transformers import PreTrainedTokenizerFast, UMT5Config, UMT5EncoderModel

    torch.manual_seed(3)
    WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"]).save_pretrained(folder / "transformer")
    AutoencoderKLWan(**WAN_VAE_STANDIN).save_pretrained(folder / "vae")
    words = ["<pad>", "</s>", "<unk>", "a", "person", "photorealistic", "studio", "lighting", ","]
    tok = Tokenizer(models.WordLevel({w: i for i, w in enumerate(words)}, unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.WhitespaceSplit()
    PreTrainedTokenizerFast(tokenizer_object=tok, pad_token="<pad>", eos_token="</s>", unk_token="<unk>").save_pretrained(
        folder / "tokenizer"
    )
    config = UMT5Config(vocab_size=len(words), d_model=text_dim, d_kv=8, d_ff=64, num_layers=2, num_heads=4)
    UMT5EncoderModel(config).save_pretrained(folder / "text_encoder")


def test_real_size_from_a_local_diffusers_folder(tmp_path, monkeypatch):
    """The real-size path end to end on a tiny folder standing in for WAN2.1-VACE-1.3B-diffusers: `gra-mi
    refiner-prompt`, from_pretrained in bfloat16 (fp32-kept modules as `cast_transformer` keeps them), LoRA + envmap
    layers, a training step, save/load of the trainable weights, and a refined window."""
    from gra_mi.cli import main
    from gra_mi.refiner.loading import cast_transformer

    wan = tmp_path / "wan"
    _local_wan_folder(wan)
    prompt = tmp_path / "prompt.safetensors"
    assert main(["refiner-prompt", "--pipeline", str(wan), "--out", str(prompt)]) == 0
    from safetensors.torch import load_file

    embeds = load_file(str(prompt))["prompt_embeds"]
    assert embeds.shape == (1, 512, 32) and embeds[0, :3].abs().sum() > 0 and embeds[0, 10:].abs().sum() == 0
    # The real 1.3B's weights are the wrong size for this folder: a clear error, not a silently different model.
    with pytest.raises(GraMiInputError, match="num_layers"):
        VideoRefiner(RefinerConfig(size="1.3B", weights=str(wan), prompt_embeds=str(prompt)))
    monkeypatch.setitem(TRANSFORMER_CONFIGS, "1.3B", TRANSFORMER_CONFIGS["tiny"])
    config = RefinerConfig(size="1.3B", weights=str(wan), prompt_embeds=str(prompt), dtype="bfloat16", lora_rank=4)
    model = VideoRefiner(config)
    from diffusers import WanVACETransformer3DModel

    reference = cast_transformer(WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"]), torch.bfloat16)
    dtypes = {n.replace(".base_layer", ""): p.dtype for n, p in model.transformer.named_parameters() if "lora_" not in n}
    assert dtypes == {n: p.dtype for n, p in reference.named_parameters()}
    assert {d for n, d in dtypes.items() if "scale_shift_table" in n} == {torch.float32}
    assert {d for n, d in dtypes.items() if n.endswith("attn1.to_q.weight")} == {torch.bfloat16}

    data = synthetic_dataset(tmp_path / "data", {0: (1, 1)}, frames=17, height=32, width=32, test_frames=17)
    out = train_refiner(data.folder, tmp_path / "model", RefinerTrainConfig(steps=2, log_every=1), model_config=config)
    loaded = VideoRefiner.load(out)
    trained = model.trainable_state()
    assert set(loaded.trainable_state()) == set(trained)
    assert main(["refine", str(data.folder), "--model", str(out), "--out", str(tmp_path / "refined"), "--steps", "2"]) == 0
    summary = json.loads((tmp_path / "refined" / "refine.json").read_text())
    assert summary["frames"] == 17 and summary["fuse_lora"] is True and np.isfinite(summary["psnr_refined"])


def _to_original_wan_keys(state: dict) -> dict:
    """diffusers → original Wan2.1 key names (the inverse of diffusers' convert_wan_transformer_to_diffusers)."""
    import re

    renames = [
        (r"^condition_embedder\.time_embedder\.linear_1", "time_embedding.0"),
        (r"^condition_embedder\.time_embedder\.linear_2", "time_embedding.2"),
        (r"^condition_embedder\.text_embedder\.linear_1", "text_embedding.0"),
        (r"^condition_embedder\.text_embedder\.linear_2", "text_embedding.2"),
        (r"^condition_embedder\.time_proj", "time_projection.1"),
        (r"^scale_shift_table", "head.modulation"),
        (r"^proj_out", "head.head"),
        (r"\.attn1\.", ".self_attn."),
        (r"\.attn2\.", ".cross_attn."),
        (r"\.to_out\.0\.", ".o."),
        (r"\.to_([qkv])\.", r".\1."),
        (r"\.ffn\.net\.0\.proj\.", ".ffn.0."),
        (r"\.ffn\.net\.2\.", ".ffn.2."),
        (r"^(blocks\.\d+)\.scale_shift_table", r"\1.modulation"),
        (r"\.norm2\.", ".norm__swap."),
        (r"\.norm3\.", ".norm2."),
        (r"\.norm__swap\.", ".norm3."),
        (r"^(vace_blocks\.\d+)\.proj_in", r"\1.before_proj"),
        (r"^(vace_blocks\.\d+)\.proj_out", r"\1.after_proj"),
    ]
    out = {}
    for key, value in state.items():
        for pattern, repl in renames:
            key = re.sub(pattern, repl, key)
        out[key] = value
    return out


def test_real_size_from_original_checkpoints(tmp_path, monkeypatch):
    """An original-format transformer checkpoint (Wan2.1 key names) through the real-size loader: converted, loaded in
    bfloat16 with the float32-kept parameters unrounded; wrong files are named. (The VAE's key conversion is
    diffusers' own: replaced by the identity here, so a diffusers-format tiny VAE stands in for Wan2.1_VAE.pth.)"""
    import diffusers
    from diffusers import AutoencoderKLWan, WanVACETransformer3DModel
    from diffusers.loaders import single_file_utils
    from safetensors.torch import save_file

    monkeypatch.setitem(TRANSFORMER_CONFIGS, "1.3B", TRANSFORMER_CONFIGS["tiny"])
    monkeypatch.setattr(diffusers, "AutoencoderKLWan", lambda: AutoencoderKLWan(**WAN_VAE_STANDIN))
    monkeypatch.setattr(single_file_utils, "convert_wan_vae_to_diffusers", lambda state: state)
    torch.manual_seed(5)
    source = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["tiny"])
    original = _to_original_wan_keys({k: v.contiguous() for k, v in source.state_dict().items()})
    assert single_file_utils.convert_wan_transformer_to_diffusers(dict(original)).keys() == source.state_dict().keys()
    save_file(original, str(tmp_path / "wan_vace.safetensors"))

    save_file(AutoencoderKLWan(**WAN_VAE_STANDIN).state_dict(), str(tmp_path / "vae.safetensors"))
    prompt = tmp_path / "prompt.safetensors"
    save_file({"prompt_embeds": torch.randn(1, 8, 32)}, str(prompt))
    config = dict(size="1.3B", weights=str(tmp_path / "wan_vace.safetensors"), prompt_embeds=str(prompt), dtype="bfloat16")
    with pytest.raises(GraMiInputError, match="vae-weights"):
        VideoRefiner(RefinerConfig(**config))
    model = VideoRefiner(RefinerConfig(**config, vae_weights=str(tmp_path / "vae.safetensors")))
    loaded = dict(model.transformer.named_parameters())
    for name, param in source.named_parameters():
        head, _, leaf = name.rpartition(".")
        mine = loaded[name] if name in loaded else loaded[f"{head}.base_layer.{leaf}"]  # LoRA-wrapped layers
        assert torch.equal(mine.detach(), param.detach().to(mine.dtype)), name  # bf16 rounding only; float32-kept ones exact
    assert loaded["scale_shift_table"].dtype == torch.float32 and loaded["patch_embedding.weight"].dtype == torch.bfloat16
    # A checkpoint of another size: named, with what did not fit.
    save_file({k: v[..., :1].contiguous() if k.endswith("q.weight") else v for k, v in original.items()}, str(tmp_path / "bad.safetensors"))
    with pytest.raises(GraMiInputError, match="bad.safetensors"):
        VideoRefiner(
            RefinerConfig(**{**config, "weights": str(tmp_path / "bad.safetensors")}, vae_weights=str(tmp_path / "vae.safetensors"))
        )


def test_real_configs_lora_size():
    """The 1.3B config built on the meta device: LoRA r32 on the main blocks adds the 43.7 M parameters of a full count."""
    from diffusers import WanVACETransformer3DModel
    from peft import LoraConfig

    from gra_mi.refiner.config import LORA_TARGETS

    with torch.device("meta"):
        model = WanVACETransformer3DModel(**TRANSFORMER_CONFIGS["1.3B"])
    base = sum(p.numel() for p in model.parameters())
    model.add_adapter(LoraConfig(r=32, lora_alpha=32, target_modules=LORA_TARGETS))
    lora = sum(p.numel() for n, p in model.named_parameters() if "lora_" in n)
    dim, ffn, layers = 1536, 8960, 30
    assert lora == layers * 32 * (8 * 2 * dim + 2 * (dim + ffn))  # 8 attention projections + 2 FFN projections per block
    assert 2.0e9 < base < 2.2e9


def test_bad_dataset_is_named(tmp_path):
    (tmp_path / "dataset.json").write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(GraMiInputError, match="format"):
        RefinerDataset(tmp_path)
    with pytest.raises(GraMiInputError, match="window: must be 4k"):
        RefinerConfig(window=16).validate()


def test_cli_end_to_end(tmp_path, capsys):
    from gra_mi.cli import main

    data, model, out = tmp_path / "data", tmp_path / "model", tmp_path / "refined"
    assert main(["refiner-data", "--synthetic", "--out", str(data), "--sequences", "2", "--resolution", "32", "--test-length", "21"]) == 0
    assert main(["train-refiner", str(data), "--out", str(model), "--steps", "3", "--lora-rank", "4", "--env-blocks", "1,3"]) == 0
    assert json.loads((model / "train.json").read_text())["mix"]["sequences"] == ["s0_selection00"]  # chosen on it
    assert main(["refine", str(data), "--model", str(model), "--out", str(out), "--steps", "2", "--mix", "1"]) == 0
    summary = json.loads((out / "refine.json").read_text())
    assert summary["frames"] == 21 and summary["windows"] == 2 and summary["mix"] == 1.0
    # flicker correction beside the refined frames; composites need data made from a capture (named, exit 2)
    assert main(["refine", str(data), "--model", str(model), "--out", str(out), "--steps", "2", "--deflicker", "--frames", "3"]) == 0
    summary = json.loads((out / "refine.json").read_text())
    assert summary["deflicker"]["filter_eps"] == 0.05 and "psnr_deflickered" in summary
    capsys.readouterr()
    assert main(["refine", str(data), "--model", str(model), "--out", str(tmp_path / "m"), "--mix", "0", "--frames", "2"]) == 0
    assert "delivered the input unchanged: mix 0 (--mix)" in capsys.readouterr().out
    assert (out / "deflickered" / "frame_0002.exr").is_file() and (out / "deflickered" / "deflickered.mp4").is_file()
    assert main(["refine", str(data), "--model", str(model), "--out", str(tmp_path / "c"), "--composite"]) == 2
    assert main(["train-refiner", str(data), "--out", str(tmp_path / "x"), "--size", "1.3B"]) == 2


@pytest.mark.slow
def test_ddp_training_with_two_processes(tmp_path):
    import os
    import subprocess
    import sys

    data = synthetic_dataset(tmp_path / "data", {0: (2, 0)}, frames=17, height=32, width=32)
    env = {**os.environ, "GRA_MI_QUIET": "1", "OMP_NUM_THREADS": "1"}
    cmd = [
        sys.executable, "-m", "torch.distributed.run", "--nproc_per_node", "2", "--master_port", str(free_port()), "-m", "gra_mi.cli",
        "train-refiner", str(data.folder), "--out", str(tmp_path / "ddp"), "--steps", "4", "--checkpoint-every", "2",
    ]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "ddp" / "refiner.safetensors").exists() and (tmp_path / "ddp" / "train.json").exists()


@pytest.mark.slow
def test_vae_pretraining_script_trains_scores_and_writes_loadable_weights(path_traced_fit, tmp_path):
    """pipelines/pretrain_tiny_vae.py end to end on a few steps: training cameras only, the held-out round-trip
    curve (CSV + PNG), and weights the refiner's tiny VAE config loads."""
    import subprocess
    import sys

    from safetensors import safe_open
    from safetensors.torch import load_file

    from gra_mi.refiner.config import VAE_CONFIGS
    from gra_mi.refiner.tiny_vae import TinyVideoAutoencoder

    out = tmp_path / "vae.safetensors"
    script = Path(__file__).resolve().parent.parent / "pipelines" / "pretrain_tiny_vae.py"
    args = [sys.executable, str(script), "--steps", "6", "--eval-every", "3", "--capture", str(path_traced_fit / "cap")]
    done = subprocess.run([*args, "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = out.with_suffix(".csv").read_text().splitlines()
    assert rows[0] == "seconds,steps,held_out_psnr_db,held_out_temporal" and len(rows) >= 3
    assert all(np.isfinite(float(r.split(",")[2])) for r in rows[1:]) and out.with_suffix(".png").is_file()
    with safe_open(str(out), framework="pt") as f:
        stats = {k: json.loads(v) for k, v in f.metadata().items()}
    assert len(stats["latents_mean"]) == len(stats["latents_std"]) == 16 and min(stats["latents_std"]) > 0
    TinyVideoAutoencoder(**VAE_CONFIGS["tiny"], **stats).load_state_dict(load_file(str(out)))
    # the exact start holds the delivered frames to well above the 30 dB goal before any training
    first = float(rows[1].split(",")[2])
    assert first > 30, rows


@pytest.mark.slow
def test_refiner_prior_script_trains_and_the_refiner_loads_its_prior(tmp_path, monkeypatch):
    """pipelines/pretrain_tiny_refiner.py end to end on a few steps (on synthetic data): every DiT weight trains, and
    the exported prior is what a tiny refiner starts from."""
    import subprocess
    import sys

    from safetensors.torch import load_file

    import gra_mi.refiner.model as rm

    data = synthetic_dataset(tmp_path / "data", {0: (2, 0)}, frames=17, height=32, width=32)
    out = tmp_path / "prior.safetensors"
    script = Path(__file__).resolve().parent.parent / "pipelines" / "pretrain_tiny_refiner.py"
    args = [sys.executable, str(script), "--data", str(data.folder), "--steps", "2", "--work", str(tmp_path / "work"), "--out", str(out)]
    done = subprocess.run(args, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    prior = load_file(str(out))
    assert not any(k.startswith("vae.") or "lora_" in k for k in prior) and "prompt_embeds" in prior
    fresh = VideoRefiner(RefinerConfig(prior=False, lora_rank=0))
    moved = [k for k, v in prior.items() if k.startswith("transformer.blocks.0.") and not torch.equal(v, fresh.state_dict()[k])]
    assert moved, "pretraining trains the main DiT blocks, not only the adapters"
    monkeypatch.setattr(rm, "TINY_PRIOR_WEIGHTS", out)
    model = VideoRefiner(RefinerConfig(lora_rank=4))
    state = model.state_dict()
    for key, value in prior.items():  # under LoRA, a main-block linear's weight sits in base_layer
        head, _, leaf = key.rpartition(".")
        mine = state[key] if key in state else state[f"{head}.base_layer.{leaf}"]
        assert torch.equal(mine, value.to(mine.dtype)), key  # stored in float16
    # a prior of another config is named with the script that rebuilds it
    from safetensors.torch import save_file

    save_file({k: v[..., :1].contiguous() for k, v in prior.items()}, str(tmp_path / "bad.safetensors"))
    monkeypatch.setattr(rm, "TINY_PRIOR_WEIGHTS", tmp_path / "bad.safetensors")
    with pytest.raises(GraMiInputError, match="pretrain_tiny_refiner.py"):
        VideoRefiner(RefinerConfig())


# --------------------------------------------------------------------------------------------------------------
# The tiny VAE and the subject crop
# --------------------------------------------------------------------------------------------------------------


def test_tiny_vae_starts_exact_in_block_means_and_is_causal():
    """At initialisation the round trip is each frame's 4 × 4 block mean (float64 NumPy reference); latent frame 0
    holds pixel frame 0 alone and frame k ≥ 1 frames 4k − 3 … 4k, as Wan's causal VAE."""
    from gra_mi.refiner.tiny_vae import TinyVideoAutoencoder

    vae = TinyVideoAutoencoder()
    g = torch.Generator().manual_seed(0)
    video = torch.rand(1, 3, 9, 16, 24, generator=g) * 2 - 1
    with torch.no_grad():
        z = vae.encode(video).latent_dist.mode()
        back = vae.decode(z).sample
    assert z.shape == (1, 16, 3, 4, 6) and back.shape == video.shape
    v = video.double().numpy()
    means = v.reshape(1, 3, 9, 4, 4, 6, 4).mean(axis=(4, 6))
    expected = np.repeat(np.repeat(means, 4, axis=3), 4, axis=4)
    np.testing.assert_allclose(back.double().numpy(), expected, atol=1e-6)
    # channels 0..11 are the block means of (colour, frame in the group): latent frame 1 is frames 1-4
    np.testing.assert_allclose(z[0, 0, 1].numpy(), means[0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(z[0, 4 * 2 + 3, 2].numpy(), means[0, 2, 8], atol=1e-6)
    with torch.no_grad():  # causal, also once the branches have weights: later frames leave earlier latents alone
        for branch in (vae.encode_branch, vae.decode_branch):
            branch[-1].weight.normal_(std=0.05)
        later = video.clone()
        later[:, :, 5:] = 0
        a, b = vae.encode(video).latent_dist.mode(), vae.encode(later).latent_dist.mode()
    assert torch.equal(a[:, :, :2], b[:, :, :2]) and not torch.equal(a[:, :, 2], b[:, :, 2])
    with pytest.raises(ValueError, match="multiples of 4"):
        vae.encode(torch.zeros(1, 3, 5, 18, 16))


def test_subject_crop_goes_back_exactly():
    """A box magnified 4× lines 4 × 4 crop pixels up with one delivered pixel: a change that keeps every block mean
    (the tiny VAE's start) leaves the delivered frame as it was, to float precision; a constant change comes back
    as itself inside the box and nothing outside."""
    from gra_mi.refiner.data import subject_boxes
    from gra_mi.refiner.dataset import crop_box, paste_box

    rng = np.random.default_rng(2)
    full = rng.uniform(0, 2, (2, 64, 80, 3)).astype(np.float32)  # capture resolution
    frames = full.reshape(2, 32, 2, 40, 2, 3).mean(axis=(2, 4))  # delivered at scale 0.5 (area)
    masks = np.zeros((2, 32, 40), bool)
    masks[0, 5:20, 10:17] = masks[1, 8:25, 12:19] = True
    size, (box,) = subject_boxes([masks], zoom=4)
    y0, x0, y1, x1 = box
    assert size == ((y1 - y0) * 4, (x1 - x0) * 4) and size[0] % 16 == 0 and size[1] % 16 == 0
    assert y0 <= 5 and y1 >= 25 and x0 <= 10 and x1 >= 19
    crops = crop_box(full, box, 0.5, size)
    assert crops.shape == (2, *size, 3)
    h, w = size
    blocks = crops.reshape(2, h // 4, 4, w // 4, 4, 3).mean(axis=(2, 4), keepdims=True)
    kept = np.broadcast_to(blocks, (2, h // 4, 4, w // 4, 4, 3)).reshape(crops.shape)
    for i in range(2):
        np.testing.assert_allclose(paste_box(frames[i], kept[i] - crops[i], box), frames[i], atol=1e-5)
    shifted = paste_box(frames[0], np.full((h, w, 3), 0.25, np.float32), box)
    inside = np.zeros((32, 40), bool)
    inside[max(y0, 0) : y1, max(x0, 0) : x1] = True
    np.testing.assert_allclose(shifted[inside] - frames[0][inside], 0.25, atol=1e-6)
    assert np.array_equal(shifted[~inside], frames[0][~inside])
    # the crop samples the capture image where the box says: a crop of a ramp is the ramp
    ramp = np.broadcast_to(np.arange(80, dtype=np.float32)[None, None, :, None], (1, 64, 80, 3))
    crop = crop_box(ramp, box, 0.5, size)[0, 0, :, 0]
    centres = (x0 + (np.arange(w) + 0.5) / 4) / 0.5 - 0.5  # capture pixel coordinates of the crop's pixel centres
    inner = (centres > 0) & (centres < 79)
    np.testing.assert_allclose(crop[inner], centres[inner], atol=1e-4)


def test_residual_flow_space_round_trips_and_keeps_the_given_frames(model):
    """Tiny size: the flow runs on (latents − the input's latents) / residual_scale. The base is the reference and the
    seed frames where the mask keeps them, the coarse input's latents elsewhere; a zero residual is the input."""
    for seeded in (0, 5):
        latents, control, _, (video, mask, ref) = _inputs(model, seeded=seeded, seed=seeded)
        base = model.base_latents(control)
        kept = control[0, 32:].amax(dim=(0, 2, 3)) == 0  # latent frames the mask keeps: the reference, seed frames
        assert kept.tolist() == [True] + [False] * 5 if seeded == 0 else [True, True] + [False] * 4
        assert torch.equal(base[:, :, kept], control[:, :16, kept])
        assert torch.equal(base[:, :, ~kept], control[:, 16:32, ~kept])
        torch.testing.assert_close(model.from_flow(model.to_flow(latents, control), control), latents, atol=1e-5, rtol=1e-5)
        assert torch.equal(model.from_flow(torch.zeros_like(latents), control), base)
        # the given latent frames (reference, seed frames 0 and 1-4) take the inactive latents whatever the mask says
        given = 1 + latent_frames(seeded)
        assert given == (1 if seeded == 0 else 3)
        with_given = model.base_latents(control, given)
        assert torch.equal(with_given[:, :, :given], control[:, :16, :given])
        assert torch.equal(with_given[:, :, given:], base[:, :, given:])
        if seeded:  # the mask alone would take the reactive latents of a blank video for seed frames 1-4
            assert not torch.equal(with_given[:, :, 2], base[:, :, 2])
        zero = torch.zeros_like(latents)
        assert torch.equal(model.from_flow(zero, control, given), with_given)
        assert torch.equal(model.to_flow(with_given, control, given), zero)
    assert model.residual_scale == model.config.residual_scale > 0
    model.config.size = "1.3B"  # real sizes: the flow runs on the latents (Wan's prior models them)
    try:
        assert model.residual_scale == 0.0 and torch.equal(model.to_flow(latents, control), latents)
    finally:
        model.config.size = "tiny"
    with pytest.raises(GraMiInputError, match="residual_scale"):
        RefinerConfig(residual_scale=-1.0).validate("refiner.json")


def test_training_sequences_from_fewer_cameras():
    """`train_cameras N`: training sequences from N evenly spaced training cameras; the selection sequence (first
    training camera) and the test sequences (held-out cameras) as before; more than the capture has is refused."""
    from gra_mi.capture.dataset import Capture, FrameLighting
    from gra_mi.core.errors import GraMiParameterError
    from gra_mi.refiner.data import CaptureSequencesConfig, _sequence_jobs

    frames = [FrameLighting(0, "train", 0, "uniform", None), FrameLighting(1, "train", 0, "envmap", "e.exr")]
    frames += [FrameLighting(2, "test", 0, "envmap", "t.exr")]
    capture = Capture(Path("cap"), "x", "path", 8, [f"cam0{i}" for i in range(6)], ["cam06", "cam07"], frames)
    jobs = _sequence_jobs(capture, CaptureSequencesConfig(train_cameras=3))
    assert [(split, cam) for split, cam, *_ in jobs] == [
        ("train", "cam00"), ("train", "cam02"), ("train", "cam05"), ("selection", "cam00"), ("test", "cam06"), ("test", "cam07"),
    ]  # fmt: skip
    assert len(_sequence_jobs(capture, CaptureSequencesConfig())) == 6 + 1 + 2
    with pytest.raises(GraMiParameterError, match="train_cameras"):
        _sequence_jobs(capture, CaptureSequencesConfig(train_cameras=7))


def test_sequences_leave_out_a_cameras_gaps():
    """A real capture's gaps (an import's --missing-images skip): a training sequence drops the frames its camera
    lacks; a held-out video keeps its longest unbroken run (no frame of it follows a gap); a camera without its uniformly
    lit reference takes the next one; a camera with no reference or no frame of its sequence is refused by name."""
    from gra_mi.capture.dataset import Capture, FrameLighting
    from gra_mi.core.errors import GraMiInputError
    from gra_mi.refiner.data import CaptureSequencesConfig, _sequence_jobs

    frames = [FrameLighting(0, "train", 0, "uniform", None), FrameLighting(1, "train", 0, "envmap", "e.exr")]
    frames += [FrameLighting(f, "test", 0, "envmap", "t.exr") for f in range(2, 10)]
    frames += [FrameLighting(10, "train", 0, "envmap", "e.exr"), FrameLighting(11, "train", 0, "uniform", None)]
    capture = Capture(Path("cap"), "x", "path", 8, ["cam00", "cam01"], ["cam06", "cam07"], frames)
    gaps = {1: ["cam01"], 0: ["cam01"], 4: ["cam07"], 7: ["cam00"]}
    for f in frames:
        f.missing = gaps.get(f.frame, [])
    jobs = {(split, cam): job for split, cam, *job in _sequence_jobs(capture, CaptureSequencesConfig())}
    frames_of = {key: [e.frame for e in job[0]] for key, job in jobs.items()}
    assert frames_of["train", "cam01"] == [10] and jobs["train", "cam01"][3] == [1] and jobs["train", "cam01"][2].frame == 11
    assert frames_of["test", "cam07"] == [5, 6, 7, 8, 9] and jobs["test", "cam07"][3] == [2, 3, 4]
    assert frames_of["selection", "cam00"] == [2, 3, 4, 5, 6]  # the longer run
    assert frames_of["test", "cam06"] == list(range(2, 10)) and jobs["test", "cam06"][3] == []
    frames[-1].missing = ["cam01"]
    with pytest.raises(GraMiInputError, match="camera cam01 has no image of a uniformly lit training frame"):
        _sequence_jobs(capture, CaptureSequencesConfig())
    frames[-1].missing = []
    for f in frames[2:10]:
        f.missing = ["cam06"]
    with pytest.raises(GraMiInputError, match="camera cam06 has no image of any frame of its test sequence"):
        _sequence_jobs(capture, CaptureSequencesConfig())
