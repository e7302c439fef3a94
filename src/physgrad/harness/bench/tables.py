"""A bench's tables: pure functions of a problem's summary rows and failure log.

Per problem, :func:`method_rows` gives every candidate method its status, mean ± std of
the final test loss over its finished seeds, rank and ratio to :data:`REFERENCE`;
:func:`add_paired_tests` adds the paired test against the problem's best method. Across
problems, :func:`leaderboard` scores every method by the geometric mean of its ratios.
``*_records`` turn them into CSV rows, ``*_lines`` into printable lines (header first).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from ..seeds import as_float, number, ratio_summary, seed_ratios, summarize
from .applicability import Verdict

REFERENCE = "adam"  # the ratio column and the heat map are relative to this method

# Ratios enter logarithms (heat map, geometric mean) clipped to this range: a method that
# reaches a loss of exactly 0 (toy2d's Newton and SIP) has ratio 0, whose log would make
# every mean it enters -inf, and one blow-up should not outweigh many problems either.
RATIO_CLIP = (1e-6, 1e6)


def method_rows(
    rows: Sequence[dict[str, Any]],
    verdicts: Sequence[Verdict],
    failures: dict[str, dict[str, Any]] | None = None,
    reference: str = REFERENCE,
) -> list[dict[str, Any]]:
    """Per candidate method of one problem: status, counts, the final test loss over its
    seeds (a diverged or failed seed counting as +∞: ``median`` with its bootstrap interval
    ``low``/``high``, ``mean`` ± ``std``, +∞ once a seed failed; :mod:`physgrad.harness.seeds`),
    rank and ratio to ``reference``.

    ``rows``: the study's ``summary.csv`` rows (``method``, ``seed``, ``status``,
    ``final_test_loss``); ``failures``: ``failures.json``. ``status`` is ``ok`` (a finished
    seed), ``diverged`` (every run diverged), ``failed`` (every run failed or the check
    crashed), ``not applicable``, ``skipped`` or ``pending`` (applicable, not run yet).
    The rank orders the ``ok`` methods by (fraction of runs diverged or failed, median);
    equal keys share the lower rank. The ratio pairs the method with ``reference`` by seed:
    the median of the per-seed ratios (a failure against a value: +∞), or the ratio of the
    medians where the rows carry no seed."""
    failures = failures or {}
    table = []
    for v in verdicts:
        runs = [r for r in rows if r["method"] == v.method]
        finished = [r for r in runs if r["status"] == "finished"]
        diverged = sum(r["status"] == "diverged" for r in runs)
        failed_runs = [f for f in failures.values() if f["method"] == v.method]
        failed = len(failed_runs) + (v.status == "error")
        n_finite = sum(math.isfinite(as_float(r["final_test_loss"])) for r in finished)
        seeds = {str(r.get("seed", i)): math.inf if r["status"] == "diverged" else as_float(r["final_test_loss"])
                 for i, r in enumerate(runs)}  # fmt: skip
        seeds.update({f"failed{f.get('seed', i)}": math.inf for i, f in enumerate(failed_runs)})
        summary = summarize(list(seeds.values()))
        if v.status != "applicable" and v.status != "error":
            status = v.status
        elif n_finite:
            status = "ok"
        elif diverged:
            status = "diverged"
        elif failed:
            status = "failed"
        else:
            status = "pending"
        table.append({
            "method": v.method, "status": status, "reason": v.reason, "runs": len(runs) + failed,
            "finished": n_finite, "diverged": diverged, "failed": failed, "seeds": seeds,
            "mean": summary["mean"] if status == "ok" else math.nan, "std": summary["std"] if status == "ok" else math.nan,
            "median": summary["median"] if status == "ok" else math.nan, "low": summary["low"], "high": summary["high"],
            "n": summary["n"],
        })  # fmt: skip

    def key(t):
        return ((t["diverged"] + t["failed"]) / max(t["runs"], 1), t["median"])

    ranked = sorted((t for t in table if t["status"] == "ok"), key=key)
    rank, previous = 0, None
    for i, t in enumerate(ranked, 1):
        rank = rank if key(t) == previous else i
        t["rank"], previous = rank, key(t)
    ref = next((t for t in table if t["method"] == reference), None)
    base = ref["median"] if ref is not None else math.nan
    paired = all("seed" in r for r in rows)
    for t in table:
        t.setdefault("rank", None)
        t["problem_has_reference"] = math.isfinite(base) and base > 0
        if not (t["status"] == "ok" and t["problem_has_reference"] and ref is not None):
            t["ratio"] = math.nan
        elif paired:
            ratios = seed_ratios({k: x for k, x in t["seeds"].items() if not k.startswith("failed")},
                                 {k: x for k, x in ref["seeds"].items() if not k.startswith("failed")})  # fmt: skip
            t["ratio"] = ratio_summary(ratios)["median"]
        else:
            t["ratio"] = t["median"] / base
    return table


def best_method(table: Sequence[dict[str, Any]]) -> str | None:
    """The rank-1 method (the first of a tie), or None if no method has a result."""
    return next((t["method"] for t in sorted(table, key=lambda t: t["rank"] or math.inf) if t["rank"] == 1), None)


def add_paired_tests(table: list[dict[str, Any]], tests: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each method's paired comparison with the best method, by seed (``stats.paired_tests``
    rows): ``p_vs_best`` (two-sided Wilcoxon signed-rank p-value over seeds; NaN below 6
    seeds), ``pairs`` (test-case pairs in the seeds' means), ``seeds_best_lower`` (of
    ``seeds_compared``); NaN/None where there is nothing to pair."""
    best = best_method(table)
    for t in table:
        row = next((r for r in tests if best and {r["method_a"], r["method_b"]} == {best, t["method"]}), None)
        t["best"] = best
        if row is None or t["method"] == best:
            t.update(p_vs_best=math.nan, pairs=0, seeds_best_lower=None, seeds_compared=None)
            continue
        best_first = row["method_a"] == best
        seeds, lower = int(row["seeds"]), int(row["seeds_a_lower"])
        t.update(p_vs_best=as_float(row["p_value"]), pairs=int(row["pairs"]), seeds_compared=seeds,
                 seeds_best_lower=lower if best_first else seeds - lower)  # fmt: skip
    return table


def leaderboard(tables: dict[str, Sequence[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per method over the problems (``{problem: method_rows(...)}``): the geometric mean of
    its ratios to the reference (over the problems where the ratio is defined; each ratio
    clipped to :data:`RATIO_CLIP`), the number
    of problems that ratio covers, wins (rank 1, ties included), diverged and failed runs,
    and the problems it ran on (applicable, not skipped).

    Sorted by ``score``: the same geometric mean, but over every problem it ran on where
    the reference has a result, a problem where every run of the method diverged or failed
    counting as the worst ratio, ``RATIO_CLIP[1]`` (otherwise a method that diverges on most
    problems would lead on the one or two where it converged); then by wins."""
    methods = list(dict.fromkeys(t["method"] for table in tables.values() for t in table))
    board = []
    for method in methods:
        cells = [t for table in tables.values() for t in table if t["method"] == method]
        ran = [t for t in cells if t["status"] not in ("not applicable", "skipped")]
        if not ran:
            continue
        ratios = np.clip([t["ratio"] for t in ran if not math.isnan(t["ratio"])], *RATIO_CLIP)  # ∞: a failure
        lost = sum(t["status"] in ("diverged", "failed") for t in ran if t["problem_has_reference"])
        scored = np.concatenate([ratios, np.full(lost, RATIO_CLIP[1])])
        board.append({
            "method": method,
            "score": float(10 ** np.mean(np.log10(scored))) if scored.size else math.nan,
            "geomean_ratio": float(10 ** np.mean(np.log10(ratios))) if ratios.size else math.nan,
            "ratio_problems": int(ratios.size),
            "wins": sum(t["rank"] == 1 for t in ran),
            "divergences": sum(t["diverged"] for t in ran),
            "failures": sum(t["failed"] for t in ran),
            "problems": len(ran),
            "runs": sum(t["runs"] for t in ran),
        })  # fmt: skip

    def key(b):
        finite = math.isfinite(b["score"])
        return (not finite, b["score"] if finite else 0, -b["wins"])

    board.sort(key=key)
    return board


# --- formatting ------------------------------------------------------------------------------

TABLE_COLUMNS = (
    "problem", "method", "status", "runs", "finished", "diverged", "failed", "final_test_loss_mean",
    "final_test_loss_std", "rank", "ratio_to_adam", "best", "p_vs_best", "pairs", "seeds_best_lower",
    "seeds_compared", "reason", "final_test_loss_median", "final_test_loss_low", "final_test_loss_high",
    "target", "time_to_target_median", "time_to_target_low", "time_to_target_high", "target_reached",
)  # fmt: skip
BOARD_COLUMNS = (
    "method",
    "score",
    "geomean_ratio_to_adam",
    "ratio_problems",
    "wins",
    "divergences",
    "failures",
    "runs",
    "problems",
)


def _number(x: float, spec: str = ".3e") -> str:
    """A CSV cell: empty for NaN or a non-number, ``inf`` for a failure's +∞."""
    if not isinstance(x, (int, float)) or math.isnan(x):
        return ""
    return "inf" if math.isinf(x) else format(x, spec)


def table_records(problem: str, table: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """``method_rows`` (with paired tests) as ``bench_table.csv`` rows."""
    return [{
        "problem": problem, "method": t["method"], "status": t["status"], "runs": t["runs"],
        "finished": t["finished"], "diverged": t["diverged"], "failed": t["failed"],
        "final_test_loss_mean": _number(t["mean"], ".6e"), "final_test_loss_std": _number(t["std"], ".6e"),
        "rank": t["rank"] or "", "ratio_to_adam": _number(t["ratio"], ".6g"), "best": t.get("best") or "",
        "p_vs_best": _number(t.get("p_vs_best", math.nan), ".3g"), "pairs": t.get("pairs") or "",
        "seeds_best_lower": "" if t.get("seeds_best_lower") is None else t["seeds_best_lower"],
        "seeds_compared": t.get("seeds_compared") or "", "reason": t["reason"],
        "final_test_loss_median": _number(t["median"], ".6e"), "final_test_loss_low": _number(t["low"], ".6e"),
        "final_test_loss_high": _number(t["high"], ".6e"), "target": _number(t.get("target", math.nan), ".6g"),
        "time_to_target_median": _number(t["ttt"], ".6g") if t.get("ttt_reached") else "",
        "time_to_target_low": _number(t.get("ttt_low", math.nan), ".6g") if t.get("ttt_reached") else "",
        "time_to_target_high": _number(t.get("ttt_high", math.nan), ".6g") if t.get("ttt_reached") else "",
        "target_reached": t.get("ttt_reached", ""),
    } for t in table]  # fmt: skip


def table_lines(
    table: Sequence[dict[str, Any]], reference: str = REFERENCE, inapplicable: bool = True
) -> list[list[str]]:
    """A problem's table as printable lines (header first): ranked methods first, then the
    diverged/failed/pending ones, then (with ``inapplicable``) the skipped methods and
    those that do not apply, with the reason."""
    from ..seeds import median_cell
    from ..stats import format_p

    best = best_method(table)
    header = ["rank", "method", "runs", "final test loss: median [95% CI] over seeds", f"/ {reference}",
              f"vs {best or 'best'}: Wilcoxon p over seeds, from 6 (seeds lower)", "note",
              "time to target: median over seeds"]  # fmt: skip
    order = {"ok": 0, "diverged": 1, "failed": 1, "pending": 2, "skipped": 3, "not applicable": 4}
    lines = [header]
    for t in sorted(table, key=lambda t: (order[t["status"]], t["rank"] or 0)):
        if not inapplicable and t["status"] in ("skipped", "not applicable"):
            continue
        notes = []
        if t["diverged"]:
            notes.append(f"{t['diverged']} of {t['runs']} diverged")
        if t["failed"]:
            notes.append(f"{t['failed']} of {t['runs']} failed")
        if t["reason"]:
            notes.append(t["reason"])
        if t["status"] == "ok":
            loss = median_cell(t)
        else:
            loss = {"diverged": "all diverged", "failed": "failed", "pending": "not run yet"}.get(
                t["status"], str(t["status"])
            )
        if t["method"] == best:
            test = "best"
        elif t.get("seeds_compared"):
            p = t["p_vs_best"]
            test = (f"{format_p(p)}" if math.isfinite(p) else f"n/a: {t['seeds_compared']} seeds") + (
                f" ({t['seeds_best_lower']}/{t['seeds_compared']})")  # fmt: skip
        else:
            test = ""
        ratio = number(t["ratio"], ".3g") if t["status"] == "ok" else ""
        runs = str(t["runs"]) if t["status"] not in ("not applicable", "skipped") else ""
        lines.append(
            [str(t["rank"] or ""), t["method"], runs, loss, ratio, test, "; ".join(notes), t.get("ttt_cell", "")]
        )
    return lines


def board_records(board: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{**{k: b[k] for k in BOARD_COLUMNS if k in b}, "score": _number(b["score"], ".6g"),
             "geomean_ratio_to_adam": _number(b["geomean_ratio"], ".6g")}
            for b in board]  # fmt: skip


def board_lines(board: Sequence[dict[str, Any]], reference: str = REFERENCE) -> list[list[str]]:
    header = ["method", f"score (all diverged = {RATIO_CLIP[1]:g})", f"geo-mean ratio to {reference}", "problems (ratio)",
              "wins", "diverged runs", "failed runs", "problems run"]  # fmt: skip
    lines = [header]
    for b in board:
        runs = b.get("runs") or 0
        lines.append([b["method"], _number(b["score"], ".3g") or "-", _number(b["geomean_ratio"], ".3g") or "-", str(b["ratio_problems"]), str(b["wins"]),
                      f"{b['divergences']}/{runs}", f"{b['failures']}/{runs}", str(b["problems"])])  # fmt: skip
    return lines
