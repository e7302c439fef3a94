"""Paired statistics between methods of a study: mean ± std over seeds and Wilcoxon tests.

Every finished run writes ``test_cases.json``: its final metrics on each test case. Two
methods trained from the same seeds are compared on the pairs (seed, test case), so the
test removes the variation between cases that both methods share (the reviewers of List et
al. asked for paired tests: shared/papers/unrolling.md §1.6). For each pair of methods:
the Wilcoxon signed-rank test (two-sided, scipy) of the per-pair differences, the number
of pairs, the fraction of pairs where the first method is lower, the fraction of seeds
whose mean over cases is lower, and the ratio of the means. Per method: the mean over test
cases per seed, then mean ± std over seeds.

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

COLUMNS = ("metric", "method_a", "method_b", "pairs", "a_lower", "seeds", "seeds_a_lower", "ratio", "p_value")


def case_values(out: str | Path, metric: str | None = None) -> tuple[str, dict[str, dict[int, np.ndarray]]]:
    """(metric, {method: {seed: per-case values}}) from a study's finished runs; the metric
    defaults to ``rel_error`` where the runs have it, else ``loss``."""
    out = Path(out)
    values: dict[str, dict[int, np.ndarray]] = {}
    summary = out / "summary.csv"
    if not summary.exists():
        return metric or "loss", values
    with summary.open() as f:
        rows = list(csv.DictReader(f))
    for row in rows:
        path = out / row["run_dir"] / "test_cases.json"
        if not path.exists():
            continue
        cases = json.loads(path.read_text())
        if metric is None:
            metric = "rel_error" if "rel_error" in cases else "loss"
        if metric in cases:
            values.setdefault(row["method"], {})[int(row["seed"])] = np.asarray(cases[metric], float)
    return metric or "loss", values


def paired_tests(out: str | Path, metric: str | None = None, order: list[str] | None = None) -> list[dict[str, Any]]:
    """Wilcoxon signed-rank tests between every pair of methods (see the module docstring);
    also written to ``OUT/paired_tests.csv``. Empty if fewer than two methods have cases."""
    from scipy.stats import wilcoxon

    metric, values = case_values(out, metric)
    methods = [m for m in (order or sorted(values)) if m in values]
    rows = []
    for a, b in itertools.combinations(methods, 2):
        seeds = sorted(set(values[a]) & set(values[b]))
        pairs = [(x, y) for s in seeds if values[a][s].shape == values[b][s].shape for x, y in zip(values[a][s], values[b][s])]
        if not pairs:
            continue
        x, y = np.array(pairs).T
        finite = np.isfinite(x) & np.isfinite(y)
        x, y = x[finite], y[finite]
        diff = x - y
        p = float(wilcoxon(x, y).pvalue) if len(x) > 0 and np.any(diff != 0) else 1.0
        seed_lower = [np.nanmean(values[a][s]) < np.nanmean(values[b][s]) for s in seeds]
        rows.append({
            "metric": metric, "method_a": a, "method_b": b, "pairs": len(x),
            "a_lower": float(np.mean(diff < 0)) if len(x) else math.nan,
            "seeds": len(seeds), "seeds_a_lower": int(np.sum(seed_lower)),
            "ratio": float(np.mean(x) / np.mean(y)) if len(x) and np.mean(y) != 0 else math.nan,
            "p_value": p,
        })  # fmt: skip
    with (Path(out) / "paired_tests.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    return rows


def seed_means(out: str | Path, metric: str | None = None) -> dict[str, tuple[float, float, int]]:
    """{method: (mean, std, seeds)} of the per-seed mean over test cases."""
    metric, values = case_values(out, metric)
    result = {}
    for method, seeds in values.items():
        means = np.array([np.mean(v) for v in seeds.values()])
        result[method] = (float(means.mean()), float(means.std(ddof=1)) if means.size > 1 else 0.0, int(means.size))
    return result


def format_tests(rows: list[dict[str, Any]], cell: str = "") -> list[list[str]]:
    """Table lines: header, then one line per pair."""
    head = (["cell"] if cell else []) + ["pair", "metric", "pairs", "first lower", "seeds lower", "mean ratio", "Wilcoxon p"]
    lines = [head]
    for r in rows:
        lines.append(([cell] if cell else []) + [
            f"{r['method_a']} vs {r['method_b']}", r["metric"], str(r["pairs"]), f"{100 * r['a_lower']:.0f}%",
            f"{r['seeds_a_lower']}/{r['seeds']}", f"{r['ratio']:.3g}", f"{r['p_value']:.2g}",
        ])  # fmt: skip
    return lines
