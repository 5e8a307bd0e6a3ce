"""Commands of the learned stages: ``train-relightnet``, ``refiner-data``, ``train-refiner``, ``refine``,
``refiner-prompt``, ``deflicker``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from gra_mi.cli.options import CommandConfig, Restartable
from gra_mi.core.config import changed_options, option, options_need_switch
from gra_mi.core.errors import GraMiParameterError, require_positive
from gra_mi.core.limits import require_memory
from gra_mi.core.shard import ShardOptions
from gra_mi.refiner.config import RefinerConfig
from gra_mi.refiner.data import CaptureSequencesConfig
from gra_mi.refiner.deflicker import DeflickerConfig
from gra_mi.refiner.infer import RefineConfig
from gra_mi.refiner.train import RefinerTrainConfig
from gra_mi.relightnet.train import TrainConfig
from gra_mi.render.composite import PLATFORM_FLAGS, PlatformConfig

REFINER_MODEL_OPTIONS = ("size", "dtype", "lora_rank", "env_blocks", "prior", "seed")
REFINER_TRAIN_OPTIONS = ("steps", "lr", "grad_accumulation", "error_recycling", "bank_per_level", "checkpoint_every", "seed")
REFINER_TRAIN_OPTIONS += ("choose_mix", "selection_steps")


@dataclass(kw_only=True)
class TrainRelightnetCommand(Restartable):
    capture: Path = field(metadata=option(positional=True))
    """Capture folder."""
    fit: Path
    """Fit folder with albedo.exr and roughness.exr (from `gra-mi fit`)."""
    out: Path = Path("outputs/relightnet")
    """Output folder: weights, logs, plots, validation; a checkpoint makes reruns resume."""
    train: TrainConfig = field(default_factory=TrainConfig)


def run_train_relightnet(c: TrainRelightnetCommand) -> None:
    from gra_mi.relightnet.train import train_relightnet

    print(f"done: open {train_relightnet(c.capture, c.fit, c.out, c.train, c.overwrite)}")


SYNTHETIC_OPTIONS = ("subjects", "sequences", "resolution")
SYNTHETIC_FRAMES = 17  # a synthetic training sequence: one window
SYNTHETIC_BYTES_PER_PIXEL = 256  # the peak of making a synthetic sequence, per pixel and frame (measured: 50–62 bytes)


@dataclass(kw_only=True)
class RefinerDataCommand(Restartable):
    capture: Path | None = field(default=None, metadata=option(positional=True))
    """Capture folder (omit with --synthetic)."""
    fit: Path | None = None
    """Fit folder with albedo.exr and roughness.exr (from `gra-mi fit`)."""
    relightnet: Path | None = None
    """Trained RelightNet folder: coarse frames are its renders. Default: the microfacet render."""
    out: Path
    """Output folder (dataset.json + sequences/)."""
    sequences_config: CaptureSequencesConfig = field(default_factory=CaptureSequencesConfig)
    synthetic: bool = False
    """Synthetic sequences instead (a textured ball under a new light each frame): fast, for tests and trials."""
    subjects: int = 1
    """--synthetic: number of subjects."""
    sequences: int = 8
    """--synthetic: training sequences per subject."""
    resolution: int = 64
    """--synthetic: frame height and width (multiple of 16)."""
    shards: ShardOptions = field(default_factory=ShardOptions)

    def validate(self) -> None:
        super().validate()  # before the capture and fit are read (the shard included)
        if self.synthetic and not self.shards.resolved().whole:
            raise GraMiParameterError("shard", "--synthetic sequences are made in one process (seconds): drop --shard")
        require_positive({"subjects": self.subjects, "sequences": self.sequences, "resolution": self.resolution})
        if self.synthetic and self.resolution % 16:
            raise GraMiParameterError("resolution", f"must be a multiple of 16, got {self.resolution}")
        if not self.synthetic and (self.capture is None or self.fit is None):
            raise GraMiParameterError("capture", "give a capture folder and --fit (or --synthetic)")
        if not self.synthetic and (given := changed_options(self, SYNTHETIC_OPTIONS)):
            raise GraMiParameterError(given[0], "takes effect with --synthetic only: add --synthetic, or leave it out")
        if self.synthetic:  # the synthetic sequences read test_length and env_height alone, and no capture
            if any(getattr(self, n) is not None for n in ("capture", "fit", "relightnet")):
                raise GraMiParameterError("synthetic", "makes sequences of its own: drop the capture, --fit and --relightnet")
            if given := changed_options(self.sequences_config, ("scale", "zoom", "train_length", "train_cameras")):
                raise GraMiParameterError(given[0], "is an option of a capture's sequences: --synthetic makes its own")
            frames = max(SYNTHETIC_FRAMES, self.sequences_config.test_length)  # one sequence is made at a time
            require_memory("resolution", frames * self.resolution**2 * SYNTHETIC_BYTES_PER_PIXEL, f"a sequence of {frames} frames")


def run_refiner_data(c: RefinerDataCommand) -> None:
    from gra_mi.refiner.data import dataset_from_capture
    from gra_mi.refiner.synthetic import synthetic_dataset

    if c.synthetic:
        subjects = {s: (c.sequences, 1, 1) for s in range(c.subjects)}
        length, env_height = c.sequences_config.test_length, c.sequences_config.env_height
        ds = synthetic_dataset(c.out, subjects, SYNTHETIC_FRAMES, c.resolution, c.resolution, env_height, length, overwrite=c.overwrite)
    else:
        shard = c.shards.resolved()
        ds = dataset_from_capture(
            c.capture, c.fit, c.out, relightnet_dir=c.relightnet, config=c.sequences_config, overwrite=c.overwrite, shard=shard
        )  # fmt: skip
        if ds is None:
            print(f"shard {shard}: its sequences are in {c.out / 'parts'}; the shard that finishes last writes the dataset")
            return
    print(f"wrote {len(ds.sequences)} sequences ({ds.height}x{ds.width}) to {ds.folder}")


@dataclass(kw_only=True)
class TrainRefinerCommand(Restartable):
    data: Path = field(metadata=option(positional=True))
    """Refiner dataset folder (from `gra-mi refiner-data`)."""
    out: Path = Path("outputs/refiner")
    """Output folder: weights, logs, loss plot; a checkpoint makes reruns resume."""
    weights: Path | None = None
    """Real sizes: local diffusers WAN2.1-VACE folder, or original-format transformer checkpoint."""
    vae_weights: Path | None = None
    """With an original-format checkpoint: the Wan2.1 VAE checkpoint (Wan2.1_VAE.pth)."""
    prompt_embeds: Path | None = None
    """Real sizes: cached umT5 prompt embedding (from `gra-mi refiner-prompt`)."""
    init: Path | None = None
    """Start from a trained refiner (few-shot identity adaptation on a new subject's clips)."""
    model: RefinerConfig = field(default_factory=RefinerConfig, metadata=option(fields=REFINER_MODEL_OPTIONS))
    train: RefinerTrainConfig = field(default_factory=RefinerTrainConfig, metadata=option(fields=REFINER_TRAIN_OPTIONS))


def run_train_refiner(c: TrainRefinerCommand) -> None:
    from dataclasses import replace

    from gra_mi.refiner.train import train_refiner

    paths = {k: str(getattr(c, k)) if getattr(c, k) else None for k in ("weights", "vae_weights", "prompt_embeds")}
    out = train_refiner(c.data, c.out, c.train, replace(c.model, **paths), c.init, c.overwrite)
    print(f"done: weights and logs in {out}")


@dataclass(kw_only=True)
class RefineCommand(Restartable):
    data: Path = field(metadata=option(positional=True))
    """Refiner dataset folder holding the sequence."""
    model: Path
    """Trained refiner folder (from `gra-mi train-refiner`)."""
    sequence: str | None = None
    """Sequence name (default: the first test sequence)."""
    out: Path = Path("outputs/refined")
    """Output folder."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    deflicker: bool = False
    """Also write flicker-corrected frames (guided filter towards the coarse input; paper supplementary) to OUT/deflickered/."""
    flicker: DeflickerConfig = field(default_factory=DeflickerConfig)
    composite: bool = False
    """Also write composite.mp4: the frames over the environment on a platform with the subject's shadow (data made
    from a capture)."""
    platform: PlatformConfig = field(default_factory=PlatformConfig, metadata=option(renames=PLATFORM_FLAGS))

    def validate(self) -> None:
        super().validate()
        options_need_switch(self.flicker, self.deflicker, "--deflicker")
        options_need_switch(self.platform, self.composite, "--composite")


def run_refine(c: RefineCommand) -> None:
    from gra_mi.refiner.dataset import RefinerDataset
    from gra_mi.refiner.infer import refine_to_folder

    sequence = c.sequence
    if sequence is None:
        dataset = RefinerDataset(c.data)
        sequence = (dataset.names("test") or dataset.names())[0]
    deflicker, composite = c.flicker if c.deflicker else None, c.platform if c.composite else None
    summary = refine_to_folder(c.model, c.data, sequence, c.out, c.refine, deflicker=deflicker, composite=composite, overwrite=c.overwrite)
    rate = f"{summary['frames_per_second']:.2f} frames/s"
    print(f"refined {summary['frames']} frames in {summary['windows']} windows ({rate}) into {c.out}")
    if summary["mix"] < 1:
        said = "the input unchanged" if summary["mix"] == 0 else f"{summary['mix']:g} of the refiner's change"
        source = "--mix" if c.refine.mix is not None else f"chosen in training: {Path(c.model) / 'mix.md'}"
        print(f"delivered {said}: mix {summary['mix']:g} ({source})")


@dataclass(kw_only=True)
class RefinerPromptCommand(CommandConfig):
    pipeline: Path
    """Local diffusers WAN2.1(-VACE) folder with tokenizer/ and text_encoder/."""
    prompt: str = "a person, photorealistic, studio lighting"
    """The fixed prompt."""
    out: Path = field(metadata=option(writes=(".safetensors",)))
    """The .safetensors file to write."""


def run_refiner_prompt(c: RefinerPromptCommand) -> None:
    from gra_mi.refiner.loading import cache_prompt_embedding

    print(f"wrote {cache_prompt_embedding(c.pipeline, c.prompt, c.out)}")


@dataclass(kw_only=True)
class DeflickerCommand(CommandConfig):
    frames: Path = field(metadata=option(positional=True))
    """Folder of frames to correct (EXR, or PNG; sorted by name), e.g. a refine output's frames/."""
    stable: Path
    """Folder of the temporally stable renders of the same views (e.g. RelightNet's), one per frame, same size."""
    exposure: float | None = None
    """Linear → display exposure the filter works at (default: the first stable frame's 99th percentile at 0.8)."""
    flicker: DeflickerConfig = field(default_factory=DeflickerConfig)
    out: Path = Path("outputs/deflickered")
    """Output folder."""

    def validate(self) -> None:
        super().validate()
        if self.exposure is not None and not (math.isfinite(self.exposure) and self.exposure > 0):
            raise GraMiParameterError("exposure", f"must be a finite number > 0, got {self.exposure}")


def run_deflicker(c: DeflickerCommand) -> None:
    from gra_mi.refiner.deflicker import deflicker_folder

    written = deflicker_folder(c.frames, c.stable, c.out, c.flicker, c.exposure)
    print(f"deflickered {len(written)} frames into {c.out}")
