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

from ..study import as_float, mean_std
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
    """Per candidate method of one problem: status, counts, mean ± std of the final test
    loss over its finished seeds, rank and ratio to ``reference``.

    ``rows``: the study's ``summary.csv`` rows (``method``, ``status``, ``final_test_loss``);
    ``failures``: ``failures.json``. ``status`` is ``ok`` (a finished seed),
    ``diverged`` (every run diverged), ``failed`` (every run failed or the check crashed),
    ``not applicable``, ``skipped`` or ``pending`` (applicable, not run yet).
    The rank orders the methods with a mean by (fraction of runs diverged or failed, mean);
    equal keys share the lower rank. The ratio is mean / reference mean where both are
    finite and the reference's is positive."""
    failures = failures or {}
    table = []
    for v in verdicts:
        runs = [r for r in rows if r["method"] == v.method]
        finished = [r for r in runs if r["status"] == "finished"]
        diverged = sum(r["status"] == "diverged" for r in runs)
        failed = sum(f["method"] == v.method for f in failures.values()) + (v.status == "error")
        losses = [as_float(r["final_test_loss"]) for r in finished]
        n_finite = sum(map(math.isfinite, losses))
        mean, std = mean_std(losses)
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
            "finished": n_finite, "diverged": diverged, "failed": failed, "mean": mean, "std": std,
        })  # fmt: skip
    ranked = sorted(
        (t for t in table if math.isfinite(t["mean"])),
        key=lambda t: ((t["diverged"] + t["failed"]) / max(t["runs"], 1), t["mean"]),
    )
    rank, previous = 0, None
    for i, t in enumerate(ranked, 1):
        key = ((t["diverged"] + t["failed"]) / max(t["runs"], 1), t["mean"])
        rank = rank if key == previous else i
        t["rank"], previous = rank, key
    base = next((t["mean"] for t in table if t["method"] == reference), math.nan)
    for t in table:
        t.setdefault("rank", None)
        t["problem_has_reference"] = math.isfinite(base) and base > 0
        t["ratio"] = t["mean"] / base if math.isfinite(t["mean"]) and t["problem_has_reference"] else math.nan
    return table


def best_method(table: Sequence[dict[str, Any]]) -> str | None:
    """The rank-1 method (the first of a tie), or None if no method has a result."""
    return next((t["method"] for t in sorted(table, key=lambda t: t["rank"] or math.inf) if t["rank"] == 1), None)


def add_paired_tests(table: list[dict[str, Any]], tests: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each method's paired test against the best method (``stats.paired_tests`` rows):
    ``p_vs_best`` (two-sided Wilcoxon signed-rank p-value), ``pairs``, ``seeds_best_lower``
    (of ``seeds_compared``); NaN/None where there is nothing to pair."""
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
        ratios = np.clip([t["ratio"] for t in ran if math.isfinite(t["ratio"])], *RATIO_CLIP)
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
    "seeds_compared", "reason",
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
    return format(x, spec) if isinstance(x, (int, float)) and math.isfinite(x) else ""


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
    } for t in table]  # fmt: skip


def table_lines(
    table: Sequence[dict[str, Any]], reference: str = REFERENCE, inapplicable: bool = True
) -> list[list[str]]:
    """A problem's table as printable lines (header first): ranked methods first, then the
    diverged/failed/pending ones, then (with ``inapplicable``) the skipped methods and
    those that do not apply, with the reason."""
    from ..stats import format_p

    best = best_method(table)
    header = ["rank", "method", "runs", "final test loss (mean ± std)", f"/ {reference}",
              f"vs {best or 'best'}: Wilcoxon p (seeds lower)", "note"]  # fmt: skip
    order = {"ok": 0, "diverged": 1, "failed": 1, "pending": 2, "skipped": 3, "not applicable": 4}
    lines = [header]
    for t in sorted(table, key=lambda t: (order[t["status"]], t["rank"] or 0)):
        if not inapplicable and t["status"] in ("skipped", "not applicable"):
            continue
        notes = []
        if t["diverged"]:
            notes.append(f"{t['diverged']}/{t['runs']} diverged")
        if t["failed"]:
            notes.append(f"{t['failed']}/{t['runs']} failed")
        if t["reason"]:
            notes.append(t["reason"])
        if t["status"] == "ok":
            loss = f"{t['mean']:.3e} ± {t['std']:.1e}"
        else:
            loss = {"diverged": "all diverged", "failed": "failed", "pending": "not run yet"}.get(
                t["status"], str(t["status"])
            )
        if t["method"] == best:
            test = "best"
        elif t.get("pairs"):
            test = f"{format_p(t['p_vs_best'])} ({t['seeds_best_lower']}/{t['seeds_compared']})"
        else:
            test = ""
        ratio = _number(t["ratio"], ".3g")
        runs = str(t["runs"]) if t["status"] not in ("not applicable", "skipped") else ""
        lines.append([str(t["rank"] or ""), t["method"], runs, loss, ratio, test, "; ".join(notes)])
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
