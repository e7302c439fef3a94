#!/usr/bin/env bash
# The SIP reproduction studies (docs/reproductions/sip.md), as `physgrad compare` commands.
# Three independent lanes (the 300 s / 400 s heat and Poisson lanes c and d are gone: the
# 1,000- and 10,000-step comparisons are the long-study lanes sip_heat_10k and sip_poisson):
#   taskset -c 1 bash docs/reproductions/sip_runs.sh a &  taskset -c 0 bash docs/reproductions/sip_runs.sh b
# Then: python docs/reproductions/sip_report.py  (tables and figures from the study CSVs).
set -euo pipefail
PG=${PHYSGRAD:-physgrad}
OUT=${OUT:-studies/sip}
lane=${1:-all}

lane_a() {
  $PG compare toy2d --steps 10 --set eval_every=1 --out "$OUT/toy2d" --quiet
  $PG compare linear_oscillators --methods adam,sip,hig --seconds 100 --seeds 3 \
    --set eval_seconds=5 --out "$OUT/linear_oscillators" --quiet
  # Poisson and heat 64x64: 100 steps, the first iteration at which the authors' plot script
  # compares Adam with SIP (it also compares at 1,000 and 10,000: the long-study lanes). A step
  # budget, not seconds: a U-Net step costs 5-8 s on one CPU core, so 120 calibrated seconds
  # would be ~20 steps, and a wall-clock budget would carry the machine's load.
  $PG compare poisson --methods adam,sip --steps 100 --seeds 3 \
    --set eval_every=10 --set eval_samples=128 --out "$OUT/poisson-100" --quiet
}

lane_b() {
  $PG compare exp_inverse --methods sgd,adam,sip --seconds 20 --seeds 3 \
    --set eval_seconds=1 --out "$OUT/exp_inverse" --quiet
  $PG compare heat --methods adam,sgd,sip --steps 100 --seeds 3 \
    --set eval_every=10 --set eval_samples=128 --out "$OUT/heat-100" --quiet
  for xi in 1 4 16 64; do  # the paper's xi sweep at phi = 0
    $PG compare sine --methods adam,sip --seconds 20 --seeds 3 --set xi=$xi --set phi=0 \
      --set eval_seconds=1 --set eval_samples=4096 --out "$OUT/sine-xi$xi-phi0" --quiet
  done
  for phi in 0 15 30 45; do  # the paper's phi sweep at xi = 32
    $PG compare sine --methods adam,sip --seconds 20 --seeds 3 --set xi=32 --set phi=$phi \
      --set eval_seconds=1 --set eval_samples=4096 --out "$OUT/sine-xi32-phi$phi" --quiet
  done
}

lane_e() {  # heat without a network (the authors' plot_heat_optim.py): GD vs the iterated inverse
  $PG compare heat --no-network --methods sgd,sip --steps 1000 --seeds 3 --set n_train=128 \
    --set sgd.lr=128 --set sip.optimizer=sgd --set sip.lr=128 --set eval_every=10 \
    --out "$OUT/heat-direct" --quiet
}

case $lane in
  a) lane_a ;;
  b) lane_b ;;
  e) lane_e ;;
  *) lane_a; lane_b; lane_e ;;
esac
