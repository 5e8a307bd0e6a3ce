"""The runtime of a command: the Mitsuba variant (with gra-mi's plugins registered for it) and the torch device.

Each command starts it once (:func:`start_runtime`, called by the CLI before the command's library function); library
code asks for what it needs with :func:`ensure_mitsuba` and :func:`torch_device` and never chooses either itself.
The two are independent: the Mitsuba variant follows Dr.Jit's backends, the torch device follows torch's CUDA, so a
torch-only command (``train-refiner``, ``refine``) uses the GPU where one works without loading Mitsuba at all.

``llvm_ad_rgb`` is the default variant; ``cuda_ad_rgb`` is picked automatically where a CUDA device works. The Dr.Jit LLVM
backend needs libLLVM >= 16 (Dr.Jit 1.5 aborts the process on Debian's libLLVM 14/15 with
``LLVM ERROR: Cannot select ... fminimum``); :func:`check_llvm` finds a usable one *before* Dr.Jit loads, so users get a
message that says what to do instead of a crash.
"""

from __future__ import annotations

import glob
import logging
import os
import re
from dataclasses import dataclass

import numpy as np

from gra_mi.core.errors import GraMiInputError, GraMiParameterError

logger = logging.getLogger(__name__)

SUPPORTED_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
"""The JIT variants: gra-mi's kernels (visibility, shading, rasterisation, the fit) are vectorised Dr.Jit code."""
MIN_LLVM_MAJOR = 16
LLVM_HELP = (
    "Dr.Jit 1.5's LLVM backend needs libLLVM >= 16 (Debian 12 ships 14/15, which crash with "
    "'LLVM ERROR: Cannot select ... fminimum'). Install one with `sudo apt-get install libllvm19` "
    "(or run scripts/setup.sh), or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= 16."
)


def _llvm_major(path: str) -> int | None:
    match = re.search(r"libLLVM[-.]?(\d+)", os.path.basename(path))
    return int(match.group(1)) if match else None


def find_libllvm() -> str | None:
    """The newest libLLVM >= 16 on this machine, or None."""
    patterns = [
        "/usr/lib/*/libLLVM-*.so*",
        "/usr/lib/llvm-*/lib/libLLVM*.so*",
        "/usr/lib/libLLVM*.so*",
        "/usr/local/lib/libLLVM*.so*",
        "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    ]
    found = []
    for pattern in patterns:
        for path in glob.glob(pattern):
            major = _llvm_major(path)
            if major is None and "llvm-" in path:
                major = int(re.search(r"llvm-(\d+)", path).group(1))
            if major is not None and major >= MIN_LLVM_MAJOR:
                found.append((major, path))
    return max(found)[1] if found else None


def check_llvm() -> None:
    """Make sure Dr.Jit's LLVM backend will load a libLLVM it can use; raise with instructions otherwise."""
    configured = os.environ.get("DRJIT_LIBLLVM_PATH")
    if configured:
        if not os.path.exists(configured):
            raise GraMiInputError("DRJIT_LIBLLVM_PATH", f"'{configured}' does not exist. {LLVM_HELP}")
        return
    path = find_libllvm()
    if path is None:
        raise GraMiInputError("libLLVM", f"no libLLVM >= {MIN_LLVM_MAJOR} found. {LLVM_HELP}")
    # Dr.Jit searches the default library names itself and may pick libLLVM-14 first: pin the good one.
    os.environ["DRJIT_LIBLLVM_PATH"] = path


def cuda_available() -> bool:
    """True where Dr.Jit can start its CUDA backend (a driver and a device are present)."""
    if not glob.glob("/dev/nvidia[0-9]*") and not os.environ.get("GRA_MI_ASSUME_CUDA"):
        return False
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # no driver: Dr.Jit raises on probing
        return False


def gpu_count() -> int:
    """GPUs the driver exposes on this machine (device nodes; CUDA is not started to count them)."""
    return len([p for p in glob.glob("/dev/nvidia*") if p[len("/dev/nvidia") :].isdigit()])


def bind_local_gpu(env=None, gpus: int | None = None) -> str | None:
    """One process per GPU: under ``torchrun`` (``LOCAL_RANK``) or ``srun`` (``SLURM_LOCALID``), show this process
    only the GPU of its local rank (``CUDA_VISIBLE_DEVICES``), before Dr.Jit or torch start CUDA, so that
    ``cuda_ad_rgb`` and torch's ``cuda`` are that GPU (each Dr.Jit process uses one device). A launcher that already
    gave each process one GPU is left alone; more ranks than GPUs share them round-robin. Returns the GPU bound,
    or None (no launcher, or no GPU)."""
    env = os.environ if env is None else env
    local = env.get("LOCAL_RANK", env.get("SLURM_LOCALID"))
    if local is None:
        return None
    try:
        rank = int(local)
    except ValueError:
        raise GraMiInputError("$LOCAL_RANK", f"expected an integer, got '{local}'") from None
    visible = env.get("CUDA_VISIBLE_DEVICES")
    devices = [d.strip() for d in visible.split(",") if d.strip()] if visible is not None else None
    if devices is None:
        devices = [str(i) for i in range(gpu_count() if gpus is None else gpus)]
    if len(devices) <= 1:
        return devices[0] if devices else None
    chosen = devices[rank % len(devices)]
    if rank >= len(devices):
        logger.warning("local rank %d of more ranks than the %d GPUs: sharing GPU %s", rank, len(devices), chosen)
    env["CUDA_VISIBLE_DEVICES"] = chosen
    return chosen


def choose_variant(requested: str | None = None) -> str:
    """Set the Mitsuba variant for this process and return its name.

    ``requested=None`` means automatic: ``cuda_ad_rgb`` where CUDA works, else ``llvm_ad_rgb``.
    """
    if requested is not None and requested not in SUPPORTED_VARIANTS:
        raise GraMiParameterError("variant", f"unknown variant '{requested}', expected one of {SUPPORTED_VARIANTS}")
    variant = requested or ("cuda_ad_rgb" if cuda_available() else "llvm_ad_rgb")
    if variant.startswith("cuda") and not cuda_available():
        raise GraMiParameterError("variant", f"{variant} needs a working CUDA GPU and driver, and none was found; use llvm_ad_rgb (CPU)")
    if variant.startswith("llvm"):
        check_llvm()
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    logger.debug("Mitsuba variant: %s", variant)
    return variant


TORCH_DEVICES = ("cpu", "cuda")


@dataclass
class Runtime:
    """What a command runs on. ``None``: not needed by this command (yet)."""

    variant: str | None = None
    torch_device: str | None = None


RUNTIME = Runtime()  # one per process, like Mitsuba's own variant


def pick_torch_device(requested: str | None = None) -> str:
    """``cuda`` where torch sees a GPU, else ``cpu``; ``requested`` (cpu, cuda, cuda:N) overrides."""
    import torch

    if requested is None:
        return "cuda" if torch.cuda.is_available() else "cpu"
    if requested.split(":")[0] not in TORCH_DEVICES:
        raise GraMiParameterError("device", f"unknown torch device '{requested}', expected cpu, cuda or cuda:N")
    if requested.startswith("cuda") and not torch.cuda.is_available():
        raise GraMiParameterError("device", f"'{requested}' asked for, but torch sees no CUDA GPU (use cpu)")
    return requested


def torch_device() -> str:
    """The torch device for library code: the one this command started with, else the automatic choice."""
    if RUNTIME.torch_device is None:
        RUNTIME.torch_device = pick_torch_device()
    return RUNTIME.torch_device


def columns(value) -> np.ndarray:
    """A Dr.Jit vector (``mi.Color3f``, ``mi.Point2f``, …) as an (N, C) NumPy array, read component by component.

    ``np.array(vector)`` runs a kernel whose component offsets (N, 2N) are literals: one kernel per array size, each
    compiled once and kept in memory. A fit's views each have their own size; read this way, none compiles anything.
    """
    import drjit as dr

    dr.eval(value)
    return np.stack([np.asarray(value[i]) for i in range(len(value))], axis=1)


def segment(origin, direction, maxt):
    """A ray that stops at ``maxt`` (a shadow ray's segment to a light or a camera). ``mi.Ray3f(o, d, x)`` would not do:
    its third argument is the ray's *time*, and the ray then runs on past the light, where a floor or another body
    part would shadow what the light does reach."""
    import mitsuba as mi

    ray = mi.Ray3f(origin, direction)
    ray.maxt = maxt
    return ray


def opaque(kind, values):
    """A Mitsuba vector type (``mi.Point3f``, ``mi.Color3f``, ``mi.Float``) holding ``values`` as opaque device variables.

    Python floats in Dr.Jit code become literals baked into the kernel: a camera or a light that moves would make a
    new kernel (an LLVM compile, 20-60 ms) at every position. Opaque values are kernel inputs, so one kernel serves
    every position (a viewer orbiting, a light dragged, a video's frames, a rig's cameras).
    """
    import drjit as dr
    import mitsuba as mi

    values = [float(v) for v in (values if hasattr(values, "__len__") else [values])]
    scalars = [dr.opaque(mi.Float, v) for v in values]
    return scalars[0] if kind is mi.Float else kind(*scalars)


def concat(kind, arrays: list):
    """One array of ``kind`` (``mi.Float``, ``mi.UInt32``, a vector or a struct of them: ``mi.Point3f``,
    ``mi.Frame3f``) holding ``arrays`` one after another, without leaving the device.

    ``drjit.concat`` writes each piece at a literal offset: one kernel (an LLVM compile) per piece. Here the offset is
    a kernel input, so joining hundreds of a fit's views compiles one kernel per type.
    """
    import drjit as dr
    import mitsuba as mi

    if len(arrays) == 1:
        return arrays[0]
    out = dr.empty(kind, sum(dr.width(a) for a in arrays))
    start = 0
    for a in arrays:
        n = dr.width(a)
        if n:
            dr.scatter(out, a, dr.arange(mi.UInt32, n) + dr.opaque(mi.UInt32, start))
        start += n
    dr.eval(out)
    return out
