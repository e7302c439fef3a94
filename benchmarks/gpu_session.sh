#!/usr/bin/env bash
# One prepared GPU session: what a CPU cannot reach, in a fixed time budget.
#
#   OUT=/some/dir bash benchmarks/gpu_session.sh [TOTAL_SECONDS]   (default 500)
#
# 1. versions and the device;
# 2. step times on the GPU, back to back in one process (benchmarks/hig_step.py: adam and
#    hig's gram and structured routes at the paper's batch; benchmarks/khig_step.py: adam,
#    khig and exact hig interleaved) -- the calibration of the time axis below;
# 3. the Poisson 8x8 HIG run at the paper's batch of 64 (issue: evidence, rows H5/H6), for
#    whatever time is left: `physgrad compare` with a step budget, stopped by SIGTERM, which
#    checkpoints; the run directory comes back as poisson_hig_gpu.tgz and resumes with the
#    same command (the budget is a step count, so the curve is step-indexed and machine-free).
#
# physgrad runs from src/ against the machine's own jax (no install: the GPU machine has no
# network). kfac-jax is absent there, so K-FAC is left out of the step benchmark.
set -uo pipefail
TOTAL=${1:-500}
START=$(date +%s)
OUT=${OUT:?set OUT to a directory for the results}
PY=${PY:-python3}
export PYTHONPATH=src PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
export PHYSGRAD_CACHE=${PHYSGRAD_CACHE:-/tmp/physgrad-cache}
left() { echo $((TOTAL - ($(date +%s) - START))); }

{
  date -u
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  "$PY" -c "import jax, equinox, optax, lineax, physgrad; print('jax', jax.__version__, 'equinox', equinox.__version__, 'optax', optax.__version__, 'lineax', lineax.__version__, 'physgrad', physgrad.__version__, jax.devices())"
} 2>&1 | tee "$OUT/versions.txt"

timeout 120 "$PY" benchmarks/hig_step.py --problems oscillators,poisson_hig --routes gram,structured \
  --repeats 5 2>&1 | tee "$OUT/hig_step.txt"
timeout 120 "$PY" benchmarks/khig_step.py --problems oscillators,quantum_dipole,poisson_hig \
  --methods adam,khig,hig --repeats 10 --hig-repeats 3 2>&1 | tee "$OUT/khig_step.txt"

RUN=/tmp/poisson_hig_gpu
budget=$(( $(left) - 25 ))
echo "poisson_hig hig: ${budget} s left for the run" | tee -a "$OUT/versions.txt"
if [ "$budget" -gt 60 ]; then
  timeout -s TERM -k 20 "$budget" "$PY" -m physgrad compare poisson_hig --methods hig --seeds 1 \
    --steps 5000 --set eval_every=25 --set checkpoint_seconds=30 --out "$RUN" 2>&1 \
    | tail -40 | tee "$OUT/poisson_hig_gpu.txt"
fi
tar czf "$OUT/poisson_hig_gpu.tgz" -C /tmp poisson_hig_gpu 2>/dev/null
echo "done after $(( $(date +%s) - START )) s" | tee -a "$OUT/versions.txt"
