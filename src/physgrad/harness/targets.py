"""Time-to-target (issue 31, item 4): how long each method takes to bring the test loss down
to the problem's target, per seed, and the performance profile across problems.

**The rule.** A run reaches the target at its *first evaluation* whose test loss is at or
below the target (no interpolation between evaluations: the time is that evaluation's, so
it is resolved to the evaluation cadence and never earlier than the run got there). Its
time is the calibrated time of that evaluation's step (:mod:`physgrad.harness.calibration`)
in a calibrated study, else its training wall-clock; its steps are that step. A run that
never gets there within its budget is **censored** (``>budget``: its time is +∞ for the
statistics, shown as more than its budget), and a run that **diverged** counts as never
reaching it (+∞), even where a loss before the divergence was below the target, as a
diverged seed is +∞ in every other table. Over seeds: the median with a bootstrap interval
(:func:`physgrad.harness.seeds.summarize`), +∞ seeds included, never dropped; so the median
is +∞ once half the seeds did not get there.

**The performance profile** (Dolan & Moré, Math. Program. 91, 2002): per problem p and
method m, the median time-to-target t(p, m) (+∞: not reached, not applicable or not run);
the ratio r(p, m) = t(p, m) / min over methods of t(p, ·); and per method
ρ_m(τ) = (number of problems with r(p, m) ≤ τ) / (number of problems), drawn against τ on
a log axis. ρ_m(1) is the fraction of problems where m was fastest, ρ_m(τ → ∞) the fraction
it solved at all. Every problem of the bench counts in the denominator (a problem no method
solved counts as solved by none). The second view, the **geometric-mean score**, is the
geometric mean over the problems a method ran on (and some method solved) of r(p, m), where
an unsolved problem counts as twice the problem's time budget over the fastest time (the
PAR-2 penalty of solver competitions): 1 is "fastest everywhere".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..engine import rundir
from .papers import Target, protocol
from .seeds import MIN_SEEDS_INTERVAL, as_float, interval, number, summarize

PENALTY = 2.0  # an unsolved problem counts as this many times the problem's budget (PAR-2)
TTT_COLUMNS = ("problem", "method", "seed", "target", "status", "steps_to_target", "time_to_target",
               "wall_to_target", "budget_time", "axis")  # fmt: skip


def target_of(problem: str) -> Target | None:
    """The problem's declared target (:data:`physgrad.harness.papers.PROTOCOLS`), or None."""
    return protocol(problem).target


def first_reach(points: Sequence[tuple[float, float, float, float]], target: float):
    """``(step, time, wall)`` of the first evaluation (in step order) whose value is at or
    below ``target``, or None if none is. ``points``: (step, time, wall_time, value)."""
    for step, t, wall, value in sorted(points, key=lambda p: p[0]):
        if math.isfinite(value) and value <= target:
            return step, t, wall
    return None


def run_times(
    summary_rows: Sequence[Mapping[str, Any]], results: Sequence[Mapping[str, Any]], target: float, metric: str = "loss"
) -> list[dict[str, Any]]:
    """Per run of a study: its time-to-target row (:data:`TTT_COLUMNS`). ``status`` is
    ``reached``, ``censored`` (never reached within the budget: time +∞, ``budget_time`` the
    time it ran) or ``diverged`` (+∞). ``summary_rows``/``results``: the study's
    ``summary.csv`` and ``results.csv`` rows (the calibrated time where they carry it)."""
    curves: dict[tuple[str, str], list[tuple[float, float, float, float]]] = {}
    calibrated = any(r.get("calibrated_time") not in (None, "") for r in results)
    for r in results:
        if r["split"] != "test" or r["metric"] != metric:
            continue
        wall = as_float(r["wall_time"])
        t = as_float(r.get("calibrated_time")) if calibrated else wall
        key = (str(r["method"]), str(r["seed"]))
        curves.setdefault(key, []).append(
            (as_float(r["step"]), t if math.isfinite(t) else wall, wall, as_float(r["value"]))
        )
    out = []
    for row in summary_rows:
        key = (str(row["method"]), str(row["seed"]))
        points = curves.get(key, [])
        budget = as_float(row.get("calibrated_seconds")) if calibrated else as_float(row.get("train_seconds"))
        if not math.isfinite(budget):
            budget = as_float(row.get("train_seconds"))
        base = {"problem": row.get("problem", ""), "method": key[0], "seed": key[1], "target": target,
                "budget_time": budget, "axis": "calibrated" if calibrated else "wall-clock"}  # fmt: skip
        hit = first_reach(points, target)
        if row["status"] == "diverged":
            out.append({**base, "budget_time": math.nan, "status": "diverged", "steps_to_target": math.inf, "time_to_target": math.inf,
                        "wall_to_target": math.inf})  # fmt: skip
        elif hit is None:
            capped = str(row.get("wall_capped")).lower() == "true"  # stopped by --wall-cap before its budget
            out.append({**base, "status": "capped" if capped else "censored", "steps_to_target": math.inf, "time_to_target": math.inf,
                        "wall_to_target": math.inf})  # fmt: skip
        else:
            step, t, wall = hit
            out.append({**base, "status": "reached", "steps_to_target": step, "time_to_target": t,
                        "wall_to_target": wall})  # fmt: skip
    return out


def method_times(runs: Sequence[Mapping[str, Any]], order: Sequence[str]) -> list[dict[str, Any]]:
    """Per method: seeds, how many reached the target, and the median (with its bootstrap
    interval) over seeds of the time and the steps to it, +∞ seeds included."""
    table = []
    for method in order:
        mine = [r for r in runs if r["method"] == method]
        if not mine:
            continue
        time = summarize([r["time_to_target"] for r in mine])
        steps = summarize([r["steps_to_target"] for r in mine])
        table.append({"method": method, "seeds": len(mine), "reached": sum(r["status"] == "reached" for r in mine),
                      "diverged": sum(r["status"] == "diverged" for r in mine), "time": time, "steps": steps,
                      "budget_time": max((as_float(r["budget_time"]) for r in mine
                                          if math.isfinite(as_float(r["budget_time"]))), default=math.nan),
                      "per_seed": {r["seed"]: r for r in mine}})  # fmt: skip
    return table


def seed_cell(run: Mapping[str, Any]) -> str:
    """One seed's time-to-target: ``12.3 s``, ``>60 s`` (censored at its budget), ``>20 s
    (wall cap)`` (stopped by the wall-clock cap first) or ``diverged``."""
    if run["status"] == "diverged":
        return "diverged"
    if run["status"] == "capped":
        return f">{as_float(run['budget_time']):.3g} s (wall cap)"
    if run["status"] == "censored":
        return f">{as_float(run['budget_time']):.3g} s"
    return f"{run['time_to_target']:.3g} s"


def median_time_cell(t: Mapping[str, Any]) -> str:
    """The median over seeds: a time (with its 95 % bootstrap interval from 3 seeds on), or
    ``>budget`` where it is +∞ (half the seeds or more never got there: more than the
    budget, or ``never`` where every seed diverged), with how many seeds reached it and how
    many diverged."""
    median, budget = t["time"]["median"], t["budget_time"]
    if math.isinf(median):
        text = f">{budget:.3g} s (>budget)" if math.isfinite(budget) else "never"
    elif t["time"]["n"] >= MIN_SEEDS_INTERVAL:  # with its bootstrap interval (∞ where censored seeds reach it)
        text = f"{median:.3g} s {interval(t['time'], '.3g')}"
    else:
        text = f"{median:.3g} s"
    diverged = f", {t['diverged']} diverged" if t["diverged"] else ""
    return f"{text} ({t['reached']}/{t['seeds']} reached{diverged})"


def table_lines(target: Target, table: Sequence[Mapping[str, Any]], axis: str) -> list[list[str]]:
    """Printable lines (header first) of a study's time-to-target table."""
    seeds = sorted({s for t in table for s in t["per_seed"]}, key=lambda s: (len(s), s))
    head = ["method", f"{axis} time to test loss ≤ {target.loss:g}: median over seeds", "steps: median",
            *[f"seed {s}" for s in seeds]]  # fmt: skip
    lines = [head]
    for t in table:
        steps = t["steps"]["median"]
        lines.append([t["method"], median_time_cell(t), ">budget" if math.isinf(steps) else f"{steps:.0f}",
                      *[seed_cell(t["per_seed"][s]) if s in t["per_seed"] else "" for s in seeds]])  # fmt: skip
    return lines


def study_times(
    out: str | Path, problem: str | None = None
) -> tuple[Target | None, list[dict[str, Any]], list[dict[str, Any]]]:
    """(target, per-run rows, per-method table) of a study directory from its
    ``summary.csv`` and ``results.csv``; writes ``time_to_target.csv``. No target: (None, [], [])."""

    from .study import method_order, read_csv, write_csv

    out = Path(out)
    study = rundir.read_json(out / "study.json", rundir.NOT_A_STUDY, empty={})
    if not (out / "summary.csv").exists():
        return None, [], []
    rows = read_csv(out / "summary.csv")
    problem = problem or study.get("problem") or (rows[0]["problem"] if rows else "")
    target = target_of(str(problem))
    if target is None or not rows:
        return target, [], []
    runs = run_times(rows, read_csv(out / "results.csv"), target.loss)
    write_csv(out / "time_to_target.csv", TTT_COLUMNS,
              [{**r, **{k: _cell(r[k]) for k in ("steps_to_target", "time_to_target", "wall_to_target", "budget_time")}}
               for r in runs])  # fmt: skip
    return target, runs, method_times(runs, method_order(rows, study))


def _cell(x: Any) -> str:
    x = as_float(x)
    return "" if math.isnan(x) else "inf" if math.isinf(x) else f"{x:.6g}"


# --- across problems: the performance profile --------------------------------------------------


def ratios(times: Mapping[str, Mapping[str, float]], methods: Sequence[str]) -> dict[str, dict[str, float]]:
    """``{problem: {method: t(p, m) / min t(p, ·)}}`` from ``{problem: {method: median time}}``
    (a method missing from a problem: +∞; a problem no method solved: every ratio +∞)."""
    out = {}
    for problem, row in times.items():
        best = min((row.get(m, math.inf) for m in methods), default=math.inf)
        out[problem] = {m: (row.get(m, math.inf) / best if math.isfinite(best) and best > 0 else
                            (1.0 if best == 0 and row.get(m, math.inf) == 0 else math.inf))
                        for m in methods}  # fmt: skip
    return out


def profile(
    times: Mapping[str, Mapping[str, float]], methods: Sequence[str], taus: Sequence[float]
) -> dict[str, list[float]]:
    """Dolan–Moré: per method, ρ(τ) for each τ of ``taus`` (the fraction of all problems
    with ratio ≤ τ)."""
    r = ratios(times, methods)
    n = len(r)
    return {m: [sum(r[p][m] <= tau for p in r) / n if n else math.nan for tau in taus] for m in methods}


def default_taus(times: Mapping[str, Mapping[str, float]], methods: Sequence[str]) -> list[float]:
    """τ from 1 to past the largest finite ratio (twice it, and at least 10), log-spaced,
    with every ratio itself (so the steps of the profile are exact)."""
    r = ratios(times, methods)
    finite = sorted({x for row in r.values() for x in row.values() if math.isfinite(x)})
    top = max(max(finite, default=1.0) * 2, 10.0)  # at least a decade
    return sorted({1.0, *finite, *np.geomspace(1.0, top, 64).tolist()})


def scores(
    times: Mapping[str, Mapping[str, float]],
    methods: Sequence[str],
    budgets: Mapping[str, float],
    ran: Mapping[str, set[str]],
) -> dict[str, dict[str, Any]]:
    """Per method: the profile's summary numbers and the geometric-mean score.
    ``budgets``: each problem's time budget (the censoring time); ``ran``: each method's
    problems (applicable and run). ``fastest``: ρ(1); ``solved``: ρ(∞) as a fraction of all
    problems; ``score``: the geometric mean of r(p, m) over the problems it ran where some
    method reached the target, an unsolved one counting as ``PENALTY`` × budget / fastest."""
    r = ratios(times, methods)
    n = len(r)
    out = {}
    for m in methods:
        logs = []
        for p, row in r.items():
            best = min((times[p].get(x, math.inf) for x in methods), default=math.inf)
            if p not in ran.get(m, set()) or not math.isfinite(best) or best <= 0:
                continue
            ratio = row[m] if math.isfinite(row[m]) else max(PENALTY * budgets.get(p, math.nan) / best, 1.0)
            logs.append(math.log10(ratio))
        logs = [x for x in logs if math.isfinite(x)]
        out[m] = {
            "fastest": sum(r[p][m] <= 1.0 for p in r) / n if n else math.nan,
            "solved": sum(math.isfinite(r[p][m]) for p in r) / n if n else math.nan,
            "problems_solved": sum(math.isfinite(r[p][m]) for p in r),
            "problems": n,
            "problems_run": len(ran.get(m, set())),
            "score": 10 ** float(np.mean(logs)) if logs else math.nan,
            "score_problems": len(logs),
        }
    return out


def profile_lines(board: Sequence[Mapping[str, Any]]) -> list[list[str]]:
    """The leaderboard's printable lines (header first)."""
    head = ["method", "fastest (ρ(1))", "within 2× (ρ(2))", "within 10× (ρ(10))", "solved (ρ(∞))",
            "geo-mean time ratio (unsolved: 2× budget)", "problems run", "final-loss score (/ adam)"]  # fmt: skip
    lines = [head]
    for b in board:
        lines.append([b["method"], f"{b['rho1']:.2f}", f"{b['rho2']:.2f}", f"{b['rho10']:.2f}",
                      f"{b['solved']:.2f} ({b['problems_solved']}/{b['problems']})",
                      number(b["score"], ".3g") + (f" ({b['score_problems']})" if b["score_problems"] else ""),
                      str(b["problems_run"]), number(b.get("loss_score", math.nan), ".3g")])  # fmt: skip
    return lines
