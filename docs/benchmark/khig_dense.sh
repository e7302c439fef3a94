#!/bin/bash
# The standard profile (physgrad bench --standard: paper settings and batch sizes, full
# datasets, 300 calibrated seconds per run; 5-20 s on the four problems with sub-millisecond
# steps) on the seven open-loop problems with dense networks, for the Kronecker-factored HIG
# against exact HIG, K-FAC, Levenberg-Marquardt, Adam and two optax optimizers; 3 seeds (the
# profile's 5 can be grown later with --seeds 5). About 6 h on one core; resumable: run it
# again to go on. Results: python -m physgrad bench ... prints the tables again from the
# finished runs; the study-level files are kept with docs/reproductions/keep_studies.py.
#   PG="taskset -c 0 physgrad" OUT=bench-dense bash docs/benchmark/khig_dense.sh
# Split over cores (each lane its own directory, committed as it grows):
# docs/benchmark/lanes/run.sh; then gather every finished problem into docs/benchmark/dense with
#   python docs/reproductions/keep_studies.py docs/benchmark/lanes/coreN docs/benchmark/dense --runs
# and redraw the whole bench from the clone: physgrad report docs/benchmark/dense
set -e
PG="${PG:-physgrad}"
$PG bench --standard --problems hig_toy,toy2d,exp_inverse,sine,oscillators,linear_oscillators,quantum_dipole \
  --methods adam,optax:adamw,optax.contrib:muon,kfac,lm,hig,khig --seeds 3 \
  --out "${OUT:-bench-dense}" --quiet "$@"
