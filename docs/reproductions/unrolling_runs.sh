#!/usr/bin/env bash
# Reproduction runs for docs/reproductions/unrolling.md (List et al., CMAME 2025; PRDP).
# Usage: bash docs/reproductions/unrolling_runs.sh LANE   (LANE: ks_correction, ks_prediction,
#        kolmogorov_correction, kolmogorov_prediction, advection, prdp, all). Each lane is a `physgrad compare` study under
#        studies/unrolling/; re-running skips finished runs. Budgets are equal epochs (equal
#        numbers of updates and targets, the paper's budget parity); override with the
#        variables below. Data are generated on first use and cached ($PHYSGRAD_CACHE).
set -euo pipefail
PHYSGRAD=${PHYSGRAD:-physgrad}
OUT=${OUT:-studies/unrolling}
SEEDS=${SEEDS:-3}
EPOCHS_KS=${EPOCHS_KS:-8}
EPOCHS_KOLM=${EPOCHS_KOLM:-4}
# Kolmogorov on 2 CPU cores: 16² coarse / 64² reference, forcing mode 4 (mode 6 is cut by
# the 2/3 dealiasing at 16²), a 16 x 3 ResNet; the paper's size is KOLM="n=32 forcing_mode=6".
KOLM=${KOLM:-"n=16 forcing_mode=4 width=16 blocks=3 frames=400"}
PRDP_STEPS=${PRDP_STEPS:-3000}
PRDP_N=${PRDP_N:-128}  # grid points: large enough that the Jacobi sweeps weigh in the step time
lane=${1:-all}

run_ks() {  # $1: setup
  $PHYSGRAD compare ks --methods one,nog,wig --seeds "$SEEDS" --epochs "$EPOCHS_KS" --quiet \
    --set setup="$1", --out "$OUT/ks_$1"
}

run_kolmogorov() {  # $1: setup
  local sets=()
  for s in $KOLM; do sets+=(--set "$s"); done
  $PHYSGRAD compare kolmogorov --methods one,nog,wig --seeds "$SEEDS" --epochs "$EPOCHS_KOLM" --quiet \
    "${sets[@]}" --set setup="$1", --out "$OUT/kolmogorov_$1"
}

run_advection() {
  # trainax's quick-start: supervised (WIG) rollouts of 1, 5 and 20 steps, 1000 Adam steps
  $PHYSGRAD compare advection_1d --methods wig --seeds "$SEEDS" --steps 1000 --quiet \
    --set setup=prediction --set m=1,5,20 --out "$OUT/advection_quickstart"
  # the three modalities in both setups at m = 5
  $PHYSGRAD compare advection_1d --methods one,nog,wig --seeds "$SEEDS" --steps 1000 --quiet \
    --set setup=prediction,correction --out "$OUT/advection_modalities"
}

run_prdp() {
  # WIG correction through the implicit-upwind solver: PRDP (from K = 1) against fixed K
  $PHYSGRAD compare advection_1d --methods wig --seeds "$SEEDS" --steps "$PRDP_STEPS" --quiet \
    --set n="$PRDP_N" --set setup=correction --set eval_every=20 --set iterations=20 --set prdp=true --out "$OUT/prdp"
  $PHYSGRAD compare advection_1d --methods wig --seeds "$SEEDS" --steps "$PRDP_STEPS" --quiet \
    --set n="$PRDP_N" --set setup=correction --set eval_every=20 --set iterations=1,2,5,20 --out "$OUT/prdp_fixed"
}

case "$lane" in
  ks_correction) run_ks correction ;;
  ks_prediction) run_ks prediction ;;
  kolmogorov_correction) run_kolmogorov correction ;;
  kolmogorov_prediction) run_kolmogorov prediction ;;
  advection) run_advection ;;
  prdp) run_prdp ;;
  all) run_ks correction; run_ks prediction; run_kolmogorov correction; run_kolmogorov prediction; run_advection; run_prdp ;;
  *) echo "unknown lane $lane; valid: ks_correction, ks_prediction, kolmogorov_correction, kolmogorov_prediction, advection, prdp, all" >&2; exit 2 ;;
esac
