"""Seeds are the replicates: per-method aggregates over seeds, with every failure counted.

A study trains each method from n seeds, and each seed gives one value of each quantity
(its final test loss, its mean over the test cases). Those n values are the replicates. The
test cases of one seed share one trained network, so they are not n × cases independent
draws of the method: their spread is reported as its own per-seed quantity (each seed's
standard deviation over the test cases, then the median over seeds) and never pooled into
a test.

* A diverged seed is a failure: its value is +∞, the worst, in every aggregate. The median
  is +∞ once half the seeds diverged, the mean as soon as one did, a ranking puts the method
  last; no aggregate is taken over the surviving seeds alone.
* The aggregate is the median over seeds with a 95 % percentile-bootstrap interval over
  seeds (``scipy.stats.bootstrap``, 9,999 resamples from a fixed generator, so a table is
  reproducible); with fewer than 3 seeds there is no interval (``n/a``). An interval end
  that a failure reaches is +∞.
* The mean ± standard deviation over seeds is kept beside it where no seed diverged.
* A ratio between two methods pairs them by seed: the median over seeds of the per-seed
  ratio (:func:`seed_ratios`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

CONFIDENCE = 0.95
RESAMPLES = 9999
MIN_SEEDS_INTERVAL = 3  # below this a bootstrap over seeds has too few distinct resamples to mean anything
BOOTSTRAP_SEED = 0


def as_float(text: Any) -> float:
    """A number read from a CSV cell (str) or JSON; NaN for an empty or non-numeric cell."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return math.nan


def mean_std(values: Sequence[float]) -> tuple[float, float]:
    """Mean ± sample standard deviation of the finite ``values`` (std 0 for a single value,
    NaN, NaN for none). Only for values that are all meant to be finite: an aggregate over
    seeds that may have diverged is :func:`summarize`'s, which counts them."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if finite.size == 0:
        return math.nan, math.nan
    return float(finite.mean()), float(finite.std(ddof=1)) if finite.size > 1 else 0.0


def _median(values: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.median(values, axis=axis)


def bootstrap_interval(values: Sequence[float] | np.ndarray, statistic=_median, confidence: float = CONFIDENCE,
                       resamples: int = RESAMPLES, seed: int = BOOTSTRAP_SEED) -> tuple[float, float]:  # fmt: skip
    """The percentile-bootstrap interval of ``statistic`` (default the median) over the
    seeds' ``values`` (``scipy.stats.bootstrap``, ``method="percentile"``); (NaN, NaN) with
    fewer than :data:`MIN_SEEDS_INTERVAL` values or a NaN among them.

    Failures enter as +∞ (and, in a log-ratio, −∞). The resampling itself runs on finite
    stand-ins far beyond every finite value (the statistic is an order statistic or a mean of
    two, so the stand-ins change nothing else), and an interval end beyond the finite values,
    which only a stand-in can produce, is reported as ±∞."""
    from scipy.stats import bootstrap

    x = np.asarray(values, dtype=float)
    if x.size < MIN_SEEDS_INTERVAL or np.isnan(x).any():
        return math.nan, math.nan
    finite = x[np.isfinite(x)]
    if finite.size == 0:
        return float(x.min()), float(x.max())
    top, bottom = float(finite.max()), float(finite.min())
    beyond = 1e12 * (top - bottom + max(abs(top), abs(bottom)) + 1.0)
    data = np.where(np.isposinf(x), top + beyond, np.where(np.isneginf(x), bottom - beyond, x))
    # random_state: the name every supported SciPy takes (>= 1.15 passes it on as rng)
    result = bootstrap((data,), statistic, n_resamples=resamples, confidence_level=confidence, method="percentile",
                       random_state=np.random.default_rng(seed))  # pyright: ignore[reportCallIssue]  # fmt: skip
    ends = [float(e) for e in (result.confidence_interval.low, result.confidence_interval.high)]
    low, high = (math.inf if e > top else -math.inf if e < bottom else e for e in ends)
    return low, high


def summarize(values: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """One quantity over seeds (failures already +∞): ``n``, ``failed`` (the +∞ values),
    ``median`` with its bootstrap interval ``low``/``high`` (NaN below 3 seeds), and ``mean``
    ± ``std`` (+∞ and NaN once a seed failed; std 0 for one seed). NaN values (no value
    recorded) are left out; an empty input gives NaN throughout."""
    x = np.asarray(values, dtype=float)
    x = x[~np.isnan(x)]
    failed = int(np.isposinf(x).sum())
    if x.size == 0:
        return {"n": 0, "failed": 0, "median": math.nan, "low": math.nan, "high": math.nan, "mean": math.nan,
                "std": math.nan}  # fmt: skip
    low, high = bootstrap_interval(x)
    if failed:
        mean, std = math.inf, math.nan
    else:
        mean, std = float(x.mean()), float(x.std(ddof=1)) if x.size > 1 else 0.0
    return {"n": int(x.size), "failed": failed, "median": float(np.median(x)), "low": low, "high": high,
            "mean": mean, "std": std}  # fmt: skip


def seed_ratio(a: float, b: float) -> float:
    """One seed's ratio a / b of two methods' values, failures (+∞) included: a failure
    against a value is +∞ (or 0 the other way round), two failures are a tie (1), as are two
    zeros; a positive value against 0 is +∞. NaN where either value is missing."""
    if math.isnan(a) or math.isnan(b):
        return math.nan
    if math.isinf(a) and math.isinf(b):
        return 1.0
    if math.isinf(b):
        return 0.0
    if b == 0:
        return 1.0 if a == 0 else math.inf
    return a / b


def ratio_summary(ratios: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """Per-seed ratios over seeds: ``n``, the ``median`` and its bootstrap interval
    ``low``/``high``, taken on the logarithms. So a ratio and its inverse agree (for an even
    count the median is the geometric mean of the two middle ratios), and a failure in a
    middle seed decides the median (a ratio of +∞ or 0 is ±∞ there, never averaged into a
    finite value); failures on both sides of the middle leave it undefined (NaN). NaN
    ratios are left out."""
    r = np.asarray(ratios, dtype=float)
    r = r[~np.isnan(r)]
    if r.size == 0:
        return {"n": 0, "median": math.nan, "low": math.nan, "high": math.nan}
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.log(r)
        median = float(np.exp(np.median(logs)))
    low, high = bootstrap_interval(logs)
    return {"n": int(r.size), "median": median, "low": math.exp(low), "high": math.exp(high)}


def seed_ratios(a: Mapping[Any, float], b: Mapping[Any, float]) -> np.ndarray:
    """Per-seed ratios a / b (:func:`seed_ratio`) over the seeds both have, in seed order."""
    return np.array([seed_ratio(a[s], b[s]) for s in sorted(set(a) & set(b), key=str)], dtype=float)


# --- formatting ------------------------------------------------------------------------------


def number(x: float, spec: str = ".3e") -> str:
    """A value for a table: ``∞`` for a failure, ``n/a`` for NaN."""
    if math.isnan(x):
        return "n/a"
    return "∞" if math.isinf(x) else format(x, spec)


def interval(summary: Mapping[str, Any], spec: str = ".2e") -> str:
    """``[low, high]``, or ``[n/a: 2 seeds]`` where there are fewer than 3 seeds."""
    if summary["n"] < MIN_SEEDS_INTERVAL:
        return f"[n/a: {summary['n']} seed{'s' if summary['n'] != 1 else ''}]"
    return f"[{number(summary['low'], spec)}, {number(summary['high'], spec)}]"


def median_cell(summary: Mapping[str, Any]) -> str:
    """``1.234e-03 [1.1e-03, 1.5e-03]``: the median over seeds and its 95 % interval."""
    if summary["n"] == 0:
        return "no value"
    return f"{number(summary['median'])} {interval(summary)}"


def mean_cell(summary: Mapping[str, Any]) -> str:
    """``mean ± std`` over seeds, or ``∞ (a seed diverged)``: no mean over the survivors."""
    if summary["n"] == 0:
        return "no value"
    if summary["failed"]:
        return f"∞ ({summary['failed']} diverged)"
    return f"{summary['mean']:.3e} ± {summary['std']:.1e}"


def runs_cell(runs: int, diverged: int) -> str:
    """``3`` or ``3 (1 of 3 diverged)``."""
    return f"{runs}" + (f" ({diverged} of {runs} diverged)" if diverged else "")


# --- a study's table: one row per method -----------------------------------------------------

TABLE_NOTE = ("over seeds: medians [95% bootstrap CI, from 3 seeds], a diverged seed counts as ∞; ratios: median "
              "of the per-seed ratios; test-case spread: median over seeds of each seed's std over the test cases")  # fmt: skip


# a run whose in-run ms/step is outside [1/RATIO_LIMIT, RATIO_LIMIT] x its calibrated one is flagged
RATIO_LIMIT = 1.2
# The in-run ms/step (a row of :func:`aggregate`) on each calibration clock
# (harness.calibration.CLOCKS, the record's "clock"), and what that clock counts.
IN_RUN = {"wall": "ms_per_step", "cpu": "cpu_ms_per_step"}
CLOCK_WORDS = {"wall": "wall-clock seconds", "cpu": "the run's CPU seconds, its thread's and XLA's (engine.cpu_clock)"}


def row_clock(row: Mapping[str, Any]) -> str:
    """The clock a row's calibrated ms/step was timed on ("wall" where unrecorded: a record
    written before the cpu clock, or a test's fake clock)."""
    clock = row.get("clock") or "wall"
    return clock if clock in IN_RUN else "wall"


def calibration_ratio(row: Mapping[str, Any]) -> float:
    """A method's in-run ms/step over its calibrated one, both on the calibration's clock
    (:func:`row_clock`: the in-run wall-clock or CPU seconds per step; medians over seeds;
    NaN without)."""
    in_run, calibrated = row.get(IN_RUN[row_clock(row)], math.nan), row.get("calibrated_ms", math.nan)
    return in_run / calibrated if math.isfinite(in_run) and math.isfinite(calibrated) and calibrated > 0 else math.nan


def mismatched(row: Mapping[str, Any]) -> bool:
    """Whether a method's in-run step cost is more than RATIO_LIMIT away from its calibrated one."""
    r = calibration_ratio(row)
    return math.isfinite(r) and not 1 / RATIO_LIMIT <= r <= RATIO_LIMIT


def table_note(table: Sequence[Mapping[str, Any]]) -> str:
    """:data:`TABLE_NOTE`; where the rows name their calibration's clock, a line saying which
    clock the in-run / calibrated ratio is on; and a line naming the methods whose in-run step
    cost is outside [1/1.2, 1.2]x the calibrated one (their budgets did not take the seconds
    they stand for)."""
    lines = [TABLE_NOTE]
    clocks = sorted({row_clock(t) for t in table if t.get("clock") and math.isfinite(t.get("calibrated_ms", math.nan))})
    if clocks:
        lines.append(f"in-run / calibrated ms/step: both on the {' and '.join(clocks)} clock "
                     f"({'; '.join(CLOCK_WORDS[c] for c in clocks)} per step)")  # fmt: skip
    flagged = [f"{t['method']} {calibration_ratio(t):.2f}x" for t in table if mismatched(t)]
    if flagged:
        lines.append(f"* in-run / calibrated ms/step outside [1/{RATIO_LIMIT:g}, {RATIO_LIMIT:g}]: "
                     f"{', '.join(flagged)} (a loaded machine, or a calibration that did not time the run's step)")  # fmt: skip
    return "\n".join(lines)


def seed_values(rows: Sequence[Mapping[str, Any]], method: str, key: str) -> dict[str, float]:
    """{seed: value of ``key``} of one method's runs, +∞ for a diverged run (a finished run
    without a value keeps NaN: nothing was recorded, which is not a failure)."""
    out = {}
    for r in rows:
        if r["method"] == method:
            out[str(r["seed"])] = math.inf if r["status"] == "diverged" else as_float(r[key])
    return out


def aggregate(rows: list[dict[str, Any]], order: Sequence[str], spread: Mapping[str, float] | None = None):
    """Per method: runs, diverged count, the final and best test loss over seeds
    (:func:`summarize`, a diverged seed's final loss +∞), its per-seed final losses
    (``seeds``, for ratios paired by seed), the test-case spread (``spread``: the median
    over seeds of each seed's std over the test cases, :func:`physgrad.harness.stats.case_spread`;
    NaN where unknown), steps and time per step (medians over seeds).

    ``final_test_loss`` and ``best_test_loss`` keep their (mean, std) pairs for older
    readers; the mean is +∞ once a seed diverged."""
    table = []
    for method in order:
        runs = [r for r in rows if r["method"] == method]
        if not runs:
            continue
        seeds = seed_values(runs, method, "final_test_loss")
        final = summarize(list(seeds.values()))
        best = summarize([as_float(r["best_test_loss"]) for r in runs])  # a diverged run's best is real
        steps = [as_float(r["steps"]) for r in runs]
        times = [as_float(r["time_per_step"]) for r in runs]
        cpu_times = [as_float(r.get("cpu_time_per_step")) for r in runs]
        calibrated = [as_float(r.get("calibrated_ms_per_step")) for r in runs]
        clock = next((str(r["calibration_clock"]) for r in runs if r.get("calibration_clock")), None)
        table.append({
            "method": method, "runs": len(runs), "diverged": sum(r["status"] == "diverged" for r in runs),
            "final": final, "best": best, "seeds": seeds, "spread": (spread or {}).get(method, math.nan),
            "final_test_loss": (final["mean"], final["std"]), "best_test_loss": (best["mean"], best["std"]),
            "steps": float(np.nanmedian(steps)) if not np.isnan(steps).all() else math.nan,
            "ms_per_step": 1e3 * float(np.nanmedian(times)) if not np.isnan(times).all() else math.nan,
            "cpu_ms_per_step": 1e3 * float(np.nanmedian(cpu_times)) if not np.isnan(cpu_times).all() else math.nan,
            "calibrated_ms": float(np.nanmedian(calibrated)) if not np.isnan(calibrated).all() else math.nan,
            "clock": clock,  # the calibration's clock (None: unrecorded, the wall clock)
        })  # fmt: skip
    return table


def paired_ratio(row: Mapping[str, Any], reference: Mapping[str, Any]) -> dict[str, Any]:
    """A method's final loss over the reference's, paired by seed: the median over their
    common seeds of the per-seed ratios and its bootstrap interval (:func:`ratio_summary`)."""
    return ratio_summary(seed_ratios(row["seeds"], reference["seeds"]))


def format_table(table: list[dict[str, Any]], reference: str | None = None) -> list[list[str]]:
    """Rows of strings for printing, header first: runs (``k of n diverged``), the final test
    loss as median [95 % interval] over seeds and as mean ± std over seeds (``∞`` once a seed
    diverged), the test-case spread, the best test loss (median over seeds), steps and
    ms/step (medians); ``reference`` adds the median over seeds of the per-seed ratio to that
    method (:func:`ratio_summary`). :data:`TABLE_NOTE` says so under a table. A calibrated
    study adds the calibrated ms/step and the in-run over calibrated ratio on the
    calibration's clock, marked ``*`` outside [1/1.2, 1.2] (:func:`table_note` names them
    under the table); calibrated on the cpu clock, the in-run CPU ms/step too."""
    ref = next((t for t in table if t["method"] == reference), None)
    header = ["method", "runs", "final test loss, median [95% CI]", "mean ± std", "test-case spread",
              "best test loss", "steps", "ms/step"]  # fmt: skip
    calibrated = any(math.isfinite(t.get("calibrated_ms", math.nan)) for t in table)
    clock = next((row_clock(t) for t in table if t.get("clock")), "wall")
    if calibrated:
        header[-1] = "ms/step (wall)"
        header += [*([f"ms/step ({clock})"] if clock != "wall" else []), "calibrated ms/step", f"{clock} / calibrated"]
    if ref is not None:
        header.append(f"final / {reference}")
    lines = [header]
    for t in table:
        line = [t["method"], runs_cell(t["runs"], t["diverged"]), median_cell(t["final"]), mean_cell(t["final"]),
                number(t["spread"], ".1e"), number(t["best"]["median"]), f"{t['steps']:.0f}",
                f"{t['ms_per_step']:.2f}"]  # fmt: skip
        if calibrated:
            ratio = calibration_ratio(t)
            line += [f"{t.get(IN_RUN[clock], math.nan):.2f}"] if clock != "wall" else []
            line += [number(t.get("calibrated_ms", math.nan), ".3g"),
                     "-" if math.isnan(ratio) else f"{ratio:.2f}{' *' if mismatched(t) else ''}"]  # fmt: skip
        if ref is not None:
            ratio = paired_ratio(t, ref)
            line.append("-" if ratio["n"] == 0 else f"{number(ratio['median'], '.3g')} {interval(ratio, '.3g')}")
        lines.append(line)
    return lines
