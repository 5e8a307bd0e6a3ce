"""Pack what the GPU machine's image lacks of gra-mi's dependencies into ``.gpu/site.tar.xz``, for its Python.

The lent GPU machines (/work/.library/device) reach no package index and take at most 64 MiB of working tree and
carried files per call; Mitsuba's wheel alone is 63 MB. So: gra-mi's dependencies (pyproject.toml, resolved through
this environment's installed metadata) that the image does not have, at this environment's versions, as wheels for
the machine's Python, with every file of 64 KiB or more that the CPU rehearsal of the check never opened or mapped
left out (``.gpu/trace.txt``, written by ``scripts/gpu_check.sh --cpu``; a variant's library keeps its CUDA twin).

    .venv/bin/python scripts/gpu/pack.py [--python 3.12] [--out .gpu]
"""

from __future__ import annotations

import argparse
import importlib.metadata as metadata
import os
import re
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from pathlib import Path

import tomllib
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[2]
LIMIT = 64 * 2**20  # what a device call carries, working tree included
KEEP_UNTRACED_BELOW = 64 * 2**10

# The GPU image's packages ('cuda' image, /work/.library/device/KINDS.md, read 2026-11-17).
IMAGE_HAS = """absl-py accelerate aiofiles aiohappyeyeballs aiohttp aiosignal annotated-doc anyio attrs botorch build certifi
charset-normalizer chex click cloudpickle cmake colorama contourpy coverage cuda-bindings cuda-core cuda-pathfinder
cuda-toolkit cupy-cuda13x cycler cython diffrax e3nn einops equinox etils execnet filelock flatbuffers flax fonttools
formulaic frozenlist fsspec gpytorch grpcio h11 h5py hf-xet httpcore httpx huggingface-hub humanize hypothesis idna imageio iniconfig
interface-meta jax jax-cuda13-pjrt jax-cuda13-plugin jaxlib jaxtyping jinja2 joblib kiwisolver lazy-loader lightning
lightning-utilities linear-operator lineax llvmlite lxml markdown markdown-it-py markupsafe matplotlib mdurl meson
ml-dtypes mpi4py mpmath msgpack multidict multipledispatch mypy-extensions nanobind narwhals networkx ninja numba
numba-cuda numpy numpyro nvidia-cublas nvidia-cuda-cupti nvidia-cuda-nvrtc nvidia-cuda-runtime nvidia-cudnn-cu13
nvidia-cufft nvidia-cufile nvidia-curand nvidia-cusolver nvidia-cusparse nvidia-cusparselt-cu13 nvidia-ml-py
nvidia-nccl-cu13 nvidia-nvjitlink nvidia-nvshmem-cu13 nvidia-nvtx onnx onnx-ir onnxruntime onnxscript
opencv-python-headless optax opt-einsum opt-einsum-fx optimistix orbax-checkpoint packaging pandas pathspec patsy peft
pillow pip pluggy portalocker prometheus-client propcache protobuf psutil pyarrow pybind11 py-cpuinfo pygments
pyparsing pyproject-hooks pyre-extensions pytest pytest-benchmark pytest-cov pytest-mock pytest-timeout pytest-xdist
python-dateutil pytorch-lightning pyyaml regex requests rich sacrebleu safetensors scikit-build-core scikit-image
scikit-learn scipy seaborn sentencepiece sentence-transformers setuptools shellingham simplejson six sortedcontainers
statsmodels sympy tabulate tensorboard tensorboard-data-server tensorstore threadpoolctl tifffile tiktoken timm
tokenizers toolz torch torchaudio torchdiffeq torch-geometric torchmetrics torchvision tqdm transformers treescope
triton typer typing-extensions typing-inspect urllib3 uvloop wadler-lindig werkzeug wheel wrapt xarray xxhash yarl
zipp""".split()

# Left behind, each with what the check does without it.
TOO_BIG = {
    "warp-lang": "anny skins with torch instead (its own fallback; the same meshes)",
    "usd-core": "130 MB of libraries: the demo's USD export is reported as not made",
    "imageio-ffmpeg": "a 165 MB ffmpeg: MP4 previews are reported as not made (unless the machine has an ffmpeg)",
}
PLATFORMS = [f"manylinux_2_{n}_x86_64" for n in (17, 24, 27, 28, 31, 34, 35)] + ["manylinux2014_x86_64", "manylinux1_x86_64", "any"]


def norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def needed(python: str) -> dict[str, str]:
    """{distribution: version} of gra-mi's dependencies, recursively, that the image lacks (and that fit)."""
    environment = {"python_version": python, "python_full_version": f"{python}.0", "extra": ""}
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    todo, found = [Requirement(r) for r in project["dependencies"]], {}
    image = {norm(n) for n in IMAGE_HAS}
    while todo:
        req = todo.pop()
        name = norm(req.name)
        if name in image or name in found or norm(req.name) in TOO_BIG or (req.marker and not req.marker.evaluate(environment)):
            continue
        found[name] = metadata.version(req.name)
        todo += [Requirement(r) for r in metadata.requires(req.name) or []]
    return found


def download(wheels: dict[str, str], python: str, folder: Path) -> list[Path]:
    pins = [f"{name}=={version}" for name, version in sorted(wheels.items())]
    platforms = [arg for p in PLATFORMS for arg in ("--platform", p)]
    command = [sys.executable, "-m", "pip", "download", "-q", "--no-deps", "--only-binary=:all:", "--implementation", "cp"]
    subprocess.run([*command, "--python-version", python, *platforms, "-d", str(folder), *pins], check=True)
    return sorted(folder.glob("*.whl"))


def traced(trace: Path) -> set[str]:
    """Site-relative paths the rehearsal touched, ABI tags and the CUDA/LLVM variant twins made alike."""
    lines = [os.path.normpath(line) for line in trace.read_text().split("\n")]  # a library's RPATH: x/../x.libs/
    paths = {line.split("site-packages/", 1)[1] for line in lines if "site-packages/" in line}
    return {same_key(p) for p in paths}


def same_key(path: str) -> str:
    """A module's source and its compiled cache (what an import opens) alike, any Python's, and a variant's library
    alike for the CPU and the GPU."""
    path = re.sub(r"__pycache__/([^/]+?)\.cpython-3\d+(\.opt-\d)?\.pyc$", r"\1.py", path)
    return re.sub(r"cpython-3\d+", "cpython-3x", path).replace("cuda_ad_", "llvm_ad_")


def pack(wheels: list[Path], used: set[str], out: Path) -> list[tuple[str, int, int]]:
    """Write ``out`` (tar.xz); per wheel (name, bytes kept, bytes left out)."""
    rows = []
    with tarfile.open(out, "w:xz", preset=6) as tar:
        for wheel in wheels:
            kept = dropped = 0
            with zipfile.ZipFile(wheel) as archive:
                for info in archive.infolist():
                    if info.is_dir() or "__pycache__" in info.filename:
                        continue
                    if info.file_size >= KEEP_UNTRACED_BELOW and same_key(info.filename) not in used:
                        dropped += info.file_size
                        continue
                    kept += info.file_size
                    entry = tarfile.TarInfo(info.filename)
                    entry.size, entry.mode = info.file_size, (info.external_attr >> 16) or 0o644
                    with archive.open(info) as data:
                        tar.addfile(entry, data)
            rows.append((wheel.name, kept, dropped))
    return rows


def tree_bytes() -> int:
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=REPO, capture_output=True, check=True).stdout
    return sum((REPO / f).stat().st_size for f in files.decode().split("\0") if f and (REPO / f).is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--python", default="3.12", help="The GPU machine's Python (major.minor). Default: 3.12.")
    parser.add_argument("--out", type=Path, default=REPO / ".gpu", help="Folder of site.tar.xz and trace.txt. Default: .gpu")
    args = parser.parse_args()
    trace = args.out / "trace.txt"
    if not trace.is_file():
        sys.exit(f"pack: {trace} is missing: run `bash scripts/gpu_check.sh --cpu` first (it records the files the check uses)")
    wheels = needed(args.python)
    with tempfile.TemporaryDirectory() as folder:
        rows = pack(download(wheels, args.python, Path(folder)), traced(trace), args.out / "site.tar.xz")
    for name, kept, dropped in rows:
        print(f"{name:80s} kept {kept / 2**20:7.1f} MiB, left out {dropped / 2**20:7.1f} MiB")
    for name, why in TOO_BIG.items():
        print(f"not carried: {name}: {why}")
    size, tree = (args.out / "site.tar.xz").stat().st_size, tree_bytes()
    print(
        f"{args.out / 'site.tar.xz'}: {size / 2**20:.1f} MiB; with the working tree {(size + tree) / 2**20:.1f} of {LIMIT / 2**20:.0f} MiB"
    )
    if size + tree > LIMIT:
        sys.exit("pack: over the device call's limit")


if __name__ == "__main__":
    main()
