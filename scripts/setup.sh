#!/usr/bin/env bash
# Set up gra-mi on a fresh Debian/Ubuntu machine (no GPU needed): a libLLVM that Dr.Jit 1.5 can use, a virtual
# environment in .venv, and the package with its test tools. Safe to run again: it only does what is missing.
set -euo pipefail
cd "$(dirname "$0")/.."

say() { printf 'setup: %s\n' "$*" >&2; }

# 1. libLLVM >= 16. Dr.Jit 1.5's CPU backend aborts on Debian 12's libLLVM 14/15 ("Cannot select ... fminimum").
have_llvm() {
    [ -n "${DRJIT_LIBLLVM_PATH:-}" ] && [ -e "$DRJIT_LIBLLVM_PATH" ] && return 0
    local f
    for f in /usr/lib/*/libLLVM-*.so* /usr/lib/llvm-*/lib/libLLVM*.so*; do
        [[ "$f" =~ (libLLVM-|llvm-)([0-9]+) ]] && [ "${BASH_REMATCH[2]}" -ge 16 ] && return 0
    done
    return 1
}
if ! have_llvm; then
    SUDO=""
    [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
    if command -v apt-get >/dev/null && { [ "$(id -u)" -eq 0 ] || [ -n "$SUDO" ]; }; then
        say "installing libllvm19 for Dr.Jit (apt-get)"
        $SUDO apt-get update -qq
        $SUDO apt-get install -y -qq libllvm19 >/dev/null || $SUDO apt-get install -y -qq libllvm16 >/dev/null
    fi
    if ! have_llvm; then
        say "Dr.Jit needs libLLVM >= 16. Install it (Debian/Ubuntu: 'sudo apt-get install libllvm19'),"
        say "or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version 16 or newer, then run this script again."
        exit 1
    fi
fi

# 2. Chromium and its driver, for the browser test of `gra-mi view` (skipped, saying so, where they cannot be installed).
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
    SUDO=""
    [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
    if command -v apt-get >/dev/null && { [ "$(id -u)" -eq 0 ] || [ -n "$SUDO" ]; }; then
        say "installing chromium and chromium-driver for the viewer's browser test (apt-get)"
        { $SUDO apt-get update -qq && $SUDO apt-get install -y -qq chromium chromium-driver >/dev/null; } || say "chromium not installed: the browser test will be skipped"
    fi
fi

# 3. Virtual environment and packages.
PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    say "creating .venv with $($PYTHON --version)"
    "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip install -q --disable-pip-version-check)
if ! .venv/bin/python -c "import torch" 2>/dev/null; then
    say "installing torch"
    "${PIP[@]}" "torch==2.13.0" || "${PIP[@]}" torch
fi
if ! .venv/bin/python -c "import gra_mi, mitsuba, drjit, anny, pytest" 2>/dev/null || [ pyproject.toml -nt .venv/.gra-mi-installed ]; then
    say "installing gra-mi and its dependencies"
    "${PIP[@]}" -e ".[dev]"
    touch .venv/.gra-mi-installed
fi

# 4. What `gra-mi export`'s checks use, each skipped (saying so) where it cannot be installed: the Khronos glTF-Validator
#    (npm, ~0.4 MB, into .tools/) and Blender as a Python module (bpy 4.5 LTS, the release for Python 3.11: a ~370 MB
#    download, ~950 MB installed, in its own .venv-blender because it pins NumPy 1.26 and ships its own USD).
if [ ! -d .tools/node_modules/gltf-validator ] && command -v npm >/dev/null; then
    say "installing the Khronos glTF-Validator (npm) into .tools/"
    npm install --prefix .tools --no-audit --no-fund --silent gltf-validator@2.0.0-dev.3.10 >/dev/null || say "gltf-validator not installed: .glb checks will be skipped"
fi
if [ -z "${GRA_MI_NO_BLENDER:-}" ] && ! .venv-blender/bin/python -c "import bpy" 2>/dev/null; then
    say "installing Blender as a Python module (bpy 4.5) into .venv-blender (set GRA_MI_NO_BLENDER=1 to skip)"
    { "$PYTHON" -m venv .venv-blender && .venv-blender/bin/python -m pip install -q --disable-pip-version-check "bpy==4.5.*"; } \
        || say "bpy not installed: the Blender comparison will be skipped"
fi
say "ready: .venv/bin/gra-mi --help"
