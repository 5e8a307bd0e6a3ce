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
say "ready: .venv/bin/gra-mi --help"
