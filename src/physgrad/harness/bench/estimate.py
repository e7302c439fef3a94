"""A bench's plan without running it: per problem the runs it would make and their
estimated wall-clock time, from the calibration (``physgrad bench --quick --plan``).

Where a problem's study directory holds a calibration (``BENCH/<problem>/calibration.json``,
written by a bench that started, or by ``physgrad bench ... --calibrate-only``), each
method's run is estimated as

    steps × (calibrated seconds per step + the loop's own seconds per step) + a run's overhead

with ``steps`` the run's step budget (``seconds / calibrated seconds per step`` for a seconds
budget). The loop's own work per step (:data:`LOOP_SECONDS_PER_STEP`: the Python loop,
reading the loss back, the statistics) is not in the calibrated step and dominates the
cheapest steps; the overhead per run (:data:`RUN_OVERHEAD_SECONDS`: data, network,
evaluations, the final files) is a fixed allowance. A method without a calibration is
estimated at its training budget plus the overhead and marked as such, and its calibration
(compilation and timing, :data:`UNCALIBRATED_COMPILE_SECONDS` each) is counted too. The
figures are planning estimates on an idle machine: a loaded one stretches every step.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ...engine.types import Seconds, Steps
from ..calibration import read
from ..config import Budget

# The engine loop's wall-clock per step beside the calibrated step. The loop runs chunks of
# steps in one compiled call, so its own cost per step is a dispatch shared by the chunk: in
# the HIG toy studies (20 calibrated s, 3 seeds; docs/reproductions/data/short/hig) Adam's
# runs took 5-17 µs and GN's 17-45 µs per step beyond the calibrated step, on a loaded
# 2-core VM. 20 µs is the planning figure. (Before the chunked loop it was 1 ms: one
# dispatch per step.)
LOOP_SECONDS_PER_STEP = 2e-5
RUN_OVERHEAD_SECONDS = 4.0  # a run's data, network, evaluations and final files (small problems)
UNCALIBRATED_COMPILE_SECONDS = 10.0  # compiling and timing a method's step where no calibration records it


def estimate(
    problems: Sequence[str],
    verdicts: Mapping[str, Sequence[Any]],
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    budgets: dict[str, Budget] | None = None,
) -> list[dict[str, Any]]:
    """Per problem: ``runs``, ``methods`` (applicable), ``calibrated`` (of them), the
    estimated ``seconds`` of wall-clock (training, loop and overhead), ``calibration_seconds``
    (the calibration phase still to run) and ``total``. ``verdicts``: the bench's
    applicability (:func:`physgrad.harness.bench.applicability.plan`); ``budgets``: the
    problems whose budget is not ``budget``."""
    rows = []
    default = budget
    for problem in problems:
        budget = (budgets or {}).get(problem, default)
        methods = [v.method for v in verdicts[problem] if v.runs]
        calibration = read(Path(out) / problem)
        seconds = calibration_seconds = 0.0
        calibrated = 0
        for method in methods:
            if calibration is not None and calibration.has(method):
                calibrated += 1
                if isinstance(budget, Seconds):
                    steps = calibration.steps(method, float(budget.amount))
                elif isinstance(budget, Steps):
                    steps = int(budget.amount)
                else:
                    steps = math.nan  # epochs: unknown without the data's size
                train = calibration.time_at(method, steps) + steps * LOOP_SECONDS_PER_STEP
            else:
                train = float(budget.amount) if isinstance(budget, Seconds) else math.nan
                if isinstance(budget, Seconds):
                    calibration_seconds += UNCALIBRATED_COMPILE_SECONDS
            seconds += len(seeds) * (train + RUN_OVERHEAD_SECONDS)
        rows.append({"problem": problem, "budget": str(budget), "methods": len(methods), "runs": len(methods) * len(seeds),
                     "calibrated": calibrated, "seconds": seconds, "calibration_seconds": calibration_seconds,
                     "total": seconds + calibration_seconds})  # fmt: skip
    return rows


def duration(seconds: float) -> str:
    """``3 h 05 min``, ``42 min``, ``35 s`` or ``unknown``."""
    if not math.isfinite(seconds):
        return "unknown"
    if seconds < 90:
        return f"{seconds:.0f} s"
    minutes = round(seconds / 60)
    if minutes < 120:
        return f"{minutes} min"
    return f"{minutes // 60} h {minutes % 60:02d} min"


def plan_lines(rows: Sequence[dict[str, Any]]) -> list[list[str]]:
    """The plan's printable lines (header first), the total last."""
    lines = [["problem", "budget per run", "applicable methods", "runs", "calibrated methods", "estimated time"]]
    for r in rows:
        lines.append([r["problem"], r["budget"], str(r["methods"]), str(r["runs"]), f"{r['calibrated']}/{r['methods']}",
                      duration(r["total"])])  # fmt: skip
    total = sum(r["total"] for r in rows)
    lines.append(["total", "", str(sum(r["methods"] for r in rows)), str(sum(r["runs"] for r in rows)),
                  f"{sum(r['calibrated'] for r in rows)}/{sum(r['methods'] for r in rows)}", duration(total)])  # fmt: skip
    return lines


def total_seconds(rows: Sequence[dict[str, Any]]) -> float:
    return sum(r["total"] for r in rows)


def wall_seconds(rows: Sequence[dict[str, Any]], workers: int) -> float:
    """The plan's wall-clock on ``workers`` workers at best: each problem's calibration one
    method after the other (it times steps alone), its runs spread evenly over the workers,
    one run per worker at a time. A lower bound: a wave of runs that does not divide evenly,
    or a worker's compilation, adds to it."""
    return sum(r["calibration_seconds"] + r["seconds"] / max(workers, 1) for r in rows)
