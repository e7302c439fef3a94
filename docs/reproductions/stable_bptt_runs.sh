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
#   taskset -c 0 bash docs/reproductions/stable_bptt_runs.sh quantum_b
# then `bash docs/reproductions/stable_bptt_runs.sh quantum` (skips every finished run,
# records the whole grid) and `python docs/reproductions/stable_bptt_report.py`.
# `cartpole_long` re-runs the hardest cart-pole setting (4 poles) at the paper's 1000
# epochs for R and C (it ran beside the quantum lanes on core 1); `quantum_long` runs the
# hardest quantum target for 250 epochs (it ran as two lanes, METHODS_LONG=sbptt_c and
# METHODS_LONG=bptt,sbptt_m, then once with all three to record the study).
# On a lent GPU machine `OUT=… bash benchmarks/gpu_session.sh 500 stable_bptt` runs these
# cells on its 16 CPU cores, one job per (cell, method); its runs are gathered here by
# running the lane with OUT set to where they were unpacked (finished runs are skipped).
set -euo pipefail
PG=${PHYSGRAD:-physgrad}
OUT=${OUT:-studies/stable_bptt}
EPOCHS_CARTPOLE=${EPOCHS_CARTPOLE:-200}
EPOCHS_GUIDANCE=${EPOCHS_GUIDANCE:-200}
EPOCHS_QUANTUM=${EPOCHS_QUANTUM:-60}
METHODS=bptt,sbptt_m,sbptt_c,no_temporal
CLIPS=value,norm,none

quantum() {  # $1: the eigenstates, $2: the clip modes to sweep
  $PG compare quantum_control --methods $METHODS --seeds 3 --epochs "$EPOCHS_QUANTUM" \
    --set eigenstate="$1" --set clip="$2" --out "$OUT/quantum_control" --quiet
}

case "${1:-all}" in
  cartpole)
    $PG compare cartpole --methods $METHODS --seeds 3 --epochs "$EPOCHS_CARTPOLE" \
      --set poles=1,2,3,4 --set clip=$CLIPS --out "$OUT/cartpole" --quiet ;;
  guidance)
    $PG compare guidance --methods $METHODS --seeds 3 --epochs "$EPOCHS_GUIDANCE" \
      --set rc=1.0,0.1,0.01,0.001 --set clip=$CLIPS --out "$OUT/guidance" --quiet ;;
  # (a trailing comma sweeps one value, so the cell keeps both names: eigenstate5_clipnone)
  quantum_a) quantum 3,4 value,norm ;;  # 4 of the 9 cells
  quantum_b) quantum 5, $CLIPS; quantum 3,4 none, ;;  # the other 5
  quantum) quantum 3,4,5 $CLIPS ;;
  cartpole_long)  # the hardest cart-pole setting at the paper's 1000 epochs, R vs C
    $PG compare cartpole --methods bptt,sbptt_c --seeds 3 --epochs 1000 \
      --set poles=4, --set clip=value,norm --out "$OUT/cartpole-1000ep" --quiet ;;
  all) for lane in cartpole guidance quantum cartpole_long quantum_long; do bash "$0" "$lane"; done ;;
  quantum_long)  # the hardest quantum target for longer: does C overtake M? (R, M, C; norm clipping)
    $PG compare quantum_control --methods "${METHODS_LONG:-bptt,sbptt_m,sbptt_c}" --seeds 3 --epochs 250 \
      --set eigenstate=5, --set clip=norm, --out "$OUT/quantum_control-250ep" --quiet ;;
  *) echo "unknown lane $1; valid: cartpole, guidance, quantum_a, quantum_b, quantum, cartpole_long, quantum_long, all" >&2; exit 2 ;;
esac
