"""Paired statistics between methods of a study: mean ± std over seeds and Wilcoxon tests.

Every run writes ``test_cases.json``: its final metrics on each test case. Two methods
trained from the same seeds are compared on the pairs (seed, test case), so the test removes
the variation between cases that both methods share (the reviewers of List et al. asked for
paired tests). For each pair of methods: the Wilcoxon signed-rank test (two-sided, scipy) of
the per-pair differences, the number of pairs, the fraction of pairs where the first method
is lower, the fraction of seeds whose mean over cases is lower, and the ratio of the means.
Per method: the mean over test cases per seed, then mean ± std over seeds.

Only FINISHED runs enter the statistics. A diverged run also writes ``test_cases.json``
(from its last finite parameters), and its values can be astronomically large: one such
seed once turned a comparison into "mean ratio 2.26e-29, p 0". So a seed is paired only
where both methods finished; each row counts the diverged seeds of both methods, and a
pair with no seed left says so instead of showing numbers. Non-finite per-case values of
finished runs are dropped pair by pair and counted.

Read the p-value as conditional on the trained networks: the cases of one seed share one
network, so (seed, case) pairs are not independent draws of the training method. With few
seeds the seed-level count ("seeds lower") is the statement about the method itself; a
signed-rank test on per-seed means needs ≥ 6 seeds to reach p < 0.05 (two-sided).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

# The first nine columns are the original layout of paired_tests.csv (readers index them
# by name); the counts after them say what was left out of the pairs and why.
COLUMNS = (
    "metric", "method_a", "method_b", "pairs", "a_lower", "seeds", "seeds_a_lower", "ratio", "p_value",
    "runs_a", "runs_b", "diverged_a", "diverged_b", "dropped",
)  # fmt: skip

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
    """A ratio of means: three significant digits, ``n/a`` where it is undefined."""
    return f"{ratio:.3g}" if math.isfinite(ratio) else "n/a"


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
            status = json.loads(path.read_text()).get("status", "") if path.exists() else ""
        row["status"] = status or "finished"
    return rows


def case_values(out: str | Path, metric: str | None = None) -> tuple[str, dict[str, dict[int, np.ndarray]]]:
    """(metric, {method: {seed: per-case values}}) from a study's finished runs (diverged
    runs are left out: their values come from broken parameters); the metric defaults to
    ``rel_error`` where the runs have it, else ``loss``."""
    out = Path(out)
    values: dict[str, dict[int, np.ndarray]] = {}
    for row in _runs(out):
        path = out / row["run_dir"] / "test_cases.json"
        if row["status"] != "finished" or not path.exists():
            continue
        cases = json.loads(path.read_text())
        if metric is None:
            metric = "rel_error" if "rel_error" in cases else "loss"
        if metric in cases:
            values.setdefault(row["method"], {})[int(row["seed"])] = np.asarray(cases[metric], float)
    return metric or "loss", values


def _ratio(x: np.ndarray, y: np.ndarray) -> float:
    """mean(x) / mean(y), or NaN where either mean is 0 or non-finite: such a mean comes
    from a broken run or a degenerate metric, and its ratio would mislead."""
    if len(x) == 0:
        return math.nan
    mx, my = float(np.mean(x)), float(np.mean(y))
    if not (math.isfinite(mx) and math.isfinite(my)) or mx == 0 or my == 0:
        return math.nan
    ratio = mx / my
    return ratio if math.isfinite(ratio) and ratio != 0 else math.nan


def paired_tests(out: str | Path, metric: str | None = None, order: list[str] | None = None) -> list[dict[str, Any]]:
    """Wilcoxon signed-rank tests between every pair of methods on the seeds where both
    finished (see the module docstring); also written to ``OUT/paired_tests.csv``. A pair
    whose seeds all diverged in one method or the other keeps its row, with no pairs and
    NaN statistics, so the table can say why. Empty if fewer than two methods ran."""
    from scipy.stats import wilcoxon

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
        xs, ys, seed_lower, dropped = [], [], [], 0
        for s in sorted(set(va) & set(vb)):
            if va[s].shape != vb[s].shape:
                continue
            finite = np.isfinite(va[s]) & np.isfinite(vb[s])
            dropped += int(np.sum(~finite))
            if not finite.any():
                continue
            x, y = va[s][finite], vb[s][finite]
            xs.append(x)
            ys.append(y)
            seed_lower.append(bool(np.mean(x) < np.mean(y)))
        x = np.concatenate(xs) if xs else np.zeros(0)
        y = np.concatenate(ys) if ys else np.zeros(0)
        diff = x - y
        if len(x) == 0:
            p = math.nan
        elif np.any(diff != 0):
            p = float(wilcoxon(x, y).pvalue)  # pyright: ignore[reportAttributeAccessIssue]  # scipy's decorator hides the result type
        else:
            p = 1.0  # identical values on every pair: no evidence of a difference
        rows.append({
            "metric": metric, "method_a": a, "method_b": b, "pairs": len(x),
            "a_lower": float(np.mean(diff < 0)) if len(x) else math.nan,
            "seeds": len(seed_lower), "seeds_a_lower": int(np.sum(seed_lower)),
            "ratio": _ratio(x, y), "p_value": p,
            "runs_a": len(runs.get(a, ())), "runs_b": len(runs.get(b, ())),
            "diverged_a": len(diverged.get(a, ())), "diverged_b": len(diverged.get(b, ())),
            "dropped": dropped,
        })  # fmt: skip
    with (out / "paired_tests.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    return rows


def seed_means(out: str | Path, metric: str | None = None) -> dict[str, tuple[float, float, int]]:
    """{method: (mean, std, seeds)} of the per-seed mean over test cases (finished runs)."""
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
    """Which methods of a pair diverged on how many seeds (``gn 1/3``), or ``-``."""
    return ", ".join(f"{m} {n}/{runs}" for m, n, runs in _diverged(row)) or "-"


def _missing_reason(row: dict[str, Any]) -> str:
    """Why a pair has no (seed, case) pairs left: ``gn diverged 2/2``, ``no finite values``
    or ``no common seeds``."""
    if _diverged(row):
        return ", ".join(f"{m} diverged {n}/{runs}" for m, n, runs in _diverged(row))
    return "no finite values" if int(row.get("dropped") or 0) else "no common seeds"


def format_tests(rows: list[dict[str, Any]], cell: str = "") -> list[list[str]]:
    """Table lines: header, then one line per pair. A pair with diverged seeds names them
    (``gn 1/3``: its statistics use the other seeds); a pair with nothing left to compare
    shows ``n/a (gn diverged 2/2)`` instead of numbers; dropped non-finite pairs are
    counted beside the number of pairs."""
    head = (["cell"] if cell else []) + [
        "pair", "metric", "diverged", "pairs", "first lower", "seeds lower", "mean ratio", "Wilcoxon p",
    ]  # fmt: skip
    lines = [head]
    for r in rows:
        pairs, dropped = int(r["pairs"]), int(r.get("dropped") or 0)
        count = f"{pairs}" + (f" ({dropped} non-finite dropped)" if dropped else "")
        if pairs == 0:
            missing = f"n/a ({_missing_reason(r)})"
            cells = [count, "n/a", "n/a", missing, missing]
        else:
            cells = [count, f"{100 * float(r['a_lower']):.0f}%", f"{r['seeds_a_lower']}/{r['seeds']}",
                     format_ratio(float(r["ratio"])), format_p(float(r["p_value"]))]  # fmt: skip
        lines.append(
            ([cell] if cell else []) + [f"{r['method_a']} vs {r['method_b']}", r["metric"], diverged_note(r)] + cells
        )
    return lines
