#!/bin/bash
# Sourced by the lane scripts (docs/benchmark/tuned/lanes.sh, docs/benchmark/tuned/kronecker.sh,
# docs/reproductions/long/studies.sh): what every lane does the same way.
#
# A lane runs one fixed commit of physgrad from a detached git worktree, so that development on
# main cannot change a study half-way; its run directories live in this repository and are
# committed as they grow. The budget is CPU seconds (PHYSGRAD_CALIBRATION_CLOCK=cpu) where the
# lane says so: sharing the core with other niced lanes then stretches the wall-clock, not the
# runs.

# pin_worktree ROOT DIR COMMIT: the detached worktree DIR of the repository ROOT, created at COMMIT
# if missing; refuses (exit 2) a DIR at another commit rather than run the lane on other code.
pin_worktree() {
  local root=$1 dir=$2 commit=$3
  [ -d "$dir/src/physgrad" ] || git -C "$root" worktree add --detach "$dir" "$commit"
  [ "$(git -C "$dir" rev-parse --short=7 HEAD)" = "${commit:0:7}" ] || { echo "worktree $dir is not at $commit" >&2; exit 2; }
}

# tuned_bench TITLE OUT ARGS...: one `physgrad bench --tuned` directory OUT (5 trials, 3 seeds),
# niced on core $CORE with $WORKERS workers, from the pinned code in $CODE with the python $PY.
tuned_bench() {
  local title=$1 out=$2; shift 2
  echo "== $title ($(date -u +%FT%TZ))"
  PYTHONPATH="$CODE/src" nice -n 19 taskset -c "$CORE" "$PY" -m physgrad bench --tuned --trials 5 --seeds 3 \
    --workers "$WORKERS" --quiet --out "$out" "$@"
}

# pack_finished ROOT: after a lane, the finished runs' checkpoints removed and every finished tuned
# problem's curves gzipped (docs/reproductions/long/prune.py --pack-finished; the reports and a
# resumed lane read them packed), so that the next lane commit carries no plain curves of a
# finished problem.
pack_finished() {
  "$PY" "$1/docs/reproductions/long/prune.py" --root "$1/docs/benchmark/tuned" --pack-finished | tail -n 2
}
