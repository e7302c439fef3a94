"""Paired statistics between the methods of a study, with the seeds as the replicates.

Every run writes ``test_cases.json``: its final metrics on each test case. The test cases of
one seed share one trained network, so they are not independent draws of the training
method; the seeds are (:mod:`physgrad.harness.seeds`). Each seed therefore gives one value
per method, the mean over its test cases, and two methods are compared on their common
seeds, paired by seed:

* ``seeds``, ``seeds_a_lower`` and ``ties``: how many seeds were paired, on how many the
  first method was lower and on how many the two were equal (two diverged seeds tie);
* ``ratio`` (``ratio_low``, ``ratio_high``): the median over seeds of the per-seed ratio of
  the means, with its 95 % bootstrap interval over seeds (``n/a`` below 3 seeds);
* ``p_value``: the two-sided Wilcoxon signed-rank test of the per-seed differences, only
  where it can say something. Over n seeds with a difference the exact test cannot go
  below 2/2^n (0.0625 at n = 5), so below :data:`MIN_SEEDS_P` = 6 seeds there is no
  p-value (NaN; the table says why) rather than one that can never be small.

A diverged seed is a failure, never left out: its value is +∞, it loses to every finished
seed and ties with another diverged one (the test ranks it as the largest difference).
Each row counts the runs and diverged seeds of both methods. The test-case spread is its
own per-seed quantity (:func:`case_spread`: each seed's std over the cases, median over
seeds), never pooled into a test. Non-finite per-case values of finished runs are left out
of that seed's mean, pair by pair, and counted (``dropped``); ``pairs`` counts the (seed,
case) pairs that entered the means and ``a_lower`` the fraction of them where the first
method was lower (descriptive only).
"""

from __future__ import annotations

import csv
import io
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..engine import rundir
from ..engine.packed import kept_path, open_kept
from ..errors import ConfigError

# The first nine columns are the original layout of paired_tests.csv (readers index them
# by name); the counts after them say what was left out of the pairs and why, then the
# seed-level additions.
COLUMNS = (
    "metric", "method_a", "method_b", "pairs", "a_lower", "seeds", "seeds_a_lower", "ratio", "p_value",
    "runs_a", "runs_b", "diverged_a", "diverged_b", "dropped", "ties", "ratio_low", "ratio_high", "tested",
)  # fmt: skip

# The fewest seeds with a difference on which a two-sided signed-rank test is computed: with
# n seeds its smallest p-value is 2/2^n (exact test), 0.0625 at 5 seeds, 0.031 at 6.
MIN_SEEDS_P = 6

# Below this a p-value sits so far in the tail of scipy's normal approximation that its
# digits mean nothing (and soon underflow to 0): only the bound is printed.
P_FLOOR = 1e-300


def format_p(p: float) -> str:
    """A p-value for a table: two significant digits (``3.2e-05``, ``0.041``), ``<1e-300``
    for 0 and anything below (an underflow, not a zero probability), ``1.0`` only for an
    exact 1 (a value just below 1 keeps the digits that show it is below), ``n/a`` when
    there is no p-value (NaN: no pairs to test)."""
    p = float(p)
    if not math.isfinite(p):
        return "n/a"
    if p < P_FLOOR:
        return f"<{P_FLOOR:.0e}"
    if p == 1.0:
        return "1.0"
    for digits in range(2, 18):  # 17 significant digits tell any two doubles apart
        text = f"{p:.{digits}g}"
        if float(text) != 1.0:
            return text
    return repr(p)


def format_ratio(ratio: float) -> str:
    """A ratio: three significant digits, ``∞`` where a failure (or a loss of 0) makes it
    infinite, ``n/a`` where it is undefined."""
    if math.isnan(ratio):
        return "n/a"
    return "∞" if math.isinf(ratio) else f"{ratio:.3g}"


def _runs(out: Path) -> list[dict[str, Any]]:
    """The rows of ``summary.csv`` with each run's status: the ``status`` column, else the
    run's ``summary.json``; a run with neither (a hand-made summary) counts as finished,
    as every listed run did before statuses were read here."""
    summary = out / "summary.csv"
    if not summary.exists():
        return []
    with summary.open() as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        status = row.get("status") or ""
        if not status:
            path = out / row["run_dir"] / "summary.json"
            status = rundir.read_json(path, rundir.RUN_DAMAGED, empty={}).get("status", "")
        row["status"] = status or "finished"
    return rows


def case_values(out: str | Path, metric: str | None = None) -> tuple[str, dict[str, dict[int, np.ndarray]]]:
    """(metric, {method: {seed: per-case values}}) from a study's finished runs (diverged
    runs are left out: their values come from broken parameters); the metric defaults to
    ``rel_error`` where the runs have it, else ``loss``."""
    out = Path(out)
    values: dict[str, dict[int, np.ndarray]] = {}
    for row in _runs(out):
        path = out / row["run_dir"] / "test_cases.json"  # or its packed copy (prune.py --pack)
        if row["status"] != "finished" or not kept_path(path).exists():
            continue
        try:
            with open_kept(path) as f:
                cases = json.load(f)
        except (OSError, ValueError, EOFError) as e:
            raise ConfigError(f"{kept_path(path)} is damaged ({type(e).__name__}); {rundir.RUN_DAMAGED}") from None
        if metric is None:
            metric = "rel_error" if "rel_error" in cases else "loss"
        if metric in cases:
            values.setdefault(row["method"], {})[int(row["seed"])] = np.asarray(cases[metric], float)
    return metric or "loss", values


def signed_rank_p(differences: np.ndarray) -> tuple[float, int]:
    """(two-sided Wilcoxon signed-rank p-value, seeds tested) of per-seed differences; NaN
    where fewer than :data:`MIN_SEEDS_P` seeds differ (zero differences, ties, are left out,
    as the test does). A failure's infinite difference enters as a finite value beyond every
    other (the test uses only signs and ranks, which it keeps)."""
    from scipy.stats import wilcoxon

    d = np.asarray(differences, dtype=float)
    d = d[~np.isnan(d) & (d != 0)]
    if d.size < MIN_SEEDS_P:
        return math.nan, int(d.size)
    finite = np.abs(d[np.isfinite(d)])
    beyond = 2.0 * (float(finite.max()) if finite.size else 1.0) + 1.0
    d = np.where(np.isinf(d), np.sign(d) * beyond, d)
    return float(wilcoxon(d).pvalue), int(d.size)  # pyright: ignore[reportAttributeAccessIssue]  # scipy's decorator hides the result type


def _difference(a: float, b: float) -> float:
    """a − b with failures (+∞): two failures tie (0)."""
    return 0.0 if math.isinf(a) and math.isinf(b) else a - b


def paired_tests(out: str | Path, metric: str | None = None, order: list[str] | None = None) -> list[dict[str, Any]]:
    """Every pair of methods compared on their common seeds, paired by seed (see the module
    docstring); also written to ``OUT/paired_tests.csv``. A pair without a common seed keeps
    its row, with no seeds and NaN statistics, so the table can say why. Empty if fewer than
    two methods ran."""
    from .seeds import ratio_summary, seed_ratio

    out = Path(out)
    metric, values = case_values(out, metric)
    runs: dict[str, set[int]] = {}
    diverged: dict[str, set[int]] = {}
    for row in _runs(out):
        runs.setdefault(row["method"], set()).add(int(row["seed"]))
        if row["status"] == "diverged":
            diverged.setdefault(row["method"], set()).add(int(row["seed"]))
    present = set(values) | set(diverged)
    methods = [m for m in (order or sorted(present)) if m in present]
    rows = []
    for a, b in itertools.combinations(methods, 2):
        va, vb = values.get(a, {}), values.get(b, {})
        fa, fb = diverged.get(a, set()), diverged.get(b, set())
        xs, ys, lower, pairs, dropped = [], [], [], [], 0
        for s in sorted((set(va) | fa) & (set(vb) | fb)):
            if s in va and s in vb:
                if va[s].shape != vb[s].shape:
                    continue
                finite = np.isfinite(va[s]) & np.isfinite(vb[s])
                dropped += int(np.sum(~finite))
                if not finite.any():
                    continue
                x, y = float(np.mean(va[s][finite])), float(np.mean(vb[s][finite]))
                pairs.append((float(np.mean(va[s][finite] < vb[s][finite])), int(finite.sum())))
            else:  # one of them (or both) diverged on this seed: a failure, +∞
                x = math.inf if s in fa else _seed_mean(va.get(s))
                y = math.inf if s in fb else _seed_mean(vb.get(s))
                if math.isnan(x) or math.isnan(y):
                    continue
            xs.append(x)
            ys.append(y)
            lower.append(x < y)
        ratios = ratio_summary([seed_ratio(x, y) for x, y in zip(xs, ys)])
        p, tested = signed_rank_p(np.array([_difference(x, y) for x, y in zip(xs, ys)]))
        n_pairs = sum(n for _, n in pairs)
        rows.append({
            "metric": metric, "method_a": a, "method_b": b, "pairs": n_pairs,
            "a_lower": sum(f * n for f, n in pairs) / n_pairs if n_pairs else math.nan,
            "seeds": len(xs), "seeds_a_lower": int(np.sum(lower)), "ratio": ratios["median"], "p_value": p,
            "runs_a": len(runs.get(a, ())), "runs_b": len(runs.get(b, ())),
            "diverged_a": len(fa), "diverged_b": len(fb), "dropped": dropped,
            "ties": sum(x == y or (math.isinf(x) and math.isinf(y)) for x, y in zip(xs, ys)),
            "ratio_low": ratios["low"], "ratio_high": ratios["high"], "tested": tested,
        })  # fmt: skip
    text = io.StringIO()
    writer = csv.DictWriter(text, COLUMNS)
    writer.writeheader()
    writer.writerows(rows)
    rundir.atomic_write(out / "paired_tests.csv", text.getvalue())  # never half a table
    return rows


def _seed_mean(cases: np.ndarray | None) -> float:
    """A finished seed's mean over its finite test cases (NaN: none)."""
    if cases is None:
        return math.nan
    finite = cases[np.isfinite(cases)]
    return float(np.mean(finite)) if finite.size else math.nan


def case_spread(out: str | Path, metric: str | None = None) -> dict[str, float]:
    """{method: the median over seeds of each seed's standard deviation over its test cases}
    (the test-case spread as a per-seed quantity; a diverged seed's is +∞, a finished seed
    with fewer than two finite cases has none). Methods without ``test_cases.json`` are
    left out."""
    out = Path(out)
    metric, values = case_values(out, metric)
    spreads: dict[str, list[float]] = {}
    for method, seeds in values.items():
        for cases in seeds.values():
            finite = cases[np.isfinite(cases)]
            if finite.size > 1:
                spreads.setdefault(method, []).append(float(np.std(finite, ddof=1)))
    for row in _runs(out):
        if row["status"] == "diverged" and row["method"] in spreads:
            spreads[row["method"]].append(math.inf)
    return {m: float(np.median(v)) for m, v in spreads.items()}


def seed_means(out: str | Path, metric: str | None = None) -> dict[str, tuple[float, float, int]]:
    """{method: (mean, std, seeds)} of the per-seed mean over test cases, over the finished
    runs only (a per-case metric such as ``corr_time`` has no "worst" value to give a
    diverged run); a table that counts diverged seeds as failures uses
    :func:`physgrad.harness.seeds.summarize`."""
    metric, values = case_values(out, metric)
    result = {}
    for method, seeds in values.items():
        means = np.array([np.mean(v) for v in seeds.values()])
        result[method] = (float(means.mean()), float(means.std(ddof=1)) if means.size > 1 else 0.0, int(means.size))
    return result


def _diverged(row: dict[str, Any]) -> list[tuple[str, int, int]]:
    """(method, diverged seeds, runs) for each method of a pair that diverged somewhere;
    rows without the counts (an older ``paired_tests.csv``) read as none diverged."""
    out = []
    for k in ("a", "b"):
        n = int(row.get(f"diverged_{k}") or 0)
        if n:
            out.append((row[f"method_{k}"], n, int(row.get(f"runs_{k}") or 0)))
    return out


def diverged_note(row: dict[str, Any]) -> str:
    """Which methods of a pair diverged on how many seeds (``gn 1 of 3``), or ``-``."""
    return ", ".join(f"{m} {n} of {runs}" for m, n, runs in _diverged(row)) or "-"


def _missing_reason(row: dict[str, Any]) -> str:
    """Why a pair has no seed to compare: ``no finite values`` or ``no common seeds``."""
    return "no finite values" if int(row.get("dropped") or 0) else "no common seeds"


def p_cell(row: dict[str, Any]) -> str:
    """The Wilcoxon p-value over seeds, or why there is none: ``n/a: 2 seeds (min p 0.5)``
    (below :data:`MIN_SEEDS_P` seeds that differ, the exact test's smallest p-value 2/2^n)."""
    p = float(row["p_value"])
    if math.isfinite(p):
        return format_p(p)
    tested = row.get("tested")
    n = int(row["seeds"] if tested is None or tested == "" else tested)
    if n == 0:
        return "n/a: no seed differs"
    return f"n/a: {n} seed{'s' if n != 1 else ''} (min p {2 / 2**n:.2g})"


def ratio_cell(row: dict[str, Any]) -> str:
    """The median of the per-seed ratios and its 95 % interval (``[n/a: 2 seeds]`` below 3)."""
    from .seeds import MIN_SEEDS_INTERVAL

    ratio, seeds = format_ratio(float(row["ratio"])), int(row["seeds"])
    if seeds < MIN_SEEDS_INTERVAL or "ratio_low" not in row:
        return f"{ratio} [n/a: {seeds} seed{'s' if seeds != 1 else ''}]"
    return f"{ratio} [{format_ratio(float(row['ratio_low']))}, {format_ratio(float(row['ratio_high']))}]"


def format_tests(rows: list[dict[str, Any]], cell: str = "") -> list[list[str]]:
    """Table lines: header, then one line per pair, paired by seed: the methods' diverged
    seeds (``gn 1 of 3``: failures, counted as the worse value), the seeds compared, on how
    many the first was lower (and tied), the median per-seed ratio with its interval and the
    Wilcoxon p-value over seeds, or why there is none (:func:`p_cell`). A pair with no seed to compare shows
    ``n/a (no common seeds)`` instead of numbers; dropped non-finite test cases are counted."""
    head = (["cell"] if cell else []) + [
        "pair", "metric", "diverged", "seeds", "first lower", "ratio, median [95% CI]", "Wilcoxon p",
    ]  # fmt: skip
    lines = [head]
    for r in rows:
        seeds, dropped = int(r["seeds"]), int(r.get("dropped") or 0)
        count = f"{seeds}" + (f" ({dropped} non-finite cases dropped)" if dropped else "")
        if seeds == 0:
            missing = f"n/a ({_missing_reason(r)})"
            cells = [count, "n/a", missing, missing]
        else:
            ties = int(r.get("ties") or 0)
            lower = f"{r['seeds_a_lower']}/{seeds}" + (f" ({ties} tied)" if ties else "")
            cells = [count, lower, ratio_cell(r), p_cell(r)]
        lines.append(
            ([cell] if cell else []) + [f"{r['method_a']} vs {r['method_b']}", r["metric"], diverged_note(r)] + cells
        )
    return lines
