#!/usr/bin/env bash
# The stabilised-BPTT reproduction sweeps (docs/reproductions/stable_bptt.md), as
# `physgrad compare` sweeps: methods R (bptt), M (sbptt_m), C (sbptt_c), S (no_temporal)
# x each task's complexity setting x clip mode {value, norm, none}, 3 seeds each,
# Adam lr 1e-3 (eps 1e-7), batch 8 in fixed order, full train and test loss every epoch.
#
# Epochs (the paper: 1000 for cart-pole and quantum control, the GBR script says 10):
# cart-pole and guidance 200 epochs (6,400 updates), quantum control 60 epochs
# (1,920 updates) -- what fits on a 2-core CPU in one session (a quantum-control update
# costs ~25 ms here). On a GPU, raise EPOCHS_* to the paper's 1000.
#
# Lanes (the report ran each pinned to one core, two at a time):
#   taskset -c 1 bash docs/reproductions/stable_bptt_runs.sh cartpole &
#   taskset -c 0 bash docs/reproductions/stable_bptt_runs.sh guidance
#   taskset -c 1 bash docs/reproductions/stable_bptt_runs.sh quantum_a &
#   OUT=studies/stable_bptt_b taskset -c 0 bash docs/reproductions/stable_bptt_runs.sh quantum_b
# (a sweep directory takes one writer at a time, so the second part-lane writes elsewhere),
# then `mv studies/stable_bptt_b/quantum_control/eigenstate* studies/stable_bptt/quantum_control/`,
# `bash docs/reproductions/stable_bptt_runs.sh quantum` (skips every finished run, records
# the whole grid) and `python docs/reproductions/stable_bptt_report.py`.
# `cartpole_long` re-runs the hardest cart-pole setting (4 poles) at the paper's 1000
# epochs for R and C (it ran beside the quantum lanes on core 1); `quantum_long` runs the
# hardest quantum target for 250 epochs (the kept run: one lane with all three methods;
# METHODS_LONG picks a subset, e.g. to split it across cores, each into its own OUT).
# On a lent GPU machine `OUT=… bash benchmarks/gpu_session.sh 500 stable_bptt` runs these
# cells on its 16 CPU cores, one job per (cell, method), listed by `stable_bptt_runs.sh
# cells TASK...` from the same spec as the sweeps; its runs are gathered here by running
# the lane with OUT set to where they were unpacked (finished runs are skipped).
set -euo pipefail
PG=${PHYSGRAD:-physgrad}
OUT=${OUT:-studies/stable_bptt}
EPOCHS_CARTPOLE=${EPOCHS_CARTPOLE:-200}
EPOCHS_GUIDANCE=${EPOCHS_GUIDANCE:-200}
EPOCHS_QUANTUM=${EPOCHS_QUANTUM:-60}
METHODS=bptt,sbptt_m,sbptt_c,no_temporal
CLIPS=value,norm,none

# Each sweep once: problem, output directory, epochs, methods, the two swept settings and
# the cost of one (cell, method) job with 3 seeds in core-minutes (measured on one core of
# the 2-core machine; `cells` orders a lent machine's jobs by it). A setting with one value
# keeps a trailing comma, so the cell directory keeps both names: poles4_clipvalue.
spec() {
  case "$1" in
    cartpole) echo "cartpole cartpole $EPOCHS_CARTPOLE $METHODS poles=1,2,3,4 clip=$CLIPS 3" ;;
    guidance) echo "guidance guidance $EPOCHS_GUIDANCE $METHODS rc=1.0,0.1,0.01,0.001 clip=$CLIPS 1.5" ;;
    quantum) echo "quantum_control quantum_control $EPOCHS_QUANTUM $METHODS eigenstate=3,4,5 clip=$CLIPS 4.5" ;;
    # the hardest cart-pole setting at the paper's 1000 epochs, R vs C
    cartpole_long) echo "cartpole cartpole-1000ep 1000 bptt,sbptt_c poles=4, clip=value,norm 15" ;;
    # the hardest quantum target for longer: does C overtake M? (R, M, C; norm clipping)
    quantum_long) echo "quantum_control quantum_control-250ep 250 ${METHODS_LONG:-bptt,sbptt_m,sbptt_c} eigenstate=5, clip=norm, 20" ;;
    *) echo "unknown lane $1; valid: cartpole, guidance, quantum_a, quantum_b, quantum, cartpole_long, quantum_long, all, cells TASK..." >&2; return 2 ;;
  esac
}

sweep() {  # $1: the task; $2, $3: override its swept settings (quantum_a, quantum_b)
  local line problem out epochs methods a b
  line=$(spec "$1") || exit 2
  read -r problem out epochs methods a b _ <<< "$line"
  $PG compare "$problem" --methods "$methods" --seeds 3 --epochs "$epochs" \
    --set "${2:-$a}" --set "${3:-$b}" --out "$OUT/$out" --quiet
}

# one line per (cell, method) job: cost problem out epochs method setting_a, setting_b,
cells() {
  local task line problem out epochs methods a b cost va vb m
  for task in "$@"; do
    line=$(spec "$task") || exit 2
    read -r problem out epochs methods a b cost <<< "$line"
    for vb in $(tr , ' ' <<< "${b#*=}"); do for va in $(tr , ' ' <<< "${a#*=}"); do
      for m in $(tr , ' ' <<< "$methods"); do
        echo "$cost $problem $out $epochs $m ${a%%=*}=$va, ${b%%=*}=$vb,"
      done
    done; done
  done
}

case "${1:-all}" in
  cartpole|guidance|quantum|cartpole_long|quantum_long) sweep "$1" ;;
  quantum_a) sweep quantum eigenstate=3,4 clip=value,norm ;;  # 4 of the 9 cells
  quantum_b) sweep quantum eigenstate=5, clip=$CLIPS; sweep quantum eigenstate=3,4 clip=none, ;;  # the other 5
  all) for lane in cartpole guidance quantum cartpole_long quantum_long; do bash "$0" "$lane"; done ;;
  cells) shift; cells "$@" ;;
  *) spec "$1"; exit 2 ;;
esac
