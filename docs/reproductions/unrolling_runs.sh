#!/usr/bin/env bash
# Reproduction runs for docs/reproductions/unrolling.md (List et al., CMAME 2025; PRDP).
# Usage: bash docs/reproductions/unrolling_runs.sh LANE   (LANE: ks_correction, ks_prediction,
#        kolmogorov, advection, prdp, all). Each lane is a `physgrad compare` study under
#        studies/unrolling/; re-running skips finished runs. Budgets are equal epochs (equal
#        numbers of updates and targets, the paper's budget parity); override with the
#        variables below. Data are generated on first use and cached ($PHYSGRAD_CACHE).
set -euo pipefail
PHYSGRAD=${PHYSGRAD:-physgrad}
OUT=${OUT:-studies/unrolling}
SEEDS=${SEEDS:-3}
EPOCHS_KS=${EPOCHS_KS:-8}
lane=${1:-all}

run_ks() {  # $1: setup
  $PHYSGRAD compare ks --methods one,nog,wig --seeds "$SEEDS" --epochs "$EPOCHS_KS" --quiet \
    --set setup="$1", --out "$OUT/ks_$1"
}

case "$lane" in
  ks_correction) run_ks correction ;;
  ks_prediction) run_ks prediction ;;
  all) run_ks correction; run_ks prediction ;;
  *) echo "unknown lane $lane; valid: ks_correction, ks_prediction, all" >&2; exit 2 ;;
esac
