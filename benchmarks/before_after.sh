#!/bin/bash
# The step benchmarks of an earlier commit and of this tree, back to back, pinned to one core:
#   bash benchmarks/before_after.sh OLD_COMMIT [CORE]
# The old code runs from a git worktree (../before-OLD_COMMIT) with its own benchmarks; both
# with float64 enabled as the command line runs (the old code enabled it on import). Two
# rounds each, alternating, so drift in the machine's load shows as a round-to-round spread.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
OLD_COMMIT=${1:?usage: before_after.sh OLD_COMMIT [CORE]}
CORE=${2:-1}
PY="$ROOT/.venv/bin/python"
OLD="$ROOT/../before-$OLD_COMMIT"
[ -d "$OLD/src/physgrad" ] || git -C "$ROOT" worktree add --detach "$OLD" "$OLD_COMMIT"
# BENCHES (one benchmark command per line) replaces the default list, e.g. to leave out
# poisson_hig's 20-second HIG steps: BENCHES=$'hig_step.py --problems hig_toy,oscillators --repeats 30'
DEFAULT_BENCHES=$'hig_step.py --repeats 30\nsip_step.py --repeats 20\nrollout_step.py --repeats 10\nunrolling_step.py --repeats 10'
while IFS= read -r bench; do
  [ -n "$bench" ] || continue
  for round in 1 2; do
    echo "=== before ($OLD_COMMIT), round $round: $bench"
    (cd "$OLD/benchmarks" && PYTHONPATH="$OLD/src" JAX_ENABLE_X64=1 taskset -c "$CORE" "$PY" $bench </dev/null)
    echo "=== after (working tree), round $round: $bench"
    (cd "$ROOT/benchmarks" && JAX_ENABLE_X64=1 taskset -c "$CORE" "$PY" $bench </dev/null)
  done
done <<<"${BENCHES:-$DEFAULT_BENCHES}"
