"""``physgrad bench`` and ``physgrad report`` on a bench directory, on the console: the
profile's choices resolved, the plan and its estimated time, each problem's table, the two
leaderboards and the files written (:class:`~physgrad.harness.options.BenchOptions` carries
the flags)."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from ...engine import rundir
from ...engine.types import Seconds
from ..arguments import DEFAULT_SECONDS, UsageError, output_dir
from ..config import Budget
from ..console import files, print_table
from ..options import BenchOptions


@dataclasses.dataclass(frozen=True)
class BenchChoices:
    """What a bench runs: the flags of :class:`~physgrad.harness.options.BenchOptions` with
    the profile's problems, methods, settings, budgets and seeds filled in."""

    problems: list[str]
    methods: list[str]
    seeds: range
    budget: Budget
    budgets: dict[str, Budget]  # a problem's own budget where the profile gives it one
    settings: dict[str, Any]
    out: Path


def choices(options: BenchOptions) -> BenchChoices:
    """The profile's (``--quick``, ``--standard``) choices where a flag leaves them open,
    checked; the output directory made."""
    from .. import bench

    name, settings = options.profile, options.settings
    if name:
        profile = bench.profile_choice(name)
        problems = bench.choose_problems(options.problems) if options.problems else list(profile["problems"])
        methods = bench.choose_methods(options.methods) if options.methods else list(profile["methods"])
        settings = {**bench.quick_settings(problems, methods, name), **settings}
        budget = options.budget or Seconds(profile["seconds"])
        budgets = {} if options.budget else bench.profile_budgets(profile, problems)
        seeds = options.seeds or profile["seeds"]
    else:
        problems = bench.choose_problems(options.problems)
        methods = bench.choose_methods(options.methods)
        budget, seeds, budgets = options.budget or Seconds(DEFAULT_SECONDS), options.seeds or 1, {}
    if options.tuned and not options.seeds:  # the chosen configuration on at least 3 seeds (AlgoPerf: 3 studies)
        seeds = max(seeds, 3)
    default = (f"bench-{name}" if name else "bench") + ("-tuned" if options.tuned else "")
    out = output_dir(options.out if options.out is not None else default)
    return BenchChoices(problems, methods, range(seeds), budget, budgets, settings, out)


def bench_command(console, options: BenchOptions) -> int:
    """The bench of ``options``: the plan (``--plan``, ``--calibrate-only``) or the runs and
    their tables."""
    from .. import bench

    run, name = choices(options), options.profile
    budget, budgets, settings = run.budget, run.budgets, run.settings
    calibrate = not options.no_calibrate and isinstance(budget, Seconds)
    console.print(
        f"bench{f' ({name} profile)' if name else ''}: {len(run.problems)} problems x {len(run.methods)} candidate "
        f"methods, budget {budget}{' (calibrated)' if calibrate else ''} per run"
        + "".join(f", {p} {b}" for p, b in budgets.items())
        + f", seeds {list(run.seeds)}, "
        f"settings {settings or 'paper defaults'} -> {run.out}"
    )
    if options.tuned:
        console.print(f"tuned: {options.trials} trials per method and problem, chosen on validation (holdout "
                      f"{options.holdout:g} where a problem has no val split), then {len(run.seeds)} seeds on test")  # fmt: skip
    if options.plan or options.calibrate_only:
        return print_plan(console, options, run)
    console.print("deciding which methods apply to which problem (from shapes; no data, no training)")
    from ...engine.progress import RichProgressMeter
    from ..tune_cli import executor_of  # --workers / --scheduler (harness/workers.py)

    if options.tuned:
        from .tuned import tuned_bench

        with executor_of(options) as executor:
            tuned = tuned_bench(run.problems, run.methods, budget, run.out, trials=options.trials,
                                seeds=len(run.seeds), settings=settings, budgets=budgets, holdout=options.holdout,
                                profile=name, executor=executor, echo=console.print)  # fmt: skip
        print_tuned(console, tuned)
        return 0

    meter = None if options.quiet or not console.is_terminal else RichProgressMeter
    with executor_of(options) as executor:
        result = bench.bench(run.problems, run.methods, run.seeds, budget, run.out, settings=settings, progress=meter,
                             echo=console.print, devices=options.devices, profile=name,
                             calibrate=not options.no_calibrate, budgets=budgets, executor=executor)  # fmt: skip
    print_bench(console, result)
    return 0


def print_bench(console, result) -> None:
    """A bench's tables per problem, its two leaderboards and the files written
    (:class:`physgrad.harness.bench.BenchReport`; the budgets and seeds from its bench.json)."""
    from .. import bench

    out = result.files["markdown"].parent
    info = rundir.read_json(out / "bench.json", rundir.NOT_A_STUDY)
    budget = Budget.of(info["budget"])
    budgets = {p: Budget.of(b) for p, b in info.get("budgets", {}).items()}
    seeds = len(info["seeds"])
    for problem in info["problems"]:
        table = result.tables[problem]
        print_table(
            console,
            bench.table_lines(table, inapplicable=False),
            title=f"{problem}: {budgets.get(problem, budget)} per run",
        )
        for status in ("skipped", "not applicable"):
            names = [t["method"] for t in table if t["status"] == status]
            if names:
                console.print(f"  {status}: {', '.join(names)} (reasons in {out / problem / 'bench_table.md'})")
    plural = "s" if seeds != 1 else ""
    print_table(console, result.profile_lines, title=f"leaderboard: performance profile of the time to target, "
                f"{budget} per run, {seeds} seed{plural}",
                caption="rho(tau): fraction of all problems within a factor tau of the fastest method's median "
                        "time to the problem's target test loss; geo-mean over the problems run (unsolved: 2x the "
                        "budget); profile.png draws rho(tau)")  # fmt: skip
    print_table(console, result.lines, title=f"by final test loss: {budget} per run, {seeds} seed{plural}")
    written = files(*(result.files[k] for k in ("markdown", "leaderboard", "profile", "table", "heatmap",
                                                "profile_figure")))  # fmt: skip
    console.print(f"wrote {written} and per problem {out}/PROBLEM/bench_table.csv")


def print_tuned(console, result) -> None:
    """A tuned bench's tables per problem (the chosen configurations on test), its tuned
    hyperparameters and its leaderboard at both budgets
    (:class:`physgrad.harness.bench.tuned_report.TunedReport`)."""
    from .. import bench
    from .tuned_report import CAP, effect_lines, hyper_lines, winners

    for problem, table in result.tables.items():
        print_table(console, bench.table_lines(table, inapplicable=False),
                    title=f"{problem}: the tuned configurations on test")  # fmt: skip
    if result.hyperparameters:
        print_table(console, hyper_lines(result.hyperparameters), title="tuned hyperparameters (chosen on validation)")
    if result.effect:
        print_table(console, effect_lines(result.effect), title="what tuning changed, on validation (* rank moved)",
                    caption="; ".join(winners(result.effect)))  # fmt: skip
    print_table(console, result.lines, title="leaderboard (tuned): time to target at the full and at half the budget",
                caption=f"integrated performance profile: 1/({CAP:g}-1) x the integral of rho(tau) over tau in "
                        f"[1, {CAP:g}] (1: fastest on every problem); geo-mean time ratio over the problems run "
                        "(unsolved: 2x the budget)")  # fmt: skip
    written = files(*(result.files[k] for k in ("markdown", "leaderboard", "hyperparameters", "effect", "table",
                                                "profile_full", "profile_half")))  # fmt: skip
    console.print(f"wrote {written}; per problem its tune (trials.csv, best.json) and final/ study")


def print_plan(console, options: BenchOptions, run: BenchChoices) -> int:
    """``--plan`` (and ``--calibrate-only``, which calibrates first): the runs per problem
    and their estimated time from the calibration (:mod:`physgrad.harness.bench.estimate`);
    nothing trains."""
    from .. import bench
    from ..workers import default_workers
    from .estimate import (
        LOOP_SECONDS_PER_STEP,
        RUN_OVERHEAD_SECONDS,
        UNCALIBRATED_COMPILE_SECONDS,
        duration,
        wall_seconds,
    )

    problems, seeds, budget, budgets, out = run.problems, run.seeds, run.budget, run.budgets, run.out
    verdicts = bench.plan(problems, run.methods, run.settings, echo=console.print)
    if options.calibrate_only:
        if not isinstance(budget, Seconds) or options.no_calibrate:
            raise UsageError("--calibrate-only needs a calibrated --seconds budget")
        bench.calibrate_only(problems, verdicts, budget, out, settings=run.settings, echo=console.print,
                             devices=options.devices, budgets=budgets)  # fmt: skip
    if options.tuned:  # trials and test runs per method, and the test study's calibration
        from .tuned import tuned_estimate

        rows = tuned_estimate(problems, verdicts, options.trials, len(seeds), budget, out, budgets)
    else:
        rows = bench.estimate(problems, verdicts, seeds, budget, out, budgets)
    runs_text = f"{options.trials} trials + {len(seeds)} seeds" if options.tuned else f"{len(seeds)} seeds"
    print_table(console, bench.plan_lines(rows), title=f"plan: {budget} per run, {runs_text} -> {out}",
                caption=f"a calibrated method: steps x (calibrated s/step + {1e6 * LOOP_SECONDS_PER_STEP:g} us of "
                        f"loop per step) + {RUN_OVERHEAD_SECONDS:g} s per run; not calibrated: its budget + "
                        f"{RUN_OVERHEAD_SECONDS:g} s per run and {UNCALIBRATED_COMPILE_SECONDS:g} s to calibrate it; "
                        "on an idle machine")  # fmt: skip
    uncalibrated = sum(r["methods"] - r["calibrated"] for r in rows)
    note = (f"; {uncalibrated} method(s) not calibrated yet (--calibrate-only times them)" if uncalibrated else
            "; every method calibrated")  # fmt: skip
    console.print(f"estimated total: {duration(bench.total_seconds(rows))} for {sum(r['runs'] for r in rows)} runs"
                  f"{note}; nothing was trained")  # fmt: skip
    workers = options.workers if options.workers is not None else default_workers()
    if options.scheduler is None and workers > 1:  # a cluster's size is its own: not known here
        console.print(f"on {workers} workers: about {duration(wall_seconds(rows, workers))} of wall-clock at best "
                      "(the runs spread over them; each problem's calibration one method after the other)")  # fmt: skip
    return 0
