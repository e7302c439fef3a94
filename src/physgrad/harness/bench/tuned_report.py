"""The leaderboard of a tuned bench (:mod:`physgrad.harness.bench.tuned`), (re)written from its
files alone: ``physgrad report BENCH`` redraws it.

Per problem the test runs of the chosen configurations (``BENCH/<problem>/final/``) give
each run's time to the problem's target test loss (:mod:`physgrad.harness.targets`: the
calibrated time of its first evaluation at or below the target; a diverged run never
reaches it) and, per method, the median over seeds t(p, m). Across problems, with
r(p, m) = t(p, m) / min over methods of t(p, ·) and ρ_m(τ) the fraction of the bench's
problems with r(p, m) ≤ τ (Dolan & Moré 2002), two numbers per method:

- the **integrated performance profile**, AlgoPerf's benchmark score (Dahl et al. 2023,
  §4.5), capped at r_max = 4:

      B_m = 1/(r_max − 1) ∫₁^{r_max} ρ_m(τ) dτ = (1/n) Σ_p max(0, r_max − r(p, m)) / (r_max − 1),

  exact because ρ_m is a step function: a problem solved within r ≤ r_max adds
  (r_max − r)/(r_max − 1)/n, one solved slower or not at all adds 0; 1 is "fastest on every
  problem", 0 "never within 4× of the fastest";
- the **geometric-mean score** of the untuned bench (:func:`physgrad.harness.targets.scores`):
  the geometric mean of r(p, m) over the problems the method ran where some method reached
  the target, an unsolved one counting as twice the problem's time budget over the fastest
  time (PAR-2).

**Two budgets.** Both at the full budget and at half of it: a run reaches the target within
half its budget when its first reach is at or before half its calibrated time, and the
penalty's budget is halved. The trials were tuned for the full budget; reading the same
runs at half shows whether the ranking holds earlier in training ("Fantastic pretraining
optimizers", Wen et al. 2025, found rankings that flip between intermediate and final
checkpoints). A diverged run counts as not reaching the target at either budget, as in
every other table.

**What tuning changed** (``tuning_effect.csv``), on each problem's validation split, where
both configurations ran: per method the untuned configuration's validation loss (trial 0)
beside the chosen one's, their ratio, and the method's rank among the problem's methods by
each. It answers "would the untuned comparison have named the same winner?" with one trial
per configuration, so a rank swapped between close losses is not a verdict.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

from ...engine import rundir
from ...engine.rundir import atomic_write
from .. import plots, targets
from ..config import ConfigError
from ..seeds import as_float, number
from ..study import markdown, write_csv
from .applicability import Verdict
from .report import problem_table
from .tables import TABLE_COLUMNS, table_lines, table_records

CAP = 4.0  # r_max: AlgoPerf's cap on the performance ratio
BUDGETS = (("half", 0.5), ("full", 1.0))  # (name, fraction of each run's budget)
BOARD_COLUMNS = ("budget", "fraction", "method", "integrated", "score", "score_problems", "fastest", "solved",
                 "problems_solved", "problems", "problems_run")  # fmt: skip
HYPER_COLUMNS = ("problem", "method", "name", "untuned", "tuned", "low", "high", "trials_finished", "trials")
EFFECT_COLUMNS = ("problem", "method", "untuned_val_loss", "tuned_val_loss", "gain", "rank_untuned", "rank_tuned")


class TunedReport(NamedTuple):
    """A tuned bench's tables (``{problem: method rows}`` of the chosen configurations on
    test), its leaderboard (one row per budget and method, :data:`BOARD_COLUMNS`), the
    tuned hyperparameters beside the untuned ones, and the files written."""

    tables: dict[str, list[dict[str, Any]]]
    board: list[dict[str, Any]]
    hyperparameters: list[dict[str, Any]]
    files: dict[str, Path | None]
    effect: list[dict[str, Any]] = []

    @property
    def lines(self) -> list[list[str]]:
        """The leaderboard's printable lines: both budgets side by side."""
        return board_lines(self.board)


def integrated_profile(
    times: Mapping[str, Mapping[str, float]], methods: Sequence[str], cap: float = CAP
) -> dict[str, float]:
    """Per method B_m = 1/(cap − 1) ∫₁^cap ρ_m(τ) dτ over every problem of ``times``
    (``{problem: {method: median time}}``; a missing method: +∞), in closed form."""
    r = targets.ratios(times, methods)
    n = len(r)
    return {m: sum(max(0.0, cap - r[p][m]) for p in r if r[p][m] <= cap) / ((cap - 1.0) * n) if n else math.nan
            for m in methods}  # fmt: skip


def at_fraction(runs: Sequence[Mapping[str, Any]], fraction: float) -> list[dict[str, Any]]:
    """Time-to-target rows (:func:`physgrad.harness.targets.run_times`) read at ``fraction``
    of each run's budget: a reach after ``fraction`` × its budget time becomes censored
    there (+∞), and the budget time is scaled."""
    if fraction >= 1.0:
        return [dict(r) for r in runs]
    out = []
    for r in runs:
        limit = fraction * as_float(r["budget_time"])
        late = r["status"] == "reached" and not as_float(r["time_to_target"]) <= limit
        row = {**r, "budget_time": limit}
        if late:
            row.update(status="censored", steps_to_target=math.inf, time_to_target=math.inf, wall_to_target=math.inf)
        out.append(row)
    return out


def leaderboard(
    runs: Mapping[str, Sequence[Mapping[str, Any]]], methods: Sequence[str], ran: Mapping[str, set[str]]
) -> list[dict[str, Any]]:
    """The leaderboard rows at each budget of :data:`BUDGETS`. ``runs``: each problem's
    time-to-target rows of its test runs (every problem of the bench, [] for one not run);
    ``methods``: the methods ranked; ``ran``: each method's problems."""
    board = []
    for name, fraction in BUDGETS:
        times, budgets = {}, {}
        for problem, rows in runs.items():
            cut = at_fraction(rows, fraction)
            times[problem] = {t["method"]: t["time"]["median"] for t in targets.method_times(cut, methods)}
            budgets[problem] = max((as_float(r["budget_time"]) for r in cut if math.isfinite(as_float(r["budget_time"]))),
                                   default=math.nan)  # fmt: skip
        scores = targets.scores(times, methods, budgets, ran)
        integrated = integrated_profile(times, methods)
        rows = [{"budget": name, "fraction": fraction, "method": m, "integrated": integrated[m], **scores[m]}
                for m in methods]  # fmt: skip
        rows.sort(key=lambda b: (-b["integrated"] if not math.isnan(b["integrated"]) else 0.0, b["method"]))
        board += rows
    return board


def board_lines(board: Sequence[Mapping[str, Any]]) -> list[list[str]]:
    """Printable lines (header first): per method the integrated profile and the
    geometric-mean score at half and at the full budget, ordered by the full budget's
    integrated profile."""
    by = {(b["budget"], b["method"]): b for b in board}
    order = [b["method"] for b in board if b["budget"] == "full"]
    head = ["method", f"integrated profile (r ≤ {CAP:g}), full budget", "geo-mean time ratio, full",
            "integrated profile, half budget", "geo-mean time ratio, half", "solved (full)", "problems run"]  # fmt: skip
    lines = [head]
    for m in order:
        full, half = by[("full", m)], by[("half", m)]
        lines.append([m, f"{full['integrated']:.3f}", _score(full), f"{half['integrated']:.3f}", _score(half),
                      f"{full['problems_solved']}/{full['problems']}", str(full["problems_run"])])  # fmt: skip
    return lines


def _score(b: Mapping[str, Any]) -> str:
    return number(b["score"], ".3g") + (f" ({b['score_problems']})" if b["score_problems"] else "")


def hyperparameters(out: Path, problem: str) -> list[dict[str, Any]]:
    """One problem's tuned hyperparameters beside the untuned ones and the searched range
    (from its ``tune.json`` and ``best.json``)."""
    tune, best = out / problem / "tune.json", out / problem / "best.json"
    if not tune.exists() or not best.exists():
        return []
    from ..study import read_csv

    asked, chosen = json.loads(tune.read_text()), json.loads(best.read_text())
    # A method none of whose trials finished (all diverged, or the problem cannot hold out a
    # validation split) keeps its untuned configuration: the count says which case it is.
    trials = read_csv(out / problem / "trials.csv") if (out / problem / "trials.csv").exists() else []
    rows = []
    for method, params in chosen.items():
        mine = [t for t in trials if t["method"] == method]
        finished = sum(t["state"] == "COMPLETE" for t in mine)
        for name, value in params.items():
            low, high = asked.get("bounds", {}).get(method, {}).get(name, [math.nan, math.nan])
            rows.append({"problem": problem, "method": method, "name": name,
                         "untuned": asked.get("defaults", {}).get(method, {}).get(name), "tuned": value,
                         "low": low, "high": high, "trials_finished": finished, "trials": len(mine)})  # fmt: skip
    return rows


def tuning_effect(out: Path, problem: str) -> list[dict[str, Any]]:
    """What tuning changed on one problem, on its validation split (from its ``trials.csv``):
    per method L₀, the untuned configuration's validation loss (trial 0, where it completed
    with a finite loss; +∞ where it failed, diverged or was pruned), L*, the chosen
    configuration's (the lowest finite loss of the completed trials:
    :func:`physgrad.harness.tune_report.chosen`; +∞ where none), ``gain`` = L₀ / L* (≥ 1: the
    chosen one may be trial 0; +∞ where only a tuned trial finished, NaN where none did), and
    the method's rank among the problem's methods by L₀ and by L* (1 the lowest; equal losses
    share the better rank; None for a method with no finite loss there, which ranks nowhere).
    Trial 0 runs the untuned configuration clipped into the searched range where a default
    lies outside it (:mod:`physgrad.harness.tune`)."""
    from ..study import kept_path
    from ..tune_report import chosen, read_trials

    if not (out / problem / "tune.json").exists() or not kept_path(out / problem / "trials.csv").exists():
        return []
    info, trials = read_trials(out / problem)
    losses: dict[str, tuple[float, float]] = {}
    for method in info["methods"]:
        mine = [t for t in trials if t["method"] == method]
        if not mine:
            continue
        zero = next((t for t in mine if t["trial"] == 0 and t["state"] == "COMPLETE"), None)
        untuned = zero["val_loss"] if zero and math.isfinite(zero["val_loss"]) else math.inf
        best = chosen(trials, method)
        losses[method] = (untuned, best["val_loss"] if best else math.inf)
    rows = []
    for method, (untuned, tuned) in losses.items():
        rows.append({"problem": problem, "method": method, "untuned_val_loss": untuned, "tuned_val_loss": tuned,
                     "gain": _gain(untuned, tuned), "rank_untuned": _rank(untuned, [u for u, _ in losses.values()]),
                     "rank_tuned": _rank(tuned, [t for _, t in losses.values()])})  # fmt: skip
    return rows


def _gain(untuned: float, tuned: float) -> float:
    """L₀ / L* (see :func:`tuning_effect`), with 0 / 0 = 1 and nothing finished NaN."""
    if math.isinf(tuned):
        return math.nan
    if tuned == 0.0:
        return 1.0 if untuned == 0.0 else math.inf
    return untuned / tuned


def _rank(loss: float, losses: Sequence[float]) -> int | None:
    """1 + how many finite ``losses`` are lower; None for a loss that is not finite."""
    return 1 + sum(x < loss for x in losses if math.isfinite(x)) if math.isfinite(loss) else None


def effect_lines(effect: Sequence[Mapping[str, Any]]) -> list[list[str]]:
    """Printable lines (header first) of :func:`tuning_effect`'s rows, a problem's rows by
    their tuned rank (methods with none last), * where the rank moved."""
    lines = [["problem", "method", "untuned val loss", "tuned val loss", "untuned / tuned", "rank: untuned → tuned"]]
    for problem in dict.fromkeys(e["problem"] for e in effect):
        mine = sorted((e for e in effect if e["problem"] == problem),
                      key=lambda e: (e["rank_tuned"] is None, e["rank_tuned"] or 0, e["method"]))  # fmt: skip
        for e in mine:
            moved = "" if e["rank_untuned"] == e["rank_tuned"] else " *"
            lines.append([problem, e["method"], number(as_float(e["untuned_val_loss"]), ".3g"),
                          number(as_float(e["tuned_val_loss"]), ".3g"), number(as_float(e["gain"]), ".3g"),
                          f"{_place(e['rank_untuned'])} → {_place(e['rank_tuned'])}{moved}"])  # fmt: skip
    return lines


def _place(rank: int | None) -> str:
    return "–" if rank is None else str(rank)


def winners(effect: Sequence[Mapping[str, Any]]) -> list[str]:
    """Per problem one sentence: the method(s) ranked first on validation, untuned and tuned
    ("none finished" where no method has a finite loss)."""
    out = []
    for problem in dict.fromkeys(e["problem"] for e in effect):
        mine = [e for e in effect if e["problem"] == problem]
        first = {k: ", ".join(sorted(e["method"] for e in mine if e[k] == 1)) or "none finished"
                 for k in ("rank_untuned", "rank_tuned")}  # fmt: skip
        same = "the same" if first["rank_untuned"] == first["rank_tuned"] else "changed"
        out.append(f"{problem}: untuned {first['rank_untuned']}; tuned {first['rank_tuned']} ({same})")
    return out


def tuned_report(out: str | Path) -> TunedReport:
    """(Re)write a tuned bench's tables, leaderboard and ``bench.md`` from its files."""
    out = Path(out)
    if not (out / "bench.json").exists():
        raise ConfigError(f"{out} is not a bench directory: bench.json is missing")
    info = rundir.read_json(out / "bench.json", rundir.NOT_A_STUDY)
    if not info.get("tuned"):
        raise ConfigError(f"{out} is an untuned bench: physgrad report draws it as one")
    tables, runs, hyper, effect = {}, {}, [], []
    for problem in info["problems"]:
        verdicts = [Verdict(**v) for v in info["verdicts"][problem]]
        final = out / problem / "final"
        tables[problem] = table = problem_table(final, verdicts)
        runs[problem] = targets.study_times(final, problem)[1] if (final / "summary.csv").exists() else []
        (out / problem).mkdir(exist_ok=True)
        write_csv(out / problem / "bench_table.csv", TABLE_COLUMNS, table_records(problem, table))
        atomic_write(out / problem / "bench_table.md", markdown(table_lines(table)) + "\n")
        hyper += hyperparameters(out, problem)
        effect += tuning_effect(out, problem)
    methods = list(dict.fromkeys(t["method"] for table in tables.values() for t in table
                                 if t["status"] not in ("not applicable", "skipped")))  # fmt: skip
    ran = {m: {p for p, table in tables.items() for t in table
               if t["method"] == m and t["status"] not in ("not applicable", "skipped", "pending")} for m in methods}  # fmt: skip
    board = leaderboard(runs, methods, ran)
    write_csv(out / "leaderboard.csv", BOARD_COLUMNS, [{k: _cell(b[k]) for k in BOARD_COLUMNS} for b in board])
    write_csv(out / "hyperparameters.csv", HYPER_COLUMNS, [{k: _cell(h[k]) for k in HYPER_COLUMNS} for h in hyper])
    write_csv(out / "tuning_effect.csv", EFFECT_COLUMNS, [{k: _cell(e[k]) for k in EFFECT_COLUMNS} for e in effect])
    write_csv(out / "bench_table.csv", TABLE_COLUMNS, [r for p, t in tables.items() for r in table_records(p, t)])
    atomic_write(out / "leaderboard.md", markdown(board_lines(board)) + "\n")
    files: dict[str, Path | None] = {"leaderboard": out / "leaderboard.csv", "hyperparameters": out / "hyperparameters.csv",
                                     "table": out / "bench_table.csv", "markdown": out / "bench.md",
                                     "effect": out / "tuning_effect.csv"}  # fmt: skip
    for name, fraction in BUDGETS:  # the profile's curves at each budget
        times = {p: {t["method"]: t["time"]["median"] for t in targets.method_times(at_fraction(rows, fraction), methods)}
                 for p, rows in runs.items()}  # fmt: skip
        taus = targets.default_taus(times, methods)
        rho = targets.profile(times, methods, taus)
        if name == "full":
            write_csv(out / "profile.csv", ["tau", *rho], [{"tau": f"{tau:.6g}", **{m: f"{v[i]:.4g}" for m, v in rho.items()}}
                                                           for i, tau in enumerate(taus)])  # fmt: skip
        files[f"profile_{name}"] = plots.draw(
            plots.performance_profile, taus, rho, out / ("profile.png" if name == "full" else "profile_half.png"),
            title=f"tuned, {name} budget: performance profile of the time to each problem's target test loss",
        )  # fmt: skip
    atomic_write(out / "bench.md", tuned_markdown(info, tables, board, hyper, effect))
    return TunedReport(tables, board, hyper, files, effect)


def _cell(x: Any) -> Any:
    if isinstance(x, float):
        return "" if math.isnan(x) else "inf" if math.isinf(x) else f"{x:.6g}"
    return x


def hyper_lines(hyper: Sequence[Mapping[str, Any]]) -> list[list[str]]:
    """Printable lines (header first) of the tuned hyperparameters."""
    lines = [["problem", "method", "hyperparameter", "untuned", "tuned", "searched range", "trials finished"]]
    for h in hyper:
        lines.append([h["problem"], h["method"], h["name"], number(as_float(h["untuned"]), ".3g"),
                      number(as_float(h["tuned"]), ".3g"), f"[{h['low']:.3g}, {h['high']:.3g}]",
                      f"{h['trials_finished']}/{h['trials']}" + (" (untuned kept)" if not h["trials_finished"] else "")])  # fmt: skip
    return lines


def tuned_markdown(
    info: Mapping[str, Any],
    tables: Mapping[str, Sequence[dict[str, Any]]],
    board: Sequence[Mapping[str, Any]],
    hyper: Sequence[Mapping[str, Any]],
    effect: Sequence[Mapping[str, Any]] = (),
) -> str:
    """``bench.md`` of a tuned bench: what ran, the leaderboard, the tuned hyperparameters,
    what tuning changed on validation and every problem's table of the chosen
    configurations on test."""
    budget = ", ".join(f"{v:g} {k}" for k, v in info["budget"].items())
    own = "".join(f"; {p}: {', '.join(f'{v:g} {k}' for k, v in b.items())}" for p, b in info.get("budgets", {}).items())
    tuned = info["tuned"]
    out = [
        "# physgrad bench --tuned" + (f" ({info['profile']} profile)" if info.get("profile") else ""),
        "",
        f"- **Tuning**: {tuned['trials']} trials per method and problem from the method's declared search space "
        f"(trial 0 the untuned configuration, then quasi-random points), each on {budget}{own} per run"
        f"{' (calibrated)' if info.get('calibrated') else ''}, trained and chosen on validation data (the problem's "
        f"val split, else the last {tuned['holdout']:g} of train held out).",
        f"- **Test**: the chosen configuration of every method on seeds {', '.join(map(str, info['seeds']))}, "
        "trained on the full training split, reported on test.",
        f"- **Problems**: {', '.join(info['problems'])}; **candidates**: {', '.join(info['methods'])} (each problem "
        "runs those that apply).",
        "",
        "## Leaderboard",
        "",
        f"Integrated performance profile of the time to each problem's target test loss, capped at {CAP:g}× the "
        "fastest method (1: fastest everywhere; 0: never within the cap), beside the geometric-mean time ratio "
        "(an unsolved problem counts as twice the budget over the fastest time), at the full budget and read at "
        "half of it. Sorted by the full budget's integrated profile.",
        "",
        markdown(board_lines(board)) if board else "(no runs yet)",
        "",
        "![performance profile, full budget](profile.png) ![performance profile, half budget](profile_half.png)",
        "",
        "## Tuned hyperparameters",
        "",
        markdown(hyper_lines(hyper)) if hyper else "(none yet)",
        "",
        "## What tuning changed (validation)",
        "",
        "Per problem and method the untuned configuration's validation loss (trial 0) beside the chosen one's, "
        "and the method's rank among the problem's methods by each (* where it moved). One trial per "
        "configuration: a rank swapped between close losses is not a verdict.",
        "",
        *([markdown(effect_lines(effect)), "", *(f"- {w}" for w in winners(effect))] if effect else ["(none yet)"]),
        "",
    ]
    for problem, table in tables.items():
        out += [f"## {problem}", "", markdown(table_lines(table)), "",
                f"Trials: `{problem}/trials.csv`; the test study: `{problem}/final/`.", ""]  # fmt: skip
    return "\n".join(out)


__all__ = [
    "BUDGETS",
    "CAP",
    "TunedReport",
    "at_fraction",
    "integrated_profile",
    "leaderboard",
    "tuned_report",
    "tuning_effect",
]
