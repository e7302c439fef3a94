"""``physgrad tune`` and ``physgrad report`` on a tune directory: parsing-to-call glue over
:mod:`physgrad.harness.tune`, :mod:`physgrad.harness.tune_report` and the workers'
executor (:mod:`physgrad.harness.workers`); the parser is :mod:`physgrad.harness.arguments`'s."""

from __future__ import annotations

from pathlib import Path

from .arguments import UsageError, budget_of, output_dir, run_settings


def executor_of(args, default: int | None = None):
    """The executor of ``--workers N`` (absent: ``default``, None for
    :func:`~physgrad.harness.workers.default_workers`, the machine's cores; 1: in this
    process) and ``--scheduler ADDRESS`` (a running Dask scheduler)."""
    from .workers import executor_for

    workers = getattr(args, "workers", None) or default
    if workers is not None and workers < 1:
        raise UsageError(f"--workers must be at least 1, got {workers}")
    return executor_for(workers, scheduler=getattr(args, "scheduler", None))


def _print(console, lines, title="", caption=""):
    from .console import print_table as _print_table  # the command line's one table printer

    _print_table(console, lines, title=title, caption=caption)


def tune_command(args, console) -> int:
    """``physgrad tune PROBLEM --methods a,b --trials N [budget] [--seeds K] [--workers N]
    [--scheduler ADDRESS] [--storage URL] [--prune [--eta E --rungs R]] [--holdout F] [--set ...]``."""
    from .config import problem_slug, split_methods
    from .papers import protocol
    from .registry import PROBLEMS
    from .tune import NoPruning, SuccessiveHalving, tune

    if args.problem not in PROBLEMS:
        from .config import choose

        choose("problem", args.problem, PROBLEMS)
    methods = split_methods(args.methods) if args.methods else list(protocol(args.problem).methods)
    if args.trials < 1 or args.seeds < 1:
        raise UsageError("--trials and --seeds must be at least 1")
    if args.no_calibrate:
        raise UsageError("tune's trials train calibrated step budgets; --no-calibrate would tie them to the load")
    pruning = SuccessiveHalving(args.eta, args.rungs) if args.prune else NoPruning()
    out = output_dir(args.out or f"studies/tune-{problem_slug(args.problem)}")
    budget = budget_of(args)
    executor = executor_of(args)
    console.print(
        f"tuning {', '.join(methods)} on {args.problem}: {args.trials} trials each, budget {budget} per trial, "
        f"{'successive halving, ' if args.prune else ''}{executor.slots} worker(s) -> {out}"
    )
    with executor:
        tune(args.problem, methods, trials=args.trials, budget=budget, out=out, seeds=args.seeds,
             settings=run_settings(args), pruning=pruning, storage=args.storage, executor=executor,
             holdout=args.holdout, echo=console.print)  # fmt: skip
    return report_command(args, console, out)


def report_command(args, console, out: str | Path | None = None) -> int:
    """The table and ``trials.png`` of a tune directory (and the final study's table)."""
    from .tune_report import report

    out = Path(out or args.dir)
    result = report(out)
    _print(console, result.lines, title=f"{out}: tuned on validation, chosen configuration on test",
           caption="val loss: final loss on the validation data (the problem's val split, or train held out); test: "
                   "the chosen configuration on the seeds, median [95% interval]")  # fmt: skip
    if result.figure:
        console.print(f"wrote {result.figure}; the chosen configurations' study: physgrad report {out / 'final'}")
    return 0


__all__ = ["executor_of", "report_command", "tune_command"]
