"""The reflectance field of a capture: one image per LED (OLAT), and the image under any LED drive as their weighted sum.

Light is additive, so a camera's image under LED radiant intensities I (L, 3) is Σₖ (I[ℓₖ] / Iₖ) · OLATₖ, with ℓₖ the LED
of OLAT k and Iₖ its intensity in that frame (Debevec et al. 2000). Per colour channel this is a matrix product of the
drive weights (N lightings × K OLATs) with the OLAT stack (K × pixels), on the pixels any OLAT lights only.

The stack is held in memory when it fits ``memory_gb`` (float32, else float16 with one scale per OLAT, so an HDR
OLAT cannot overflow), and on the GPU too where torch uses one (the products run there); otherwise the OLATs are read
one at a time per batch of lightings (each OLAT read once per batch). Either way the result is the same sum; only the
time differs.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import binary_dilation

from gra_mi.capture.dataset import Capture, load_observation
from gra_mi.core.errors import GraMiInputError
from gra_mi.core.progress import progress

logger = logging.getLogger(__name__)

MISSING_SHARE_LIMIT = 0.02
"""A drive whose LEDs without an OLAT carry more than this share of its light cannot be summed (below it: their light
comes from their neighbours' OLATs, :func:`moved_to_neighbours`, with a warning)."""
NEIGHBOURS = 3  # the LEDs whose OLATs stand in for an LED without one: the nearest by direction from the stage centre
SUBJECT_MARGIN = 2  # pixels kept around the first OLAT's subject: a path-traced or matted edge moves between images
PIXEL_CHUNK = 1 << 16  # float16 stacks are widened to float32 this many pixels at a time


@dataclass
class OlatIndex:
    """Which frames of a capture are OLATs: frame, LED and that LED's RGB intensity in the frame."""

    frames: np.ndarray  # (K,) capture frame index
    leds: np.ndarray  # (K,) LED index
    intensity: np.ndarray  # (K, 3) the LED's radiant intensity in its OLAT
    num_leds: int
    directions: np.ndarray  # (L, 3) unit vectors from the stage centre to every LED
    distances: np.ndarray  # (L,) their distances from it

    @classmethod
    def of(cls, capture: Capture, stage, splits: tuple[str, ...] = ("train", "test")) -> OlatIndex:
        """Every frame of ``splits`` whose lighting is one LED (any split by default: an OLAT is a photograph either
        way; RelightNet's synthesized lightings sum the training ones only)."""
        frames, leds, intensity = [], [], []
        for entry in capture.frames:
            if entry.kind != "pattern" or entry.split not in splits:
                continue
            lighting = capture.lighting(stage, entry)
            lit = np.flatnonzero(lighting.max(axis=1) > 0)
            if lit.size == 1 and int(lit[0]) not in leds:
                frames.append(entry.frame)
                leds.append(int(lit[0]))
                intensity.append(lighting[lit[0]])
        if not frames:
            raise GraMiInputError(
                capture.folder / "capture.json", "no OLAT frames (a pattern lighting one LED): the capture holds no reflectance field"
            )
        directions = stage.led_directions()
        return cls(np.array(frames), np.array(leds), np.array(intensity, np.float64), stage.num_leds, directions, stage.led_distances())

    def lacking(self, capture: Capture, camera: str) -> np.ndarray:
        """The positions in this index of the OLATs ``camera`` has no image of (a real capture's gaps)."""
        missing = set(capture.frames_with_images(camera, [int(f) for f in self.frames])[1])
        return np.array([k for k, frame in enumerate(self.frames) if int(frame) in missing], np.int64)

    def light_from_neighbours(self, capture: Capture, camera: str, drives: dict) -> dict[str, float]:
        """Drive name → the share of its light (LED intensities (L, 3)) that ``camera`` takes from neighbouring OLATs:
        the light of the LEDs whose OLAT it has no image of (``{}`` for a camera with every one). A drive where that is
        more than :data:`MISSING_SHARE_LIMIT` is refused, naming it, the camera and the LEDs."""
        lacking = self.lacking(capture, camera)
        if not lacking.size:
            return {}
        for name, drive in drives.items():
            self.weights(drive, f"{name} on camera {camera}", lacking, quiet=True)
        leds = self.leds[lacking]
        return {name: float(np.sum(drive[leds]) / max(float(np.sum(drive)), 1e-30)) for name, drive in drives.items()}

    def weights(self, lighting: np.ndarray, source: str, lacking: np.ndarray | None = None, quiet: bool = False) -> np.ndarray:
        """(K, 3) weights of the OLATs for LED intensities (L, 3). The light of LEDs the capture has no OLAT of, or a
        camera has no image of (``lacking``: positions in this index), comes from their neighbours' OLATs
        (:func:`moved_to_neighbours`), with a warning (unless ``quiet``) while it is at most
        :data:`MISSING_SHARE_LIMIT` of the drive's light; above it the drive is refused, naming them."""
        lighting = np.asarray(lighting, np.float64)
        if lighting.shape != (self.num_leds, 3):
            raise GraMiInputError(source, f"expected ({self.num_leds}, 3) LED intensities, got {lighting.shape}")
        if not np.all(np.isfinite(lighting)) or lighting.min() < 0:
            raise GraMiInputError(source, "LED intensities must be finite and non-negative")
        usable = np.zeros(self.num_leds, bool)
        usable[self.leds] = True
        lacking = np.asarray([] if lacking is None else lacking, np.int64)
        usable[self.leds[lacking]] = False
        moved, gone, share = moved_to_neighbours(lighting, usable, self.directions, self.distances)
        if gone.size:
            named = ", ".join(str(i) for i in gone[:12]) + (" …" if gone.size > 12 else "")
            camera_gap = bool(np.isin(gone, self.leds).any())  # an OLAT the capture has, but not this camera's image of it
            if share > MISSING_SHARE_LIMIT:
                why = "which have no OLAT image of this camera" if camera_gap else "which have no OLAT in the capture"
                raise GraMiInputError(source, f"drives LEDs {named} ({100 * share:.1f} % of its light), {why}")
            if not quiet:
                logger.warning("%s: LEDs %s have no OLAT%s; their %.2f %% of the light comes from their %d nearest LEDs' OLATs",
                               source, named, " image of this camera" if camera_gap else "", 100 * share, NEIGHBOURS)  # fmt: skip
        weights = moved[self.leds] / np.maximum(self.intensity, 1e-30)
        weights[lacking] = 0.0
        return weights


def moved_to_neighbours(
    lighting: np.ndarray, usable: np.ndarray, directions: np.ndarray, distances: np.ndarray, neighbours: int = NEIGHBOURS
) -> tuple:
    """(``lighting`` with the light of the LEDs not ``usable`` moved onto their ``neighbours`` nearest usable LEDs,
    the LEDs it left, the share of the light it moved). Each neighbour takes a share inversely proportional to its angle
    from the LED, scaled by the ratio of their squared distances, so the subject receives the same light from about the
    same direction: light is smooth over a stage's neighbouring LEDs except at the shadows' and highlights' edges."""
    gone = np.flatnonzero(~usable & (lighting.max(axis=1) > 0))
    if not gone.size:
        return lighting, gone, 0.0
    share = float(lighting[gone].sum() / max(lighting.sum(), 1e-30))
    have = np.flatnonzero(usable)
    if not have.size:
        return np.zeros_like(lighting), gone, share
    cosines = directions[gone] @ directions[have].T
    nearest = np.argsort(-cosines, axis=1)[:, :neighbours]
    angles = np.arccos(np.clip(np.take_along_axis(cosines, nearest, axis=1), -1.0, 1.0))
    shares = 1.0 / np.maximum(angles, 1e-6)
    shares /= shares.sum(axis=1, keepdims=True)
    targets = have[nearest]
    scale = shares * (distances[targets] / distances[gone][:, None]) ** 2
    moved = lighting.copy()
    moved[gone] = 0.0
    np.add.at(moved, targets.ravel(), (scale[..., None] * lighting[gone][:, None, :]).reshape(-1, 3))
    return moved, gone, share


@dataclass
class ReflectanceField:
    """One camera's OLATs over the subject's pixels; :meth:`relight` sums them for any drive."""

    capture: Capture
    camera: str
    index: OlatIndex
    shape: tuple[int, int]  # (height, width)
    pixels: np.ndarray  # (P,) flat indices of the subject's pixels (the first OLAT's, grown by SUBJECT_MARGIN)
    alpha: np.ndarray  # (H, W) the subject's mask (the first OLAT's)
    stack: np.ndarray | None = None  # (3, K, P) held in memory, or None: streamed from disk
    scale: np.ndarray | None = None  # (K,) a float16 stack's per-OLAT scale
    stats: dict = field(default_factory=dict)
    lacking: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # OLATs (index positions) without an image
    _on_device: tuple | None = field(default=None, repr=False, compare=False)  # (device, the stack there)

    @classmethod
    def load(cls, capture: Capture, camera: str, index: OlatIndex, memory_gb: float = 4.0, progress_bar: bool = True) -> ReflectanceField:
        """The OLATs of one camera over the first OLAT's subject pixels (its mask and anything it lights, grown by
        ``SUBJECT_MARGIN``), held when they fit ``memory_gb``. Light another OLAT puts outside those pixels is counted
        (``stats``), not kept. OLATs a real capture's gaps left the camera without are :attr:`lacking`: their light
        comes from their neighbours' (:meth:`weights`)."""
        lacking = index.lacking(capture, camera)
        if lacking.size == len(index.frames):
            raise GraMiInputError(capture.folder / "capture.json", f"camera {camera} has no image of any OLAT", field="frames")
        gaps = set(lacking.tolist())
        present = [int(f) for k, f in enumerate(index.frames) if k not in gaps]
        first = load_observation(capture, camera, present[0])
        alpha = first[..., 3]
        subject = (alpha > 0) | (first[..., :3].max(axis=-1) > 0)
        pixels = np.flatnonzero(binary_dilation(subject, iterations=SUBJECT_MARGIN).ravel())
        field_ = cls(capture, camera, index, first.shape[:2], pixels, alpha, lacking=lacking)
        k, p = len(index.frames), pixels.size
        held = 2 * 3 * k * p <= memory_gb * 2**30
        if not held:
            field_.stats = {"held": "streamed from disk", "bytes": 0}
            return field_
        dtype = np.float32 if 4 * 3 * k * p <= memory_gb * 2**30 else np.float16
        field_.stack, field_.scale = np.empty((3, k, p), dtype), np.ones(k)
        outside = total = 0.0
        frames = progress(index.frames, description=f"OLATs {camera}") if progress_bar else index.frames
        for j, frame in enumerate(frames):
            if j in gaps:
                field_.stack[:, j] = 0.0  # its weight is always 0 (:meth:`weights`)
                continue
            rgb = load_observation(capture, camera, int(frame))[..., :3].reshape(-1, 3)
            values = rgb[pixels].T
            total += float(rgb.sum())
            outside += float(rgb.sum() - values.sum())
            if dtype == np.float16:  # an OLAT's own scale keeps HDR values inside float16's range
                field_.scale[j] = max(float(values.max()), 1e-30)
            field_.stack[:, j] = values / field_.scale[j]
        field_.stats = {
            "held": f"in memory ({np.dtype(dtype).name})",
            "bytes": int(field_.stack.nbytes),
            "light_outside": max(outside, 0.0) / max(total, 1e-30),
        }
        if outside > 1e-3 * total:
            logger.warning("%s: %.2f %% of the OLATs' light falls outside the first OLAT's subject pixels", camera, 100 * outside / total)
        return field_

    def weights(self, lighting: np.ndarray, source: str, quiet: bool = False) -> np.ndarray:
        """(K, 3) OLAT weights for LED intensities (L, 3) on this camera (:meth:`OlatIndex.weights`: the light of an
        OLAT the camera lacks comes from its neighbours')."""
        return self.index.weights(lighting, f"{source} on camera {self.camera}" if self.lacking.size else source, self.lacking, quiet)

    def relight(self, weights: np.ndarray) -> np.ndarray:
        """Images (N, H, W, 4) for OLAT weights (N, K, 3) (:meth:`weights`); alpha is the subject's mask."""
        weights = np.asarray(weights, np.float64)
        if weights.ndim == 2:
            weights = weights[None]
        if np.any(weights[:, self.lacking]):
            raise ValueError(f"weights for OLATs camera {self.camera} has no image of: use ReflectanceField.weights")
        n = weights.shape[0]
        sums = self._sum_held(weights) if self.stack is not None else self._sum_streamed(weights)
        out = np.zeros((n, self.shape[0] * self.shape[1], 4), np.float32)
        out[:, self.pixels, :3] = np.maximum(sums, 0.0)
        out[..., 3] = self.alpha.ravel()[None]
        return out.reshape(n, *self.shape, 4)

    def _sum_held(self, weights: np.ndarray) -> np.ndarray:
        stack = self._device_stack()
        if stack is not None:
            return self._sum_on_device(weights, stack)
        n, p = weights.shape[0], self.pixels.size
        sums = np.empty((n, p, 3), np.float32)
        w = (weights * self.scale[None, :, None]).astype(np.float32)
        for c in range(3):
            if self.stack.dtype == np.float32:
                sums[..., c] = w[..., c] @ self.stack[c]
                continue
            for start in range(0, p, PIXEL_CHUNK):  # float16 has no BLAS: widen one chunk at a time
                block = self.stack[c, :, start : start + PIXEL_CHUNK].astype(np.float32)
                sums[:, start : start + PIXEL_CHUNK, c] = w[..., c] @ block
        return sums

    @property
    def summed_on(self) -> str:
        """Where :meth:`relight` has summed the held stack: the torch GPU device, or the host."""
        return self._on_device[0] if self._on_device is not None and self._on_device[1] is not None else "host (NumPy)"

    def _device_stack(self, device: str | None = None):
        """The held stack on the GPU the command's torch uses (uploaded once), or None: no GPU, or too little of its
        memory free (said once; the sum is then NumPy's on the host). ``device``: another torch device (a test's)."""
        if device is None:
            from gra_mi.core.runtime import torch_device

            device = torch_device()
            if not device.startswith("cuda"):
                return None
        if self._on_device is None or self._on_device[0] != device:
            import torch

            if device.startswith("cuda") and self.stack.nbytes > 0.8 * torch.cuda.mem_get_info(torch.device(device))[0]:
                logger.warning(
                    "%s: the OLAT stack (%.1f GB) stays on the host: too little GPU memory free", self.camera, self.stack.nbytes / 1e9
                )
                self._on_device = (device, None)
            else:
                self._on_device = (device, torch.from_numpy(self.stack).to(device))
        return self._on_device[1]

    def _sum_on_device(self, weights: np.ndarray, stack) -> np.ndarray:
        """:meth:`_sum_held` on the stack's device: the same products, float16 widened a chunk at a time there."""
        import torch

        n, p = weights.shape[0], self.pixels.size
        w = torch.from_numpy((weights * self.scale[None, :, None]).astype(np.float32)).to(stack.device)
        sums = torch.empty((n, p, 3), dtype=torch.float32, device=stack.device)
        chunk = p if stack.dtype == torch.float32 else PIXEL_CHUNK
        for c in range(3):
            for start in range(0, p, chunk):
                sums[:, start : start + chunk, c] = w[..., c] @ stack[c, :, start : start + chunk].float()
        return sums.cpu().numpy()

    def _sum_streamed(self, weights: np.ndarray) -> np.ndarray:
        sums = np.zeros((weights.shape[0], self.pixels.size, 3), np.float64)
        for j, frame in enumerate(self.index.frames):
            if not np.any(weights[:, j]):
                continue  # an LED no lighting of the batch drives is not read (nor one the camera has no image of)
            image = load_observation(self.capture, self.camera, int(frame))[..., :3].reshape(-1, 3)[self.pixels]
            sums += weights[:, j][:, None, :] * image[None]
        return sums.astype(np.float32)


def static_pose(capture: Capture) -> int:
    """The one mesh frame of a static capture; a capture with several poses (a moving subject) has no reflectance field."""
    poses = {f.mesh_frame for f in capture.frames}
    if len(poses) != 1:
        raise GraMiInputError(
            capture.folder / "capture.json", f"{len(poses)} poses: a reflectance field needs a static capture (one pose lit by OLATs)"
        )
    return poses.pop()
