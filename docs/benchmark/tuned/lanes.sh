#!/bin/bash
# The tuned profile over every problem family (issue 50, item 5): physgrad bench --tuned, i.e.
# every applicable candidate gets the same 5 quasi-random trials from its declared search space
# (physgrad.harness.spaces), is chosen on a validation split, and the chosen configuration runs
# on 3 seeds on test. One bench directory per lane under docs/benchmark/tuned/, committed as it
# grows; the same command again resumes (finished trials and runs are kept).
#
# CPU-sized: the U-Net problems at 32x32 with 1,024 training samples and batch 16 (an Adam step
# ~80 ms on one core; at the paper's 64x64 and batch 64-128 a step costs seconds); every other
# problem at its shipped settings; the dense open-loop problems are the quick profile's.
# Exact HIG, GN and LM are left out of the U-Nets and ks (one step costs thousands of Adam steps
# there: docs/benchmark.md) and kept where they are affordable (advection_1d, the dense lane).
#
# Calibrated on the CPU clock ($PHYSGRAD_CALIBRATION_CLOCK=cpu): a step's budget counts its
# process's CPU seconds, so the lanes can share a loaded machine without the neighbours'
# load changing any run's number of steps. One core, niced, one run at a time by default
# (WORKERS=2 on an idle 2-core machine: the numbers do not change).
#   bash docs/benchmark/tuned/lanes.sh                 # every lane in order, on core $CORE (default 0)
#   bash docs/benchmark/tuned/lanes.sh closed_loop     # one lane; extra arguments go to physgrad bench
#   bash docs/benchmark/tuned/lanes.sh unets --plan    # its plan (estimated time), nothing run
# OUT_ROOT puts the bench directories elsewhere (docs/benchmark/tuned/workers.sh: a lane again
# on 1 and on 2 workers in scratch directories).
# physgrad report docs/benchmark/tuned/<lane> redraws a lane's leaderboard from a clone.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../../.." && pwd)"
# Each lane runs one commit from start to end. closed_loop ran at b8150ef; the others run at
# 8069c83, which builds stabilised BPTT (C) and LM on the time-steppers (at b8150ef their steps
# failed on the samples' integer solver index, and the bench left them out) and whose khig has
# the Kronecker factors of convolutions (at b8150ef a convolution's kernel went to khig's exact
# leftover block: on advection_1d's one-layer Conv1d, exact HIG by another name).
CLOSED_LOOP_COMMIT="${CLOSED_LOOP_COMMIT:-b8150ef}"
TUNED_COMMIT="${TUNED_COMMIT:-8069c83}"
CORE="${CORE:-0}"
WORKERS="${WORKERS:-1}"
PY="${PY:-$ROOT/.venv/bin/python}"
# shellcheck source=../lane_common.sh
source "$ROOT/docs/benchmark/lane_common.sh"
export PHYSGRAD_CALIBRATION_CLOCK=cpu

lane() {  # lane NAME ARGS...: one bench directory, at the lane's commit in its own worktree
  local name=$1; shift
  if [ "$name" = closed_loop ]; then
    CODE="$ROOT/../studycode-tuned"; pin_worktree "$ROOT" "$CODE" "$CLOSED_LOOP_COMMIT"
  else
    CODE="$ROOT/../studycode-tuned-${TUNED_COMMIT:0:7}"; pin_worktree "$ROOT" "$CODE" "$TUNED_COMMIT"
  fi
  tuned_bench "tuned lane $name at $(git -C "$CODE" rev-parse --short=7 HEAD)" "${OUT_ROOT:-$ROOT/docs/benchmark/tuned}/$name" "$@"
}

UNET="--set poisson.resolution=32 --set heat.resolution=32 --set navier_stokes.resolution=32"
UNET="$UNET --set n_train=1024 --set n_test=64 --set batch_size=16"
run() {
  local which=$1; shift
  case "$which" in
    closed_loop) lane closed_loop --problems cartpole,guidance,quantum_control --seconds 60 \
        --methods adam,rmsprop,optax:adamw,optax.contrib:muon,kfac,bptt,sbptt_m,sbptt_c,no_temporal "$@" ;;
    advection_1d) lane advection_1d --problems advection_1d --seconds 20 \
        --methods one,nog,wig,bptt,sbptt_c,no_temporal,adam,optax:adamw,optax.contrib:muon,kfac,hig,gn,lm,khig "$@" ;;
    ks) lane ks --problems ks --seconds 120 --methods one,nog,wig,sbptt_c,optax:adamw,optax.contrib:muon "$@" ;;
    # shellcheck disable=SC2086
    unets) lane unets --problems poisson,heat,navier_stokes --seconds 120 $UNET \
        --methods adam,rmsprop,optax:adamw,optax.contrib:muon,sip,khig "$@" ;;
    dense) lane dense --quick "$@" ;;
    *) echo "unknown lane $which: closed_loop, advection_1d, ks, unets or dense" >&2; exit 2 ;;
  esac
}

if [ $# -eq 0 ]; then
  for which in closed_loop advection_1d ks unets dense; do run "$which"; pack_finished "$ROOT"; done
else
  run "$@"
fi
