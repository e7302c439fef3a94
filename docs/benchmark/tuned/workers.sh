#!/bin/bash
# One tuned lane again on 1 and on 2 workers (issue 50: the profile's wall time with 1 and 2
# workers): the same `lanes.sh LANE` twice into scratch directories, each given the committed
# lane's calibration (so every run trains the steps the committed one trained), timed on the
# wall clock, then its tables compared byte for byte with each other and with the committed
# lane's. It needs the machine to itself: stop the other lanes first (kill -STOP their process
# groups; budgets are CPU seconds, so a paused lane loses nothing).
#   bash docs/benchmark/tuned/workers.sh                # advection_1d (~47 min + ~25 min idle)
#   bash docs/benchmark/tuned/workers.sh closed_loop    # any finished lane of lanes.sh
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/../../.." && pwd)"
LANE="${1:-advection_1d}"
SCRATCH="${SCRATCH:-${TMPDIR:-/tmp}/physgrad-workers-$LANE}"
COMMITTED="$ROOT/docs/benchmark/tuned/$LANE"
[ -f "$COMMITTED/bench.json" ] || { echo "no finished lane $LANE under docs/benchmark/tuned" >&2; exit 2; }
TABLES="leaderboard.csv hyperparameters.csv bench_table.csv"

for workers in 1 2; do
  out="$SCRATCH/workers$workers"
  rm -rf "$out" && mkdir -p "$out/$LANE"
  # the committed calibration, each file at its place (a problem's and its test study's)
  (cd "$COMMITTED" && find . -name 'calibration.json' -o -name 'calibration.csv') | while read -r f; do
    mkdir -p "$out/$LANE/$(dirname "$f")" && cp "$COMMITTED/$f" "$out/$LANE/$f"
  done
  cores=$([ "$workers" = 1 ] && echo 0 || echo 0,1)
  start=$(date +%s)
  OUT_ROOT="$out" WORKERS="$workers" CORE="$cores" bash "$ROOT/docs/benchmark/tuned/lanes.sh" "$LANE" > "$out.log" 2>&1
  echo "$LANE on $workers worker(s): $(( $(date +%s) - start )) s of wall clock (log: $out.log)"
done

status=0
for table in $TABLES; do
  for other in "$SCRATCH/workers2/$LANE" "$COMMITTED"; do
    if cmp -s "$SCRATCH/workers1/$LANE/$table" "$other/$table"; then
      echo "$table: workers 1 = ${other#"$ROOT/"}"
    else
      echo "$table: workers 1 differs from ${other#"$ROOT/"}"; status=1
    fi
  done
done
exit $status
