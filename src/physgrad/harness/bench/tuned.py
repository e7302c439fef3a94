"""``physgrad bench --tuned``: every applicable method tuned on every problem of the bench with
the same number of trials, then ranked on test (AlgoPerf's external-tuning rules).

Dahl et al. 2023 ("Benchmarking Neural Network Training Algorithms", §4) give every
submission the same number of quasi-random trials from a search space it declares, select
on validation data and score on held-out data. The untuned bench (:func:`physgrad.harness.bench.bench`)
compares methods at their paper defaults, which on toy2d lets HIG, K-FAC and KHIG diverge
and makes HIG's η depend on how the loss is normalised (issue 50). Here each problem's
study is a :func:`physgrad.harness.tune.tune` of its applicable methods, so nothing about
the trials is new: the same declared spaces (:mod:`physgrad.harness.spaces`), QMC points,
validation split, journal storage, calibration and executor.

Layout of ``BENCH/``:

- ``bench.json``: what was asked (with ``"tuned": {"trials", "holdout"}``), the
  applicability of every candidate and the machine;
- ``BENCH/<problem>/``: the problem's tune directory (``tune.json``, ``optuna.journal``,
  ``trials/``, ``trials.csv``, ``best.json``), whose ``final/`` is the chosen
  configurations' study on the seeds, reported on test (``summary.csv``, ``results.csv``);
  beside them the problem's final-loss table (``bench_table.csv``/``.md``);
- the leaderboard (:mod:`physgrad.harness.bench.tuned_report`): ``leaderboard.csv``/``.md``,
  ``hyperparameters.csv``, ``profile.csv``, ``profile.png``, ``profile_half.png``, ``bench.md``.

**Resuming.** Each problem's tune keeps its finished trials in its journal and resumes an
interrupted trial from its run's checkpoints; its ``final/`` study skips finished runs. So
the same command again loses nothing that finished, and the tables it writes are those of
an uninterrupted bench (tested).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ...engine.rundir import atomic_write, one_writer
from ...engine.types import Seconds
from ...errors import ConfigError
from ..calibration import machine
from ..config import Budget
from .applicability import Verdict, plan
from .choices import study_settings
from .estimate import estimate


def tuned_bench(
    problems: Sequence[str],
    methods: Sequence[str],
    budget: Budget,
    out: str | Path,
    *,
    trials: int = 5,
    seeds: int = 3,
    settings: dict[str, Any] | None = None,
    budgets: dict[str, Budget] | None = None,
    holdout: float = 0.2,
    profile: str = "",
    executor=None,
    echo: Callable[[str], None] = print,
):
    """Tune every applicable candidate of ``methods`` on each of ``problems`` with ``trials``
    trials on ``budget`` (``budgets``: a problem's own), choose on validation (``holdout`` of
    train where the problem has no val split), run the chosen configurations on seeds
    0..``seeds``−1 on test, and write the leaderboard (see the module docstring). Returns
    :class:`physgrad.harness.bench.tuned_report.TunedReport`. ``executor``: where the runs go
    (:mod:`physgrad.harness.workers`; None: one after the other in this process)."""
    from ..tune import tune
    from .tuned_report import tuned_report

    if trials < 1 or seeds < 1:
        raise ConfigError(f"a tuned bench needs at least 1 trial and 1 seed, got {trials} and {seeds}")
    if not 0 < holdout < 1:
        raise ConfigError(f"the validation holdout is a fraction in (0, 1), got {holdout}")
    budgets, settings, out = budgets or {}, settings or {}, Path(out)
    verdicts = plan(problems, methods, settings, echo=echo)
    with one_writer(out, "bench"):  # one writer per bench directory; each tune takes its own lock
        atomic_write(out / "bench.json", json.dumps({
            "problems": list(problems), "methods": list(methods), "seeds": list(range(seeds)),
            "budget": budget.to_dict(), "settings": settings, "profile": profile, "devices": 1,
            "calibrated": isinstance(budget, Seconds), "budgets": {p: b.to_dict() for p, b in budgets.items()},
            "tuned": {"trials": trials, "holdout": holdout},
            "verdicts": {p: [dataclasses.asdict(v) for v in vs] for p, vs in verdicts.items()}, "machine": machine(),
        }, indent=2, default=str) + "\n")  # fmt: skip
        for i, problem in enumerate(problems, 1):
            runnable = [v.method for v in verdicts[problem] if v.runs]
            mine = budgets.get(problem, budget)
            if not runnable:
                echo(f"problem {i}/{len(problems)} {problem}: no candidate applies")
                continue
            echo(f"problem {i}/{len(problems)} {problem}: {len(runnable)} methods x {trials} trials, then "
                 f"{seeds} seeds on test, budget {mine} per run")  # fmt: skip
            tune(problem, runnable, trials=trials, budget=mine, out=out / problem, seeds=seeds,
                 settings=study_settings(problem, runnable, settings), executor=executor, holdout=holdout,
                 echo=lambda line, p=problem: echo(f"{p} {line}"))  # fmt: skip
        return tuned_report(out)


def tuned_estimate(
    problems: Sequence[str],
    verdicts: Mapping[str, Sequence[Verdict]],
    trials: int,
    seeds: int,
    budget: Budget,
    out: str | Path,
    budgets: dict[str, Budget] | None = None,
) -> list[dict[str, Any]]:
    """The plan of a tuned bench (:func:`physgrad.harness.bench.estimate.estimate`'s rows):
    per method ``trials`` trial runs and ``seeds`` test runs at the same calibrated steps
    (a trial trains on the training split less the holdout, which does not change a step's
    cost; the test study takes the trials' calibration, :func:`physgrad.harness.tune.tune`),
    from the calibration in ``BENCH/<problem>/`` where there is one."""
    return estimate(problems, verdicts, range(trials + seeds), budget, out, budgets)


__all__ = ["tuned_bench", "tuned_estimate"]
