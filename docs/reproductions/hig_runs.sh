#!/bin/bash
# The studies behind docs/reproductions/hig.md. Each line is a `physgrad compare`; a study
# that is interrupted resumes where it stopped when its line is run again.
# The published numbers ran each batch pinned to one core of a 2-core CPU
# (taskset -c 1 for the first three lines, taskset -c 0 for the rest, the two batches side by side).
# Then: python docs/reproductions/hig_report.py
set -e
PG="${PG:-physgrad}"
$PG compare hig_toy --methods adam,gn,hig --seeds 3 --seconds 20 --set lam=0.01 --set eval_seconds=0.2 --out studies/hig/toy_lam0.01 --quiet
$PG compare hig_toy --methods adam,gn,hig --seeds 3 --seconds 20 --set lam=1 --set eval_seconds=0.2 --out studies/hig/toy_lam1 --quiet
$PG compare oscillators --seeds 3 --seconds 120 --set eval_seconds=2 --out studies/hig/oscillators --quiet
$PG compare linear_oscillators --seeds 3 --seconds 100 --set eval_seconds=1 --out studies/hig/linear_oscillators --quiet
$PG compare quantum_dipole --seeds 3 --seconds 150 --set eval_seconds=5 --out studies/hig/quantum_dipole --quiet
$PG compare poisson_hig --methods adam,hig --seeds 3 --seconds 60 --set eval_seconds=2 --out studies/hig/poisson_hig --quiet
$PG compare poisson_hig --methods hig,adam:1413,hig --seeds 3 --seconds 60 --set hig.batch_size=8 --set eval_seconds=2 --out studies/hig/poisson_hig_b8 --quiet
