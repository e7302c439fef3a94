#!/usr/bin/env bash
# One prepared GPU session: what a CPU cannot reach, in a fixed time budget.
#
#   OUT=/some/dir bash benchmarks/gpu_session.sh [TOTAL_SECONDS] [WHAT]   (default 500 sip)
#
# 1. versions and the device;
# 2. WHAT=steps (or poisson_hig): step times on the GPU, back to back in one process
#    (benchmarks/hig_step.py: adam and hig's gram and structured routes at the paper's batch;
#    benchmarks/khig_step.py: adam, khig and exact hig interleaved);
# 3. WHAT=poisson_hig: the Poisson 8x8 HIG run at the paper's batch of 64 (issue: evidence,
#    rows H5/H6), for whatever time is left: `physgrad compare` with a step budget, stopped by
#    SIGTERM, which checkpoints; the run directory comes back as poisson_hig_gpu.tgz and
#    resumes with the same command (the budget is a step count, so the curve is step-indexed
#    and machine-free). Ran once on an H200 (4,950 updates; docs/reproductions/data/poisson_hig_b64_gpu).
# 4. WHAT=sip (the default): the SIP paper's 10,000-step heat and Poisson 64x64 runs (long
#    rows 5 and 6; ≈ 15 h per run on a CPU core), SIP and Adam, seed 0, four processes at
#    once on the one GPU, each stopped by SIGTERM before the time is up (a checkpoint every
#    60 s). The runs resume from docs/reproductions/data/gpu_lanes (the working tree travels
#    to the device), and come back as gpu_lanes.tgz: unpack it here with
#      tar xzf FILES_AT/gpu_lanes.tgz -C docs/reproductions/data
#    and commit; the next GPU session goes on from there.
#
# physgrad runs from src/ against the machine's own jax (no install: the GPU machine has no
# network). kfac-jax is absent there, so K-FAC is left out of the step benchmark.
set -uo pipefail
TOTAL=${1:-500}
WHAT=${2:-sip}
case "$WHAT" in steps|poisson_hig|sip) ;; *) echo "unknown WHAT $WHAT; valid: steps, poisson_hig, sip" >&2; exit 2 ;; esac
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

if [ "$WHAT" != sip ]; then
timeout 120 "$PY" benchmarks/hig_step.py --problems oscillators,poisson_hig --routes gram,structured \
  --repeats 5 2>&1 | tee "$OUT/hig_step.txt"
timeout 120 "$PY" benchmarks/khig_step.py --problems oscillators,quantum_dipole,poisson_hig \
  --methods adam,khig,hig --repeats 10 --hig-repeats 3 2>&1 | tee "$OUT/khig_step.txt"

fi

if [ "$WHAT" = sip ]; then
  KEEP=docs/reproductions/data/gpu_lanes
  budget=$(( $(left) - 40 ))
  echo "sip lanes: ${budget} s left for the runs" | tee -a "$OUT/versions.txt"
  for problem in heat poisson; do
    for method in sip adam; do
      dir=/tmp/gpu_lanes/${problem}_10k/$method
      mkdir -p "$dir"
      [ -d "$KEEP/${problem}_10k/$method" ] && cp -r "$KEEP/${problem}_10k/$method/." "$dir/"
      timeout -s TERM -k 30 "$budget" "$PY" -m physgrad compare "$problem" --methods "$method" --seeds 1 \
        --steps 10000 --set eval_every=250 --set eval_samples=128 --set checkpoint_seconds=60 \
        --out "$dir" --quiet > "$dir.log" 2>&1 &
    done
  done
  wait
  for log in /tmp/gpu_lanes/*/*.log; do echo "== $log"; tail -5 "$log"; done 2>&1 | tee "$OUT/gpu_lanes.txt"
  tar czf "$OUT/gpu_lanes.tgz" -C /tmp --exclude='*.log' gpu_lanes
  echo "done after $(( $(date +%s) - START )) s" | tee -a "$OUT/versions.txt"
  exit 0
fi

RUN=/tmp/poisson_hig_gpu
budget=$(( $(left) - 25 ))
echo "poisson_hig hig: ${budget} s left for the run" | tee -a "$OUT/versions.txt"
if [ "$WHAT" = poisson_hig ] && [ "$budget" -gt 60 ]; then
  timeout -s TERM -k 20 "$budget" "$PY" -m physgrad compare poisson_hig --methods hig --seeds 1 \
    --steps 5000 --set eval_every=25 --set checkpoint_seconds=30 --out "$RUN" 2>&1 \
    | tail -40 | tee "$OUT/poisson_hig_gpu.txt"
fi
tar czf "$OUT/poisson_hig_gpu.tgz" -C /tmp poisson_hig_gpu 2>/dev/null
echo "done after $(( $(date +%s) - START )) s" | tee -a "$OUT/versions.txt"
