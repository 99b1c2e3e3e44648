#!/usr/bin/env bash
# One command for a machine with an NVIDIA GPU: install the project with its `cuda` extra
# (jax[cuda12], pyproject.toml), then run the throughput, scaling and deployment benchmarks with
# short settings, each under `timeout`, writing their tables (.md) and JSON into one folder.
#
#   bash benchmarks/gpu.sh [OUTDIR]        # OUTDIR defaults to $OUT, else ./gpu-results
#
# Run from anywhere; it changes to the repository root. PYTHON selects the interpreter
# (default: .venv/bin/python if present, else python3). The install step is skipped when JAX
# already sees a GPU. A benchmark that fails or times out is logged in OUTDIR/summary.txt and
# the script goes on; it exits 0 unless the install left no working `import espl_jax`.
# Worst case (every step hitting its timeout) is ~10 minutes, ~8 without the install; each
# benchmark's budget is set below.
#
# Offline GPU nodes (HPC clusters: a preinstalled JAX with CUDA, often newer than the pinned one,
# and no package index): WHEELS=DIR installs every wheel in DIR without resolving or touching
# the JAX found (pip --no-index --no-deps --target $SITE, default /tmp/espl-site, put first on
# PYTHONPATH); the project itself runs from this checkout (PYTHONPATH), not installed. Fill DIR
# on a machine with network, for the node's Python (here 3.12) and platform, e.g.:
#   pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 -d wheels \
#     mujoco==3.17.0 mujoco-mjx==3.17.0 brax==0.14.2 gymnasium==1.4.0 ... (their dependencies
#     that the node lacks: `python -m pip check` there lists them)
# Without WHEELS the install needs the package index; on a machine without network it fails, is
# logged, and the benchmarks run with whatever is installed (summary.txt's devices line says
# which backend they used). Not part of the test suite.
set -u -o pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
OUTDIR="${1:-${OUT:-./gpu-results}}"
mkdir -p "$OUTDIR"
OUTDIR="$(cd "$OUTDIR" && pwd)"
if [ -z "${PYTHON:-}" ]; then
    if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
SUMMARY="$OUTDIR/summary.txt"
: >"$SUMMARY"
export PYTHONPATH="$ROOT${PYTHONPATH:+:$PYTHONPATH}"

log() { echo "[$(date +%H:%M:%S)] $*" | tee -a "$SUMMARY"; }

# step NAME TIMEOUT_S COMMAND...: run under timeout, stdout+stderr to OUTDIR/NAME.md, log rc.
step() {
    local name="$1" limit="$2"
    shift 2
    local started=$SECONDS
    log "$name: $* (timeout ${limit}s; load $(cut -d' ' -f1-3 /proc/loadavg))"
    timeout --kill-after=10 "$limit" "$@" >"$OUTDIR/$name.md" 2>"$OUTDIR/$name.stderr"
    local rc=$?
    local what=ok
    if [ $rc -eq 124 ] || [ $rc -eq 137 ]; then what="TIMED OUT"; elif [ $rc -ne 0 ]; then what="FAILED"; fi
    log "$name: $what (rc $rc, $((SECONDS - started))s)"
    return 0
}

log "espl-jax GPU benchmarks into $OUTDIR"
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true; } \
    >"$OUTDIR/gpu.txt"
log "GPU: $(tail -n +2 "$OUTDIR/gpu.txt" | head -1)"

has_gpu() { "$PYTHON" -c "import jax, espl_jax; assert jax.default_backend() == 'gpu'" 2>/dev/null; }
if [ -n "${WHEELS:-}" ]; then
    SITE="${SITE:-/tmp/espl-site}"
    step install 300 "$PYTHON" -m pip install --quiet --no-index --no-deps --no-compile \
        --upgrade --target "$SITE" "$WHEELS"/*.whl
    export PYTHONPATH="$ROOT:$SITE${PYTHONPATH#"$ROOT"}"
elif has_gpu; then
    log "install: skipped (JAX already on the GPU)"
else
    step install 120 "$PYTHON" -m pip install -e ".[cuda]"
fi
"$PYTHON" - >"$OUTDIR/devices.txt" 2>&1 <<'EOF'
import jax
print(jax.__version__, jax.default_backend(), jax.devices())
EOF
log "devices: $(tail -1 "$OUTDIR/devices.txt")"
if ! "$PYTHON" -c "import espl_jax" 2>/dev/null; then
    log "espl_jax does not import; stopping"
    exit 1
fi

# Throughput: env steps/s at large batches (where a GPU pays), MJX on the GPU beside MuJoCo's C
# engine on the node's CPU; then training throughput of ours (MLP and symbolic actor) against
# brax's SAC, and the SGD step alone.
step env_throughput 45 "$PYTHON" benchmarks/env_throughput.py \
    --envs inverted_double_pendulum,hopper --batch 1,256,4096 --steps 200
step env_throughput_native 60 "$PYTHON" benchmarks/env_throughput.py --physics mjx,native \
    --envs hopper --batch 5,40 --steps 200 --json "$OUTDIR/env_throughput_native.json"
step vs_brax_sac 130 "$PYTHON" benchmarks/vs_brax_sac.py \
    --env-steps 200 --iterations 3 --sgd-steps 500 --json "$OUTDIR/vs_brax_sac.json"
# Scaling: vmapped seeds of the ESPL trainer (the env's config actor: symbolic).
step seeds 90 "$PYTHON" benchmarks/seeds.py \
    --env cartpole --seeds 1 2 4 8 --iterations 2 --updates 100 --steps 200 \
    --json "$OUTDIR/seeds.json"
# MJX speed against fidelity at batch 1, 16 and 1024 for hopper.
step mjx_fidelity 60 "$PYTHON" benchmarks/mjx_fidelity.py \
    --envs hopper --settings env,6:6,4:4,1:4 --batch 1,16,1024 --steps 100 \
    --json "$OUTDIR/mjx_fidelity.json"
# Deployment: 5000 robots, every env (numpy and C rows run on the host CPU, JAX rows on the GPU).
step deploy 90 "$PYTHON" benchmarks/deploy.py --robots 5000 --repeats 5 \
    --json "$OUTDIR/deploy.json"

log "done in ${SECONDS}s"
exit 0
