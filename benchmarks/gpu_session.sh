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
#    rows 5 and 6; ≈ 15 h per run on a CPU core), SIP and Adam, seeds 0..SEEDS-1 (SEEDS=1
#    by default), four processes at once on the one GPU, each stopped by SIGTERM before
#    the time is up (a checkpoint every 60 s). On an H200 one 10,000-step run takes
#    ≈ 130-180 s with four processes sharing the GPU: SEEDS=3 finishes all 12 runs in
#    ≈ 10 min of runs (two calls; done 2026-11-27, the committed directories are final). physgrad runs at the checkout's commit (the CPU
#    lanes of long/studies.sh pin FAST_COMMIT; the U-Net step is the same). The runs resume
#    from docs/reproductions/data/sip_{heat,poisson}_10k_gpu when the checkout holds them,
#    and everything comes back as gpu_lanes.tgz in OUT: copy it to the checkout, unpack it
#    with `tar xzf gpu_lanes.tgz -C docs/reproductions/data`, commit, and draw it with
#    `python docs/reproductions/long/report.py sip_heat_10k_gpu sip_poisson_10k_gpu`;
#    the next GPU session goes on from there.
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
  KEEP=docs/reproductions/data
  LANES=/tmp/gpu_lanes
  # 75 s kept back: SIGTERM, up to 15 s to checkpoint and exit (then SIGKILL), the tarball
  budget=$(( $(left) - 75 ))
  echo "sip lanes: ${budget} s left for the runs" | tee -a "$OUT/versions.txt"
  [ "$budget" -gt 60 ] || { echo "too little time left for the sip lanes" | tee -a "$OUT/versions.txt"; exit 1; }
  for study in sip_heat_10k_gpu sip_poisson_10k_gpu; do
    problem=${study#sip_}; problem=${problem%_10k_gpu}
    for method in sip adam; do
      dir=$LANES/$study/$method
      mkdir -p "$dir"
      if [ -d "$KEEP/$study/$method" ]; then cp -r "$KEEP/$study/$method/." "$dir/"; fi
      timeout -s TERM -k 15 "$budget" "$PY" -m physgrad compare "$problem" --methods "$method" --seeds "${SEEDS:-1}" \
        --steps 10000 --set eval_every=250 --set eval_samples=128 --set checkpoint_seconds=60 \
        --out "$dir" --quiet > "$dir.log" 2>&1 &
    done
  done
  wait
  for log in "$LANES"/*/*.log; do echo "== $log"; tail -5 "$log"; done 2>&1 | tee "$OUT/gpu_lanes.txt"
  tar czf "$OUT/gpu_lanes.tgz" -C "$LANES" --exclude='*.log' sip_heat_10k_gpu sip_poisson_10k_gpu
  echo "done after $(( $(date +%s) - START )) s" | tee -a "$OUT/versions.txt"
  exit 0
fi

RUN=/tmp/poisson_hig_gpu
budget=$(( $(left) - 25 ))
if [ "$WHAT" = poisson_hig ] && [ "$budget" -gt 60 ]; then
  echo "poisson_hig hig: ${budget} s left for the run" | tee -a "$OUT/versions.txt"
  timeout -s TERM -k 20 "$budget" "$PY" -m physgrad compare poisson_hig --methods hig --seeds 1 \
    --steps 5000 --set eval_every=25 --set checkpoint_seconds=30 --out "$RUN" 2>&1 \
    | tail -40 | tee "$OUT/poisson_hig_gpu.txt"
  tar czf "$OUT/poisson_hig_gpu.tgz" -C /tmp poisson_hig_gpu
fi
echo "done after $(( $(date +%s) - START )) s" | tee -a "$OUT/versions.txt"
