"""How much of the refiner's change to deliver, chosen on held-out data (as RelightNet's weights are chosen on its
selection views).

A generative refiner that has learnt nothing beyond its input still changes it: its samples carry the spread of
what it has seen. Delivering input + s·(refined − input) trades that spread against what it does know (s² of the
spread, (1 − s)² of the missing correction: the MSE-optimal s is a Wiener gain). Training measures the refiner on the
dataset's ``selection`` sequences (the held-out lighting on a training camera: never trained on, never scored by the
evaluation) at every candidate s and keeps the one the refined video's goal allows: PSNR no more than ``psnr_budget``
below the input's (the paper's full model gives up 0.41 dB), ꟻLIP and temporal error no worse than the input's,
and among those the lowest ꟻLIP. s = 0, the input itself, always qualifies, so a refiner that cannot earn its
place on the selection sequences delivers its input, and says so (train.json, mix.md).

"Mix" as a compositor's mix control; not diffusers' img2img ``strength``, which is ``gra-mi refine --denoise``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gra_mi.core.errors import GraMiInputError
from gra_mi.core.io import atomic_write_text, pyplot, save_figure
from gra_mi.core.metrics import compare, flip, temporal_error

MIXES = (0.0, 0.125, 0.25, 0.5, 0.75, 1.0)
PSNR_BUDGET = 0.4
"""dB of PSNR the refined video may give up for a better ꟻLIP and temporal error (the paper's full model: 0.41)."""


@dataclass
class MixScore:
    mix: float
    psnr: float
    flip: float
    temporal: float

    def qualifies(self, unchanged: MixScore, psnr_budget: float) -> bool:
        if self is unchanged:
            return True
        one_frame = not np.isfinite(unchanged.temporal)  # a one-frame sequence has no temporal error
        if not np.all(np.isfinite([self.psnr, self.flip] + ([] if one_frame else [self.temporal]))):
            return False  # a refiner whose output is not finite (diverged weights) never qualifies
        steady = one_frame or self.temporal <= unchanged.temporal
        return self.psnr >= unchanged.psnr - psnr_budget and self.flip <= unchanged.flip and steady


def choose_mix(scores: list[MixScore], psnr_budget: float = PSNR_BUDGET) -> MixScore:
    """The qualifying score with the lowest ꟻLIP (ties: the smaller mix); ``scores`` must hold mix 0."""
    unchanged = next((s for s in scores if s.mix == 0), None)
    if unchanged is None:
        raise ValueError("the scores need mix 0 (the input itself) to compare against")
    return min((s for s in scores if s.qualifies(unchanged, psnr_budget)), key=lambda s: (s.flip, s.mix))


def mix_scores(model, dataset, sequences: list[str], steps: int, shift: float, seed: int = 0, mixes=MIXES) -> list[MixScore]:
    """Refine the first window of each sequence once (mix 1), and score input + s·(refined − input) for every s
    against the ground truth: the delivered frames' display PSNR and ꟻLIP, and the temporal error, each averaged over
    the sequences. One window has no hand-off, so the blend is exactly what ``rollout(mix=s)`` delivers."""
    from gra_mi.refiner.dataset import video_to_image
    from gra_mi.refiner.infer import _subject, rollout

    if not sequences:
        raise GraMiInputError(dataset.folder / "dataset.json", "no selection sequence to choose the refiner's mix on")
    per_sequence = []
    for name in sequences:
        frames = min(model.config.window, dataset.sequences[name].frames)
        coarse_video = dataset.window(name, 0, frames)["coarse"]
        refined = {f.index: f.video for f in rollout(model, dataset, name, steps=steps, shift=shift, seed=seed, frames=frames, mix=1.0)}
        truth = [dataset.delivered(name, i, "target") for i in range(frames)]
        coarse = [dataset.delivered(name, i, "coarse") for i in range(frames)]
        masks = [_subject(c, t) for c, t in zip(coarse, truth, strict=True)]
        rows = []
        for s in mixes:
            images = []
            for i in range(frames):
                video = coarse_video[:, i] + s * (refined[i] - coarse_video[:, i])
                images.append(dataset.delivered(name, i, "coarse", video_to_image(video, dataset.exposure).permute(1, 2, 0).numpy()))
            rows.append(
                (
                    np.mean([compare(x, t, m)["psnr"] for x, t, m in zip(images, truth, masks, strict=True)]),
                    np.mean([flip(x, t, m) for x, t, m in zip(images, truth, masks, strict=True)]),
                    temporal_error(images, truth, masks, dataset.exposure),
                )
            )
        per_sequence.append(rows)
    mean = np.mean(np.asarray(per_sequence, np.float64), axis=0)
    return [MixScore(float(s), *(float(v) for v in row)) for s, row in zip(mixes, mean, strict=True)]


def write_mix_report(out: Path, scores: list[MixScore], chosen: MixScore, sequences: list[str], psnr_budget: float) -> dict:
    """``mix.md`` (the table and the choice in words) and ``mix.png``; returns what train.json records."""

    unchanged = next(s for s in scores if s.mix == 0)
    lines = [
        "# Refiner mix",
        "",
        f"Delivered: input + s·(refined − input), scored on the selection sequences ({', '.join(sequences)}; the first window of "
        f"each). A mix qualifies with PSNR at most {psnr_budget} dB below the input's and ꟻLIP and temporal error no "
        "worse; the qualifying one with the lowest ꟻLIP is kept.",
        "",
        "| mix | PSNR (dB) ↑ | ꟻLIP ↓ | temporal (%) ↓ | qualifies |",
        "|---|---|---|---|---|",
    ]
    for s in scores:
        mark = "**kept**" if s is chosen else ("yes" if s.qualifies(unchanged, psnr_budget) else "no")
        lines.append(f"| {s.mix:g} | {s.psnr:.2f} | {s.flip:.4f} | {100 * s.temporal:.2f} | {mark} |")
    if chosen.mix == 0:
        lines += ["", "No mix above 0 earns its place here: the refiner delivers its input unchanged (and samples nothing)."]
    atomic_write_text(out / "mix.md", "\n".join(lines) + "\n")
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(10, 3))
    for ax, key, label in zip(axes, ("psnr", "flip", "temporal"), ("PSNR (dB) ↑", "ꟻLIP ↓", "temporal error ↓"), strict=True):
        ax.plot([s.mix for s in scores], [getattr(s, key) for s in scores], "o-")
        ax.axvline(chosen.mix, color="0.6", ls="--")
        ax.set_xlabel("mix")
        ax.set_ylabel(label)
    fig.suptitle("Refiner mix on the selection sequences (dashed: kept)")
    fig.tight_layout()
    save_figure(fig, out / "mix.png")
    return {"chosen": chosen.mix, "psnr_budget": psnr_budget, "sequences": sequences, "scores": [vars(s) for s in scores]}
