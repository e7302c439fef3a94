#!/bin/bash
# KHIG standard-settings bench lanes (issue 34): docs/benchmark/khig_dense.sh's profile split over
# two cores, each lane its own bench directory under docs/benchmark/lanes/ (committed as it grows,
# so a later session resumes it). physgrad 195663f (worktree /work/studycode-bench), nice 5.
#   bash docs/benchmark/lanes/run.sh 0 oscillators,linear_oscillators [--calibrate-only]
#   bash docs/benchmark/lanes/run.sh 1 quantum_dipole
# Finished 2026-11-27 (all 7 problems); every lane directory was kept, runs included, into
# docs/benchmark/dense (keep_studies.py --runs) and then removed here.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../../.." && pwd)"
core=$1 problems=$2; shift 2
CODE=/work/studycode-bench
[ -d "$CODE/src/physgrad" ] || git -C "$ROOT" worktree add --detach "$CODE" 195663f
env PYTHONPATH="$CODE/src" nice -n 5 taskset -c "$core" "$ROOT/.venv/bin/python" -m physgrad bench --standard \
  --problems "$problems" --methods adam,optax:adamw,optax.contrib:muon,kfac,lm,hig,khig --seeds 3 \
  --out "$ROOT/docs/benchmark/lanes/core$core" --quiet "$@"
