#!/usr/bin/env bash
# The built wheel in a fresh venv, core only (no extras): what `pip install physgrad` will give a
# user. Builds dist/ (make dist) unless WHEEL=path is given, installs the wheel into a new venv
# under a temporary directory, and runs the command line and a short library use there, from
# outside the source tree (so `import physgrad` is the installed copy, not src/).
# Usage: .ci/smoke.sh  (or WHEEL=dist/physgrad-X-py3-none-any.whl .ci/smoke.sh); PYTHON=python3.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
if [ -z "${WHEEL:-}" ]; then
    make dist
    WHEEL=$(ls dist/physgrad-*-py3-none-any.whl)
fi
WHEEL=$(realpath "$WHEEL")
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PYTHON" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --quiet --upgrade pip
"$tmp/venv/bin/python" -m pip install --quiet "$WHEEL"
cd "$tmp"
export PATH="$tmp/venv/bin:$PATH"
physgrad --version
physgrad list
physgrad train hig_toy --method adam --steps 50 --out "$tmp/run"
test -f "$tmp/run/summary.json"
python - <<'PY'
import optax

import physgrad
from physgrad.methods import Gradient
from physgrad.problems import HigToy

assert physgrad.__file__.startswith(__import__("sys").prefix), physgrad.__file__  # the installed copy
adam = physgrad.Method(Gradient(), optax.adam(1e-3))
result = physgrad.fit(HigToy(), adam, budget=physgrad.Budget(steps=20), name="adam")
print("fit:", result.summary["status"], "final test loss", result.summary["final_test_loss"])
assert len(result.history["test_loss"]) >= 2
PY
echo "smoke test passed: $(basename "$WHEEL")"
