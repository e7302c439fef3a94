#!/bin/bash
# The Kronecker verdict, tuned (issue 51, item 5): physgrad bench --tuned (5 quasi-random trials
# per method and problem from its declared search space, chosen on validation, then 3 seeds on
# test) of the Kronecker-factored HIG forms against exact HIG, K-FAC, LM, Adam and AdamW, with
# the power ablation in the same benches. One bench directory per lane,
# docs/benchmark/tuned/kronecker_<lane>/, committed as it grows; the same command resumes it.
#
# Candidates: khig (p = -3/4), kgn and khig_half (khig at p = -1 and -1/2: the power ablation,
# registered names so that the three powers share one bench and one calibration sitting), ekhig
# (eigenvalue-corrected), kfac (kfac-jax, precon_power -1) and kfac_hig (precon_power -0.75),
# hig (exact), lm, adam, optax:adamw. Each problem's methods are calibrated one after the other
# at the start of its tune, so every cost ratio of a problem comes from one sitting.
#   dense        oscillators, quantum_dipole at their shipped settings; kfac and kfac_hig do not
#                apply to the dipole (complex simulator output: the bench lists them as such).
#   poisson_hig  poisson_hig at its shipped settings (batch 64). Exact HIG and LM left out: one
#                step ~19 s on one core, ~15,000 Adam steps (docs/performance.md), so 120 s
#                buys ~6 steps.
#   unets        poisson, heat, navier_stokes at lanes.sh's CPU size (32x32, 1,024 training
#                samples, batch 16). khig/kgn/khig_half with probes=1 (G from one random output
#                direction per sample; probes=0 needs b*dim y = 16,384 backward passes a step
#                and ~16 GiB: the memory guard refused ekhig's step so on a 16 GiB host),
#                fresh factors (HIG's way, khig's default; a step ~2.5-4.4 Adam steps,
#                docs/methods.md), and the learning rate searched around 1e-4 instead of
#                khig's 1 (trial 0 and the centre of the two decades either side). Probed on
#                poisson at this size (256 samples, 40 steps): lr 1, 0.1, 0.01 and 1e-3
#                diverged within 10 steps at damping 1e-4 (0.01 also at damping 0.1); 1e-4
#                trained at damping 1e-4 and 0.1 (test loss 5.4e4 -> 1.1e4 and 1.6e4), 1e-5 more
#                slowly (3.0e4); heat and navier_stokes were not probed. The running factors
#                that would bring a step near 1.3-2.4 Adam steps (curvature_ema 0.95,
#                refreshed every 10 steps) diverged at step 12 at
#                lr 1e-4, damping 0.1 (two steps after its first refresh), so not used.
#                Left out: hig and lm (thousands of Adam steps per step), kfac and kfac_hig
#                (kfac-jax refuses convolutions), ekhig (its correction is for dense layers
#                only, and it has no probes: 16 GiB).
#
# Plan (bash docs/benchmark/tuned/kronecker.sh LANE --plan, uncalibrated: a run costs its
# budget plus ~4 s on an idle core, 10 s per method to calibrate; 120 calibrated seconds per
# run, one worker):
#   dense        144 runs (oscillators 10 methods x 8 runs: 2 h 47 min; quantum_dipole 8 x 8:
#                2 h 14 min)                                                         5 h 01 min
#   poisson_hig   64 runs (8 methods x 8 runs)                                       2 h 14 min
#   unets        120 runs (3 problems x 5 methods x 8 runs, 84 min each)             4 h 10 min
#   total        328 runs, about 11 h 25 min of one core's CPU time (compilation under load
#   comes on top: minutes per method at load 15-20). The budget is CPU seconds
#   (PHYSGRAD_CALIBRATION_CLOCK=cpu), so sharing the core with other niced lanes stretches the
#   wall-clock, not the runs.
#
# Pinned code: a detached worktree of physgrad at $KRON_COMMIT in $CODE (default
# ../studycode-kron beside the repository), so that the lanes run one fixed commit while the
# main tree moves on; never /work/studycode-tuned (lanes.sh's, pinned at b8150ef). The default
# commit is the first with kgn and khig_half (main's d179ddb, conv KHIG with running factors,
# plus those two names).
# Start (one core, niced; every lane in order, or one lane; extra arguments go to physgrad bench):
#   CORE=0 nohup bash docs/benchmark/tuned/kronecker.sh > kronecker.log 2>&1 &
#   bash docs/benchmark/tuned/kronecker.sh unets          # one lane
#   bash docs/benchmark/tuned/kronecker.sh dense --plan   # its plan, nothing run
# physgrad report docs/benchmark/tuned/kronecker_<lane> redraws a lane's leaderboard from a clone.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../../.." && pwd)"
CODE="${CODE:-$ROOT/../studycode-kron}"
KRON_COMMIT="${KRON_COMMIT:-2463647}"
CORE="${CORE:-0}"
WORKERS="${WORKERS:-1}"
PY="${PY:-$ROOT/.venv/bin/python}"
# shellcheck source=../lane_common.sh
source "$ROOT/docs/benchmark/lane_common.sh"
pin_worktree "$ROOT" "$CODE" "$KRON_COMMIT"
export PHYSGRAD_CALIBRATION_CLOCK=cpu

lane() {  # lane NAME ARGS...: one bench directory
  local name=$1; shift
  tuned_bench "kronecker lane $name" "$ROOT/docs/benchmark/tuned/kronecker_$name" "$@"
}

KRON="khig,kgn,khig_half"
UNET="--set poisson.resolution=32 --set heat.resolution=32 --set navier_stokes.resolution=32"
UNET="$UNET --set n_train=1024 --set n_test=64 --set batch_size=16"
for m in khig kgn khig_half; do UNET="$UNET --set $m.probes=1 --set $m.lr=0.0001"; done  # one probe; lr: header
run() {
  local which=$1; shift
  case "$which" in
    dense) lane dense --problems oscillators,quantum_dipole --seconds 120 \
        --methods adam,optax:adamw,lm,hig,kfac,kfac_hig,$KRON,ekhig "$@" ;;
    poisson_hig) lane poisson_hig --problems poisson_hig --seconds 120 \
        --methods adam,optax:adamw,kfac,kfac_hig,$KRON,ekhig "$@" ;;
    # shellcheck disable=SC2086
    unets) lane unets --problems poisson,heat,navier_stokes --seconds 120 $UNET \
        --methods adam,optax:adamw,$KRON "$@" ;;
    *) echo "unknown lane $which: dense, poisson_hig or unets" >&2; exit 2 ;;
  esac
}

if [ $# -eq 0 ]; then
  for which in dense poisson_hig unets; do run "$which"; pack_finished "$ROOT"; done
else
  run "$@"
fi
