#!/usr/bin/env bash
# One prepared GPU session: what a CPU cannot reach, in a fixed time budget.
#
#   OUT=/some/dir bash benchmarks/gpu_session.sh [TOTAL_SECONDS] [WHAT]   (default 500 stable_bptt)
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
# 4. WHAT=sip: the SIP paper's 10,000-step heat and Poisson 64x64 runs (long
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
# 5. WHAT=stable_bptt: the StableBPTT sweeps (docs/reproductions/stable_bptt_runs.sh's cells)
#    on the machine's CPU cores, not its GPU (batch-8 rollouts of a few hundred parameters:
#    the many small runs are what a 2-core machine cannot get through, not their size). One
#    job per (sweep cell, method), 3 seeds each, one thread per job, as many jobs at once as
#    the machine has cores, longest first; TASKS picks the sweeps (default "cartpole"; also
#    guidance, quantum, cartpole_long, quantum_long; `bash docs/reproductions/
#    stable_bptt_runs.sh cells TASK...` lists their jobs). Every job is stopped by SIGTERM
#    before the time is up (a run in progress checkpoints), and the run directories come
#    back without their checkpoints as stable_bptt_gpu.tgz: unpack it with `tar xzf
#    stable_bptt_gpu.tgz -C /work/lanes/stable_bptt_gpu` and run the sweep's whole grid there (`OUT=/work/lanes/
#    stable_bptt_gpu bash docs/reproductions/stable_bptt_runs.sh TASK`): it skips every finished
#    run, trains any the GPU machine did not finish and records the grid; then keep it with
#    keep_studies.py --gzip. Estimated: cartpole 48 jobs × ≈ 3 core-min, quantum 36 × ≈ 4.5,
#    cartpole_long 4 × ≈ 15, quantum_long 3 × ≈ 20 (one-core times measured on the 2-core machine).
#
# physgrad runs from src/ against the machine's own jax (no install: the GPU machine has no
# network). kfac-jax is absent there, so K-FAC is left out of the step benchmark.
set -uo pipefail
TOTAL=${1:-500}
WHAT=${2:-stable_bptt}
case "$WHAT" in steps|poisson_hig|sip|stable_bptt) ;; *) echo "unknown WHAT $WHAT; valid: steps, poisson_hig, sip, stable_bptt" >&2; exit 2 ;; esac
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

if [ "$WHAT" = stable_bptt ]; then
  SB=/tmp/stable_bptt_gpu
  mkdir -p "$SB/parts" "$SB/sweeps"
  budget=$(( $(left) - 60 ))  # SIGTERM, up to 20 s to checkpoint, the tarball
  echo "stable_bptt ${TASKS:-cartpole}: ${budget} s for the jobs on $(nproc) cores" | tee -a "$OUT/versions.txt"
  [ "$budget" -gt 60 ] || { echo "too little time left for the sweeps" | tee -a "$OUT/versions.txt"; exit 1; }
  jobs=$SB/jobs.txt
  # one line per job: cost (core-min, for the order), problem, out, epochs, method, cell
  # settings -- the sweeps' own cells, from the script that owns them
  # shellcheck disable=SC2086
  bash docs/reproductions/stable_bptt_runs.sh cells ${TASKS:-cartpole} | sort -rn -s -k1,1 > "$jobs" || exit 2
  echo "$(wc -l < "$jobs") jobs" | tee -a "$OUT/versions.txt"
  DEADLINE=$(( $(date +%s) + budget ))
  export PY SB DEADLINE
  # shellcheck disable=SC2016
  JAX_PLATFORMS=cpu xargs -P "$(nproc)" -L 1 bash -c '
    problem=$1 out=$2 epochs=$3 method=$4 a=$5 b=$6
    part="$SB/parts/$out.$method.${a//[=,]/}.${b//[=,]/}"  # a sweep directory is locked: one per job
    rest=$(( DEADLINE - $(date +%s) ))  # a job that starts late gets what is left, not the whole budget
    [ "$rest" -gt 30 ] || { echo "$out $method $a $b: not started (no time left)"; exit 0; }
    timeout -s TERM -k 20 "$rest" "$PY" -m physgrad compare "$problem" --methods "$method" --seeds 3 \
      --epochs "$epochs" --set "$a" --set "$b" --threads 1 --out "$part" --quiet > "$part.log" 2>&1
    echo "$out $method $a $b: rc $? after $SECONDS s"' _ < <(cut -d" " -f2- "$jobs") | tee "$OUT/stable_bptt_jobs.txt"
  # the jobs' runs gathered into each sweep's cells, as stable_bptt_runs.sh lays them out
  for part in "$SB"/parts/*/; do
    out=$(basename "$part"); out=${out%%.*}
    for cell in "$part"*/; do
      [ -d "$cell/runs" ] || continue
      mkdir -p "$SB/sweeps/$out/$(basename "$cell")/runs" && mv "$cell"runs/* "$SB/sweeps/$out/$(basename "$cell")/runs/"
    done
  done
  finished=$(grep -l '"finished"\|"diverged"' "$SB"/sweeps/*/*/runs/*/summary.json 2>/dev/null | wc -l)
  echo "runs finished or diverged: $finished" | tee -a "$OUT/versions.txt"
  tar czf "$OUT/stable_bptt_gpu.tgz" -C "$SB/sweeps" --exclude=checkpoint .
  (cd "$SB" && tar czf "$OUT/stable_bptt_logs.tgz" parts/*.log)
  echo "done after $(( $(date +%s) - START )) s" | tee -a "$OUT/versions.txt"
  exit 0
fi

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
