"""Benchmark every applicable method on every chosen problem at equal budgets, ranked.

    physgrad bench                                   # every shipped problem, every applicable method
    physgrad bench --quick                           # a handful of fast problems, ~10 s per run, 2 seeds
    physgrad bench --seconds 600 --seeds 5           # the long version (hours to days on a few cores)
    physgrad bench --problems oscillators,sine --methods adam,hig,optax:lion --steps 500

A bench directory (default ``bench/``) holds one study directory per problem,
``BENCH/<problem>/``, laid out exactly as ``physgrad compare`` writes it (``study.json``,
``runs/``, ``summary.csv``, ``results.csv``, ``paired_tests.csv``, ``loss_vs_time.png``),
so ``physgrad report BENCH/<problem>`` works on it, and running the same bench again skips
finished (or diverged) runs and resumes interrupted ones from their checkpoints. Next to
them:

- ``BENCH/<problem>/bench_table.csv`` / ``.md``: per method the final test loss over seeds
  (median with a bootstrap interval; a diverged seed is +∞), its rank, its ratio to Adam
  (paired by seed) and the comparison with the problem's best method, paired by seed;
- ``BENCH/leaderboard.csv`` / ``.md``: per method the geometric-mean ratio to Adam over
  the problems it ran on, its wins (rank 1), divergences and failures;
- ``BENCH/heatmap.png``: log₁₀(ratio to Adam), method × problem;
- ``BENCH/bench.md``: all of it, with the budgets, settings and machine;
- ``BENCH/bench.json``: what was asked and the applicability of every candidate.

**Applicability** (:mod:`physgrad.harness.bench.applicability`): a candidate method runs on a
problem when the run's configuration resolves and the method's own ``check`` accepts the
problem's objective, decided from shapes alone (no data, no training); :data:`POLICY`
skips a few pairings that make no sense as a bench entry, with the reason.

**One run loop.** Each problem's runs are :func:`physgrad.harness.study.compare`'s, with
``record_failures=True``: a run that the engine refuses (the memory guard) or that raises
is recorded in ``BENCH/<problem>/failures.json`` (its traceback in its run directory) and
the bench goes on, while bad input and an interrupt stop it; a diverged run is an ordinary
finished study run with status ``diverged``. Refused runs are tried again on the next
invocation (a refusal costs seconds; the cause may have been fixed).

**The metric** is the one ``compare``'s table uses: each run's final test loss
(``summary.csv``). A method ranks by the fraction of its seeds that diverged first (a method
that diverges is less useful than any that does not), then by its median final test loss
over seeds, a diverged seed counting as +∞ (:mod:`physgrad.harness.seeds`). The comparison
with the best method is ``physgrad.harness.stats``' pairing by seed, with the two-sided
Wilcoxon signed-rank p-value over seeds from 6 seeds on.

The package: :mod:`~physgrad.harness.bench.choices` (problems, candidates, the quick profile,
``--set`` scopes), :mod:`~physgrad.harness.bench.applicability` (which method runs where),
:mod:`~physgrad.harness.bench.tables` (method rows, paired tests, leaderboard) and
:mod:`~physgrad.harness.bench.report` (the files above, from the study directories alone); the
heat map is drawn by :func:`physgrad.harness.plots.heatmap`. Everything here is a pure function of
its arguments and the files it reads; nothing changes global state on import.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ...engine.rundir import atomic_write, one_writer
from ...engine.types import Seconds
from ..calibration import machine
from ..config import Budget
from ..failures import read_failures
from ..study import compare
from .applicability import POLICY, Verdict, applicability, describe_verdicts, plan
from .choices import (
    PROFILES,
    QUICK,
    STANDARD,
    STANDARD_EXCLUDED,
    ZOO,
    choose_methods,
    choose_problems,
    problem_settings,
    profile_budgets,
    profile_choice,
    quick_settings,
    study_settings,
)
from .estimate import estimate, plan_lines, total_seconds
from .report import BenchReport, heatmap, problem_table, report
from .tables import REFERENCE, add_paired_tests, leaderboard, method_rows, table_lines

# What the command line, the tests and the benchmarks use; the rest lives in the modules.
__all__ = [
    "POLICY", "PROFILES", "QUICK", "REFERENCE", "STANDARD", "STANDARD_EXCLUDED", "ZOO", "BenchReport", "Verdict",
    "add_paired_tests", "applicability", "bench", "calibrate_only", "choose_methods", "choose_problems",
    "describe_verdicts", "estimate", "heatmap", "leaderboard", "machine", "method_rows", "plan", "plan_lines",
    "problem_settings", "problem_table", "profile_budgets", "profile_choice", "quick_settings", "read_failures", "report", "run_problem",
    "study_settings", "table_lines", "total_seconds",
]  # fmt: skip


def run_problem(
    problem: str,
    verdicts: Sequence[Verdict],
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    progress: Callable[[], Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    calibrate: bool = True,
    executor=None,
) -> list[dict[str, Any]]:
    """One problem's study in ``out``: :func:`physgrad.harness.study.compare` of its applicable
    methods × ``seeds`` (the same ``study.json``, run directories, skipping and resuming)
    with ``record_failures=True``, so that a run which raises (the memory guard's refusal, a
    crash) is recorded in ``failures.json`` and the others go on. Each of compare's lines is
    echoed with the problem's name in front. Returns the study's summary rows."""
    methods = [v.method for v in verdicts if v.runs]
    return compare(problem, methods, seeds, budget, out, settings=study_settings(problem, methods, settings or {}),
                   progress=progress, echo=lambda line: echo(f"{problem} {line}"), devices=devices,
                   record_failures=True, calibrate=calibrate, executor=executor)  # fmt: skip


def bench(
    problems: Sequence[str],
    methods: Sequence[str],
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    progress: Callable[[], Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    profile: str = "",
    calibrate: bool = True,
    budgets: dict[str, Budget] | None = None,
    executor=None,
) -> BenchReport:
    """Run the bench into ``out`` (see the module docstring) and write its report.

    ``methods`` are the candidates (each problem runs those that apply); ``settings`` the
    ``--set`` values (``p.name`` scopes to problem ``p``); ``profile`` names a preset such
    as ``quick`` in the report; ``budgets`` replaces ``budget`` for the problems it names
    (a profile's cheaper problems); ``calibrate``: a seconds budget is calibrated
    (:mod:`physgrad.harness.calibration`); ``executor``: where each problem's runs go
    (:mod:`physgrad.harness.workers`; None: one after the other here)."""
    budgets = budgets or {}
    settings = settings or {}
    out = Path(out)
    verdicts = plan(problems, methods, settings, echo=echo)
    with one_writer(out, "bench"):  # one writer per bench directory, for the whole bench
        atomic_write(out / "bench.json", json.dumps({
            "problems": list(problems), "methods": list(methods), "seeds": list(seeds), "budget": budget.to_dict(),
            "settings": settings, "profile": profile, "devices": devices,
            "calibrated": calibrate and isinstance(budget, Seconds),
            "budgets": {p: b.to_dict() for p, b in budgets.items()},
            "verdicts": {p: [dataclasses.asdict(v) for v in vs] for p, vs in verdicts.items()},
            "machine": machine(),
        }, indent=2, default=str) + "\n")  # fmt: skip
        for i, problem in enumerate(problems, 1):
            runnable = sum(v.runs for v in verdicts[problem])
            mine = budgets.get(problem, budget)
            echo(
                f"problem {i}/{len(problems)} {problem}: {runnable} methods x {len(seeds)} seeds, budget {mine} per run"
            )
            run_problem(problem, verdicts[problem], seeds, mine, out / problem, settings=settings, progress=progress,
                        echo=echo, devices=devices, calibrate=calibrate, executor=executor)  # fmt: skip
        return report(out)


def calibrate_only(
    problems: Sequence[str],
    verdicts: Mapping[str, Sequence[Verdict]],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    budgets: dict[str, Budget] | None = None,
) -> None:
    """The calibration phase of every problem's study and nothing else: each problem's
    applicable methods timed (:func:`physgrad.harness.calibration.study_calibration`) into
    ``out/<problem>/calibration.*``, which the bench then reuses (and ``--plan`` reads)."""
    from ..calibration import study_calibration
    from ..study import plan as study_plan

    for problem in problems:
        methods = [v.method for v in verdicts[problem] if v.runs]
        if not methods:
            continue
        configs = study_plan(problem, methods, [0], (budgets or {}).get(problem, budget),
                             study_settings(problem, methods, settings or {}))  # fmt: skip
        (Path(out) / problem).mkdir(parents=True, exist_ok=True)
        with one_writer(Path(out) / problem, "study"):
            study_calibration(Path(out) / problem, {c.method: c for c in configs}, devices=devices,
                              record_failures=True, echo=lambda line, p=problem: echo(f"{p} {line}"))  # fmt: skip
