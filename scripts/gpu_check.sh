#!/usr/bin/env bash
# The GPU check: what a GPU user runs, on a machine with an NVIDIA GPU, in one run of about eight minutes —
# the CUDA variant of every variant-parametrised test, the tiny demo end to end (cuda_ad_rgb, torch on CUDA),
# benchmarks/fit_step.py on the demo's capture and benchmarks/stages.py — and the page docs/results/gpu.md with this
# machine's CPU figures beside.
#
#   1. here (CPU, ~3 min each):  bash scripts/gpu_check.sh --cpu;  bash scripts/gpu_check.sh --cpu --trace
#        the same check on llvm_ad_rgb: .gpu/cpu/ (the CPU column); then again under strace, untimed:
#        .gpu/trace.txt (every file its processes opened, Python's and native code's alike)
#   2. here:                 .venv/bin/python scripts/gpu/pack.py
#        .gpu/site.tar.xz: the packages the GPU machine's image lacks, for its Python, trimmed by that trace
#      and, to rehearse the GPU machine's packages here: pack.py --python 3.11 --out /tmp/p311 (trace.txt copied
#      there first), then bash scripts/gpu_check.sh --cpu --site /tmp/p311/site.tar.xz
#   3. on the GPU machine:   bash scripts/gpu_check.sh --commit $(git rev-parse --short HEAD)
#        $OUT/gpu.md (the page) and $OUT/run.tar.gz (test report, logs, the demo's record, stage timings), nothing
#        else there (the device tool returns at most 8 files). Through the
#        device tool: carry [".gpu"], timeout_s 600 (the parts' own limits add up to 520 s); then copy gpu.md to
#        docs/results/ and commit it.
#
# Options: --cpu (step 1), --trace (with --cpu: record the files opened), --commit SHA (the machine's copy may have
# no .git), --out DIR (default $OUT or /tmp/gpu_check), --site TARBALL (packages to unpack onto PYTHONPATH; default
# .gpu/site.tar.xz when it exists; with --cpu: rehearse the GPU run's trimmed packages on this machine's Python).
# Each part has its own time limit, and a part that fails is reported on the page; the others still run.
set -uo pipefail
cd "$(dirname "$0")/.."
REPO=$PWD

CPU=0 TRACING=0 COMMIT="" DEST=${OUT:-/tmp/gpu_check} SITE=""
while [ $# -gt 0 ]; do
    case "$1" in
        --cpu) CPU=1 ;;
        --trace) TRACING=1 ;;
        --commit) COMMIT=$2; shift ;;
        --out) DEST=$2; shift ;;
        --site) SITE=$2; shift ;;
        -h|--help) sed -n '2,21p' "$0" | cut -c3-; exit 0 ;;
        *) echo "gpu_check: unknown option $1 (see --help)" >&2; exit 2 ;;
    esac
    shift
done
say() { printf 'gpu_check: %s\n' "$*" >&2; }

TRACE=()
if [ "$CPU" = 1 ]; then
    PYTHON=${PYTHON:-$REPO/.venv/bin/python} VARIANT=llvm_ad_rgb RUN=$REPO/.gpu/cpu
    if [ -n "$SITE" ]; then  # a rehearsal of the trimmed packages: its own folder, and what the GPU machine will lack
        RUN=$REPO/.gpu/rehearsal  # cannot be imported (scripts/gpu/sitecustomize.py)
        export PYTHONPATH=$REPO/scripts/gpu GRA_MI_HIDE_MODULES=${GRA_MI_HIDE_MODULES:-pxr,imageio_ffmpeg,warp}
    elif [ "$TRACING" = 1 ]; then  # every file any process opens, for scripts/gpu/pack.py (not timed: strace slows it)
        RUN=$REPO/.gpu/traced
        command -v strace >/dev/null || { say "the CPU run records the files it opens with strace: apt-get install strace"; exit 1; }
        TRACE=(strace -f -qq --seccomp-bpf -e trace=open,openat,execve)
        mkdir -p "$REPO/.gpu" && rm -f "$REPO/.gpu"/strace.*.log
    fi
else
    PYTHON=${PYTHON:-python3} VARIANT=cuda_ad_rgb RUN=${TMPDIR:-/tmp}/gpu_check_run  # $OUT gets 2 files only
    export GRA_MI_ASSUME_CUDA=1  # Dr.Jit's own probe decides, not the /dev/nvidia* nodes a sandbox may hide
    [ -z "$COMMIT" ] && ! git rev-parse HEAD >/dev/null 2>&1 && say "no --commit and no .git: the page will say 'commit unknown'"
    [ -z "$SITE" ] && [ -f .gpu/site.tar.xz ] && SITE=.gpu/site.tar.xz
fi
if [ -e "$RUN" ] && [ ! -e "$RUN/.gpu_check_run" ]; then  # a folder this script did not make is never emptied
    say "$RUN exists and is not a run folder this script made: move it away"; exit 2
fi
rm -rf "$RUN" && mkdir -p "$RUN" "$DEST" && touch "$RUN/.gpu_check_run" || exit 1
if [ -n "$SITE" ]; then
    rm -rf /tmp/gpu_site && mkdir -p /tmp/gpu_site && tar -xJf "$SITE" -C /tmp/gpu_site || { say "cannot unpack $SITE"; exit 1; }
    export PYTHONPATH=/tmp/gpu_site${PYTHONPATH:+:$PYTHONPATH}
fi
export PYTHONPATH=${PYTHONPATH:+$PYTHONPATH:}$REPO PYTHONUNBUFFERED=1 GRA_MI_QUIET=1 GRA_MI_COMMIT=${COMMIT:-${GRA_MI_COMMIT:-}}

part() {  # part NAME LIMIT_S COMMAND...: run it with a time limit, log it, note its exit status and seconds
    local name=$1 limit=$2; shift 2
    say "$name (at most ${limit} s)"
    local start=$SECONDS
    local tracer=()
    [ ${#TRACE[@]} -gt 0 ] && tracer=("${TRACE[@]}" -o "$REPO/.gpu/strace.$name.log")
    timeout --kill-after=10 "$limit" "${tracer[@]}" "$@" >"$RUN/$name.log" 2>&1
    local rc=$?
    printf '%s\t%s\t%s\t%s\n' "$name" "$rc" "$((SECONDS - start))" "$limit" >>"$RUN/parts.tsv"
    say "$name: exit $rc after $((SECONDS - start)) s"
}

{
    echo "python: $("$PYTHON" --version 2>&1)"
    "$PYTHON" - <<'EOF' 2>&1
import importlib.metadata as m
for name in ("torch", "mitsuba", "drjit", "diffusers", "numpy"):
    try:
        print(f"{name}: {m.version(name)}")
    except m.PackageNotFoundError:
        print(f"{name}: missing")
import torch
print("torch cuda:", torch.version.cuda, torch.cuda.get_device_name() if torch.cuda.is_available() else "no GPU")
EOF
    command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | sed 's/^/gpu: /'
    echo "cpus: $(nproc)"
} >"$RUN/env.txt"

XDIST=()
[ "$CPU" = 0 ] && "$PYTHON" -c "import xdist" 2>/dev/null && XDIST=(-n 4)
part tests 225 "$PYTHON" -m pytest -q -p no:cacheprovider -m "not slow" -k "$VARIANT" "${XDIST[@]}" --junitxml="$RUN/tests.xml" -rfE tests
part demo 140 "$PYTHON" -m gra_mi.cli demo --preset tiny --variant "$VARIANT" --out "$RUN/demo" --overwrite
cp "$RUN/demo/demo.json" "$RUN/demo.json" 2>/dev/null
part fit_step 45 "$PYTHON" benchmarks/fit_step.py --variant "$VARIANT" --capture "$RUN/demo/capture" --repeats 3 --write "$RUN/fit_step.md"
part stages 110 "$PYTHON" benchmarks/stages.py --variant "$VARIANT" --json "$RUN/stages.json"
rm -rf "$RUN/demo"

if [ "$CPU" = 1 ]; then
    if [ ${#TRACE[@]} -gt 0 ]; then
        grep -ho '"[^"]*site-packages/[^"]*"' "$REPO/.gpu"/strace.*.log | tr -d '"' | sort -u >"$REPO/.gpu/trace.txt"
        rm -f "$REPO/.gpu"/strace.*.log
    fi
    [ "$TRACING" = 1 ] && say "files opened: .gpu/trace.txt; next: .venv/bin/python scripts/gpu/pack.py" || say "CPU figures in $RUN"
    exit 0
fi
"$PYTHON" scripts/gpu/page.py --run "$RUN" --beside .gpu/cpu --commit "${COMMIT:-unknown}" --write "$DEST/gpu.md"
tar -czf "$DEST/run.tar.gz" -C "$(dirname "$RUN")" "$(basename "$RUN")"
say "wrote $DEST/gpu.md and $DEST/run.tar.gz"
