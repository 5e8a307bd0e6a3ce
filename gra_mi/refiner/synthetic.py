"""Synthetic refiner sequences, a fast stand-in for the pipeline's in tests, CI and benchmarks: a textured ball moving
under a different light each frame, whose coarse render lacks the texture's fine detail and the highlight."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gra_mi.core.provenance import claim_output
from gra_mi.refiner.dataset import RefinerDataset, write_dataset_json, write_sequence
from gra_mi.stage.envmap import pixel_directions


def _latlong_dirs(h: int) -> np.ndarray:

    return pixel_directions(h, 2 * h)


def synthetic_sequence(frames: int, height: int, width: int, env_height: int, subject_seed: int, seed: int) -> dict[str, np.ndarray]:
    """A ball with a subject-specific fine texture moving and turning under a new light each frame.

    target = texture · (ambient + sun·cos) + a specular highlight; coarse = a blurred texture under the same diffuse
    light (no highlight) — the kind of gap the refiner closes. Envmaps: the ambient colour + a sun blob, camera space.
    """
    rng = np.random.default_rng(seed)
    srng = np.random.default_rng(10_000 + subject_seed)
    freq, colors = srng.uniform(6, 14, 2), srng.uniform(0.15, 0.9, (2, 3))
    y, x = np.meshgrid((np.arange(height) + 0.5) / height, (np.arange(width) + 0.5) / width, indexing="ij")
    dirs = _latlong_dirs(env_height)
    phase0, speed = rng.uniform(0, 2 * math.pi), rng.uniform(0.15, 0.35)
    sun_az, sun_el = rng.uniform(0, 2 * math.pi), rng.uniform(-0.3, 1.0)
    out = {k: [] for k in ("coarse", "target", "env")}
    radius = 0.32 * min(height, width) / width  # in units of the image width

    def render(t: float, light_dir, sun, ambient, textured: bool):
        cx = 0.5 + 0.22 * math.sin(phase0 + speed * t)
        cy = 0.5 + 0.08 * math.cos(phase0 + 0.7 * speed * t)
        px, py = (x - cx) * width / height, (y - cy)
        r = radius * width / height
        d2 = (px**2 + py**2) / r**2
        inside = d2 < 1
        nz = np.sqrt(np.clip(1 - d2, 0, 1))
        n = np.stack([px / r, -py / r, nz], -1)
        u = np.arctan2(n[..., 0], n[..., 2]) + 0.4 * speed * t  # the ball turns: texture moves over it
        pattern = 0.5 + 0.5 * np.sin(freq[0] * u) * np.sin(freq[1] * n[..., 1] * 3)
        if not textured:
            pattern = np.full_like(pattern, 0.5)  # the coarse render's texture has lost the fine detail
        albedo = colors[0] * pattern[..., None] + colors[1] * (1 - pattern[..., None])
        cos = np.clip(n @ light_dir, 0, None)[..., None]
        image = albedo * (ambient + sun * cos)
        if textured:
            h = light_dir + np.array([0, 0, 1.0])
            h /= np.linalg.norm(h)
            image = image + 0.6 * sun * np.clip(n @ h, 0, None)[..., None] ** 40
        return (image * inside[..., None]).astype(np.float32)

    for t in range(frames):
        az = sun_az + 0.35 * t
        el = sun_el + 0.3 * math.sin(0.5 * t)
        light_dir = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
        sun = rng.uniform(0.4, 1.2, 3) * np.array([1.0, 0.9, 0.8])
        ambient = rng.uniform(0.05, 0.25, 3)
        env = ambient + sun * 40 * np.exp((dirs @ light_dir - 1) / 0.01)[..., None]
        out["env"].append(env.astype(np.float32))
        out["target"].append(render(t, light_dir, sun, ambient, True))
        out["coarse"].append(render(t, light_dir, sun, ambient, False))
    neutral = np.array([0.0, 0.0, 1.0])
    reference = render(0, neutral, np.full(3, 0.3), np.full(3, 0.6), True)
    return {
        **{k: np.stack(v) for k, v in out.items()},
        "reference": reference,
        "reference_env": np.full((env_height, 2 * env_height, 3), 0.6, np.float32),
    }


def synthetic_dataset(
    folder: str | Path,
    subjects: dict[int, tuple[int, int]],
    frames: int = 17,
    height: int = 64,
    width: int = 64,
    env_height: int = 16,
    test_frames: int = 0,
    seed: int = 0,
    overwrite: bool = False,
) -> RefinerDataset:
    """subjects: subject seed → (number of training sequences, number of test sequences of ``test_frames``[, number
    of selection sequences of ``test_frames``])."""

    config = {"subjects": {str(k): list(v) for k, v in subjects.items()}, "frames": frames, "height": height, "width": width}
    config |= {"env_height": env_height, "test_frames": test_frames, "seed": seed}
    folder = claim_output(folder, "refiner-data --synthetic", {}, config, overwrite=overwrite)
    entries = []
    k = seed
    for subject, (n_train, n_test, *n_selection) in subjects.items():
        counts = (("train", n_train, frames), ("test", n_test, test_frames or frames))
        for split, count, length in counts + (("selection", sum(n_selection), test_frames or frames),):
            for i in range(count):
                name = f"s{subject}_{split}{i:02d}"
                k += 1
                rel = write_sequence(folder, name, synthetic_sequence(length, height, width, env_height, subject, k))
                entries.append({"name": name, "split": split, "frames": length, "subject": f"synthetic{subject}", "file": rel})
    write_dataset_json(folder, entries, height, width, (height, width), exposure=1.0, env_exposure=2.0, source="synthetic")
    return RefinerDataset(folder)
