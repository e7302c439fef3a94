"""The ``physgrad`` command line: a thin layer over :mod:`physgrad.harness.train` and :mod:`physgrad.harness.study`.

    physgrad list
    physgrad train PROBLEM --method M|M1:N,M2 [--seconds S | --steps N | --epochs E] [--seed K]
                   [--set name=value ...] [--out DIR] [--resume] [--devices N|all]
                   [--coordinator HOST:PORT --num-processes P --process-id I]
    physgrad compare PROBLEM [--methods a,b,...] [--seeds N] [budget] [--set ...] [--out DIR] [--devices N]
                     (--set name=a,b,c sweeps: every cell of the grid is a study)
    physgrad report DIR
    physgrad tune PROBLEM [--methods a,b] [--trials N] [--seeds K] [budget] [--workers N] [--storage URL] [--prune]
    physgrad bench [--problems p1,p2|all] [--methods m1,m2|applicable] [--seeds N] [budget] [--out DIR]
                   [--quick | --standard] [--plan | --calibrate-only] [--set ...]
                   (every applicable method on every problem, ranked; physgrad.harness.bench)
    physgrad calibrate PROBLEM [--methods a,b] [--set ...] [--out FILE.csv|FILE.json] [--repeats N]
    physgrad demo

train, compare, bench, calibrate and demo take --threads N|default (default 1: physgrad.cpu.process_threads).
compare and bench calibrate a --seconds budget (physgrad.harness.calibration; --no-calibrate: wall-clock).
Bad input (an unknown problem, method or setting) prints one line with the valid choices
and exits with status 2.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import sys
import warnings
from pathlib import Path

from rich.console import Console
from rich.table import Table
from rich.text import Text

from .. import rundir
from .arguments import DEMO, UsageError, budget_of, build_parser, output_dir, run_settings, threads_of
from .words import command_line_words


def _print_table(console: Console, lines: list[list[str]], title: str = "", caption: str = ""):
    """A table of plain text (cells such as ``[n/a: 2 seeds]`` are not rich markup)."""
    table = Table(title=title or None, caption=caption or None)
    for i, name in enumerate(lines[0]):
        table.add_column(Text(name), justify="left" if i == 0 else "right")
    for line in lines[1:]:
        table.add_row(*(Text(cell) for cell in line))
    console.print(table)


def _files(*paths) -> str:
    """The files written, comma-separated (a figure that could not be drawn is None: left out)."""
    return ", ".join(str(p) for p in paths if p is not None)


def cmd_list(args, console):
    from ..extras import method_extra, missing_note
    from .papers import protocol
    from .registry import METHODS, PROBLEMS, describe

    console.print("[bold]problems[/bold]")
    for name, cls in PROBLEMS.items():
        note = missing_note(cls.extra)  # a problem whose optional extra is not installed
        paper = protocol(name)
        console.print(f"  {name:<19} {paper.description}" + (f" {note}" if note else ""), markup=False)
        console.print(f"  {'':<19} paper comparison: {', '.join(paper.methods)}", markup=False)
        if paper.target is not None:
            console.print(f"  {'':<19} target test loss: {paper.target.loss:g} ({paper.target.origin})", markup=False)
    console.print("[bold]methods[/bold]")
    for name in METHODS:
        note = missing_note(method_extra(name))
        console.print(f"  {name:<19} {describe(name)}" + (f" {note}" if note else ""), markup=False)
    from .registry import optax_names

    console.print("[bold]optax optimizers on DP gradients[/bold] (hyperparameters by --set, learning_rate as lr)")
    console.print("  " + ", ".join(optax_names()), markup=False, soft_wrap=False)
    console.print("  a sequence such as adam:2000,hig runs Adam for 2000 steps, then HIG from those parameters")
    from .registry import INVERSE_SOLVERS

    console.print("[bold]SIP local inverse solvers[/bold] (--set solver=...)")
    console.print(f"  {', '.join(INVERSE_SOLVERS)}", markup=False)
    console.print("  --no-network optimises x itself for each test sample (direct optimisation)", markup=False)
    console.print("  a comma-separated --set value sweeps a grid in compare: --set poles=1,2,3,4 --set clip=value,norm,none",
                  markup=False)  # fmt: skip
    return 0


def _progress(args, console):
    from ..progress import NoProgressMeter, RichProgressMeter

    return NoProgressMeter() if args.quiet or not console.is_terminal else RichProgressMeter()


def _start_processes(args) -> str | None:
    """Join a multi-process run if asked (before any JAX work); the default --devices."""
    multi = (args.coordinator, args.num_processes, args.process_id)
    if all(v is None for v in multi):
        return args.devices or "1"
    if any(v is None for v in multi):
        raise UsageError("a multi-process run needs all of --coordinator, --num-processes and --process-id")
    from ..distributed import initialize

    initialize(args.coordinator, args.num_processes, args.process_id)
    return args.devices or "all"


def cmd_train(args, console):
    from .config import make_config, method_slug
    from .study import describe_run
    from .train import read_summary, train

    devices = _start_processes(args)
    config = make_config(args.problem, args.method, budget=budget_of(args), seed=args.seed, settings=run_settings(args))
    out = output_dir(
        args.out if args.out is not None else f"runs/{args.problem}-{method_slug(args.method)}-seed{args.seed}"
    )
    stages = "; then ".join(
        f"{p.method}"
        + (f" for {p.steps} steps" if p.steps else "")
        + f": batch {p.batch_size}, "
        + ", ".join(f"{k} {v}" for k, v in p.hyperparameters.items())
        for p in config.phases
    )
    import jax

    if jax.process_index() > 0:  # process 0 reports; the others compute alike
        console.quiet = True
    where = (
        ""
        if devices == "1"
        else f" on {devices} devices" + (f" of {jax.process_count()} processes" if jax.process_count() > 1 else "")
    )
    console.print(f"{config.problem} / {stages}; seed {config.seed}, budget {config.budget}{where} -> {out}")
    before = read_summary(out) if args.resume else None
    from ..engine.recording import kept_path
    from ..engine.resume import FINAL_FILES

    missing = [name for name in FINAL_FILES if not kept_path(out / name).exists()]
    summary = train(config, out, resume=args.resume, progress=_progress(args, console), devices=devices)
    if before is not None and summary == before and missing:  # a finished run's deleted files, made again
        console.print(f"done already ({summary['status']}): {describe_run(summary)}; made again from its final "
                      f"checkpoint: {', '.join(missing)}")  # fmt: skip
    elif before is not None and summary == before:  # a resume with nothing to do leaves every file as it was
        console.print(f"done already ({summary['status']}): {describe_run(summary)}; every file unchanged")
    else:
        console.print(f"{summary['status']}: {describe_run(summary)}")
    return 0


def _run_compare(console, problem, methods, seeds, budget, settings, out, quiet=False, devices="1", calibrate=True,
                 executor=None):  # fmt: skip
    from ..progress import RichProgressMeter
    from .study import compare, plan, report

    plan(problem, methods, seeds, budget, settings)  # validate every name before anything runs
    calibrated = calibrate and budget.kind == "seconds"
    console.print(
        f"comparing on {problem}: budget {budget}{' (calibrated)' if calibrated else ''} per run, seeds {list(seeds)}, "
        f"settings {settings or 'paper defaults'}"
    )
    meter = None if quiet or not console.is_terminal else RichProgressMeter
    compare(problem, methods, seeds, budget, out, settings=settings, progress=meter, echo=console.print,
            devices=devices, calibrate=calibrate, executor=executor)  # fmt: skip
    from .seeds import table_note

    result = report(out)
    _print_table(console, result.lines, title=f"{problem}: {budget} per run", caption=table_note(result.table))
    _print_paired_tests(console, out)
    _print_targets(console, out)
    extra = [Path(out) / name for name in ("calibration.json", "time_to_target.csv") if (Path(out) / name).exists()]
    console.print(f"wrote {_files(Path(out) / 'results.csv', Path(out) / 'summary.csv', *extra, result.figure)}")
    return result


def _print_targets(console, out):
    """The study's time-to-target table (:mod:`physgrad.harness.targets`), where its problem declares a target."""
    from .targets import study_times, table_lines

    target, runs, table = study_times(out)
    if target is None or not table:
        return
    axis = runs[0]["axis"] if runs else "wall-clock"
    _print_table(console, table_lines(target, table, axis), title=f"time to the target test loss {target.loss:g}",
                 caption=f"target: {target.origin} ({target.why}). First evaluation at or below the target, no "
                         "interpolation; >budget: never reached (censored); a diverged seed never reaches it; "
                         "median over seeds, those seeds included")  # fmt: skip


def cmd_compare(args, console):
    from .config import split_methods

    methods = split_methods(args.methods) if args.methods else None
    if args.seeds < 1:
        raise UsageError("--seeds must be at least 1")
    out = output_dir(args.out if args.out is not None else f"studies/{args.problem}")
    settings = run_settings(args)
    from .study import split_grid

    if args.calibrate_only:
        budget = budget_of(args)
        if budget.kind != "seconds" or args.no_calibrate:
            raise UsageError("--calibrate-only needs a calibrated --seconds budget")
        if split_grid(settings)[1]:
            raise UsageError("--calibrate-only takes one study, not a sweep (a comma-separated --set value)")
        from .calibration import steps_for as calibration_steps
        from .study import calibrate_study

        calibration = calibrate_study(args.problem, methods, budget, out, settings=settings, echo=console.print,
                                      devices=args.devices)  # fmt: skip
        for method, stages in calibration.items():
            costs = ", ".join(f"{s.method} {1e3 * s.seconds:.4g} ms/step" for s in stages)
            console.print(f"{method}: {costs} -> {calibration_steps(float(budget.amount), stages)} steps for {budget}")
        console.print(f"wrote {Path(out) / 'calibration.json'}; nothing was trained")
        return 0
    if split_grid(settings)[1]:
        _run_grid(console, args.problem, methods, range(args.seeds), budget_of(args), settings, out, args.quiet,
                  args.devices, calibrate=not args.no_calibrate)  # fmt: skip
    else:
        from .tune_cli import executor_of  # --workers / --scheduler (harness/workers.py)

        with executor_of(args) as executor:
            _run_compare(console, args.problem, methods, range(args.seeds), budget_of(args), settings, out,
                         args.quiet, args.devices, calibrate=not args.no_calibrate, executor=executor)  # fmt: skip
    return 0


def _run_grid(console, problem, methods, seeds, budget, settings, out, quiet=False, devices="1", calibrate=True):
    """A sweep: ``--set a=1,2 --set b=x,y`` runs every cell of the grid as its own study."""
    from ..progress import RichProgressMeter
    from .study import compare_grid, grid_cells, grid_report, split_grid

    fixed, grid = split_grid(settings)
    console.print(
        f"sweeping {problem} over {' x '.join(f'{k} in {{{chr(44).join(v)}}}' for k, v in grid.items())} "
        f"({len(grid_cells(grid))} cells): budget {budget} per run, seeds {list(seeds)}, fixed settings {fixed or 'paper defaults'}"
    )
    meter = None if quiet or not console.is_terminal else RichProgressMeter
    compare_grid(problem, methods, seeds, budget, out, settings=settings, progress=meter, echo=console.print,
                 devices=devices, calibrate=calibrate)  # fmt: skip
    result = grid_report(out)
    _print_table(console, result.lines, title=f"{problem}: {budget} per run")
    _print_paired_tests(console, out)
    console.print(f"wrote {_files(Path(out) / 'grid_summary.csv', result.figure)}")


def _print_paired_tests(console, out):
    """Paired comparisons between the methods of a study or of each cell of a sweep, by seed
    (:func:`physgrad.harness.stats.paired_tests`)."""
    from .stats import MIN_SEEDS_P, format_tests, paired_tests

    out = Path(out)
    cells = (
        [(c.name, c) for c in sorted(out.iterdir()) if (c / "study.json").exists()]
        if (out / "grid.json").exists()
        else [("", out)]
    )
    lines = []
    for name, directory in cells:
        study = rundir.read_json(directory / "study.json", rundir.NOT_A_STUDY, empty={})
        rows = paired_tests(directory, order=study.get("methods"))
        table = format_tests(rows, cell=name or "")
        lines += table if not lines else table[1:]
    if len(lines) > 1:
        _print_table(console, lines, title="methods paired by seed",
                     caption=f"a diverged seed is the worse value; ratio: median of the per-seed ratios; "
                             f"two-sided Wilcoxon signed-rank test over seeds, from {MIN_SEEDS_P} seeds that differ "
                             "(below, its smallest p-value 2/2^n cannot reach 0.05)")  # fmt: skip


def cmd_report(args, console):
    from .study import grid_report, report

    if (Path(args.dir) / "tune.json").exists():  # a tune directory (harness/tune_report.py)
        from .tune_cli import report_command

        return report_command(args, console)
    if (Path(args.dir) / "bench.json").exists():  # a bench directory: every problem's table, the leaderboard
        from . import bench

        _print_bench(console, bench.report(args.dir))
        return 0
    if (Path(args.dir) / "grid.json").exists():
        result = grid_report(args.dir, panel=args.panel, metric=args.metric, split=args.split, smooth=args.smooth)
        _print_table(console, result.lines, title=str(args.dir))
        _print_paired_tests(console, args.dir)
        console.print(f"wrote {_files(Path(args.dir) / 'grid_summary.csv', result.figure)}")
        return 0
    from .seeds import table_note

    result = report(args.dir)
    _print_table(console, result.lines, title=str(args.dir), caption=table_note(result.table))
    _print_paired_tests(console, args.dir)
    _print_targets(console, args.dir)
    if result.figure:
        console.print(f"wrote {result.figure}")
    return 0


def cmd_bench(args, console):
    from . import bench
    from .config import Budget

    if args.seeds is not None and args.seeds < 1:
        raise UsageError("--seeds must be at least 1")
    if args.quick and args.standard:
        raise UsageError("give only one of --quick, --standard")
    name = "quick" if args.quick else "standard" if args.standard else ""
    settings = run_settings(args)
    given = any(getattr(args, k) is not None for k in ("steps", "epochs", "seconds"))
    if name:
        profile = bench.profile_choice(name)
        problems = bench.choose_problems(args.problems) if args.problems else list(profile["problems"])
        methods = bench.choose_methods(args.methods) if args.methods else list(profile["methods"])
        settings = {**bench.quick_settings(problems, methods, name), **settings}
        budget = budget_of(args) if given else Budget(seconds=profile["seconds"])
        budgets = {} if given else bench.profile_budgets(profile, problems)
        seeds = args.seeds or profile["seeds"]
    else:
        problems = bench.choose_problems(args.problems)
        methods = bench.choose_methods(args.methods)
        budget, seeds, budgets = budget_of(args), args.seeds or 1, {}
    out = output_dir(args.out if args.out is not None else (f"bench-{name}" if name else "bench"))
    calibrate = not args.no_calibrate and budget.kind == "seconds"
    console.print(
        f"bench{f' ({name} profile)' if name else ''}: {len(problems)} problems x {len(methods)} candidate methods, "
        f"budget {budget}{' (calibrated)' if calibrate else ''} per run"
        + "".join(f", {p} {b}" for p, b in budgets.items())
        + f", seeds {list(range(seeds))}, "
        f"settings {settings or 'paper defaults'} -> {out}"
    )
    if args.plan or args.calibrate_only:
        return _bench_plan(console, args, problems, methods, range(seeds), budget, settings, out, budgets)
    console.print("deciding which methods apply to which problem (from shapes; no data, no training)")
    from ..progress import RichProgressMeter

    meter = None if args.quiet or not console.is_terminal else RichProgressMeter
    from .tune_cli import executor_of  # --workers / --scheduler (harness/workers.py)

    with executor_of(args) as executor:
        result = bench.bench(problems, methods, range(seeds), budget, out, settings=settings, progress=meter,
                             echo=console.print, devices=args.devices, profile=name,
                             calibrate=not args.no_calibrate, budgets=budgets, executor=executor)  # fmt: skip
    _print_bench(console, result)
    return 0


def _print_bench(console, result) -> None:
    """A bench's tables per problem, its two leaderboards and the files written
    (:class:`physgrad.harness.bench.BenchReport`; the budgets and seeds from its bench.json)."""

    from . import bench
    from .config import Budget

    out = result.files["markdown"].parent
    info = rundir.read_json(out / "bench.json", rundir.NOT_A_STUDY)
    budget = Budget(**info["budget"])
    budgets = {p: Budget(**b) for p, b in info.get("budgets", {}).items()}
    seeds = len(info["seeds"])
    for problem in info["problems"]:
        table = result.tables[problem]
        _print_table(
            console,
            bench.table_lines(table, inapplicable=False),
            title=f"{problem}: {budgets.get(problem, budget)} per run",
        )
        for status in ("skipped", "not applicable"):
            names = [t["method"] for t in table if t["status"] == status]
            if names:
                console.print(f"  {status}: {', '.join(names)} (reasons in {out / problem / 'bench_table.md'})")
    plural = "s" if seeds != 1 else ""
    _print_table(console, result.profile_lines, title=f"leaderboard: performance profile of the time to target, "
                 f"{budget} per run, {seeds} seed{plural}",
                 caption="rho(tau): fraction of all problems within a factor tau of the fastest method's median "
                         "time to the problem's target test loss; geo-mean over the problems run (unsolved: 2x the "
                         "budget); profile.png draws rho(tau)")  # fmt: skip
    _print_table(console, result.lines, title=f"by final test loss: {budget} per run, {seeds} seed{plural}")
    files = _files(*(result.files[k] for k in ("markdown", "leaderboard", "profile", "table", "heatmap",
                                               "profile_figure")))  # fmt: skip
    console.print(f"wrote {files} and per problem {out}/PROBLEM/bench_table.csv")


def _bench_plan(console, args, problems, methods, seeds, budget, settings, out, budgets):
    """``--plan`` (and ``--calibrate-only``, which calibrates first): the runs per problem
    and their estimated time from the calibration (:mod:`physgrad.harness.bench.estimate`);
    nothing trains."""
    from . import bench
    from .bench.estimate import LOOP_SECONDS_PER_STEP, RUN_OVERHEAD_SECONDS, UNCALIBRATED_COMPILE_SECONDS, duration

    verdicts = bench.plan(problems, methods, settings, echo=console.print)
    if args.calibrate_only:
        if budget.kind != "seconds" or args.no_calibrate:
            raise UsageError("--calibrate-only needs a calibrated --seconds budget")
        bench.calibrate_only(problems, verdicts, budget, out, settings=settings, echo=console.print,
                             devices=args.devices, budgets=budgets)  # fmt: skip
    rows = bench.estimate(problems, verdicts, seeds, budget, out, budgets)
    _print_table(console, bench.plan_lines(rows), title=f"plan: {budget} per run, {len(seeds)} seeds -> {out}",
                 caption=f"a calibrated method: steps x (calibrated s/step + {1e6 * LOOP_SECONDS_PER_STEP:g} us of "
                         f"loop per step) + {RUN_OVERHEAD_SECONDS:g} s per run; not calibrated: its budget + "
                         f"{RUN_OVERHEAD_SECONDS:g} s per run and {UNCALIBRATED_COMPILE_SECONDS:g} s to calibrate it; "
                         "on an idle machine")  # fmt: skip
    uncalibrated = sum(r["methods"] - r["calibrated"] for r in rows)
    note = (f"; {uncalibrated} method(s) not calibrated yet (--calibrate-only times them)" if uncalibrated else
            "; every method calibrated")  # fmt: skip
    console.print(f"estimated total: {duration(bench.total_seconds(rows))} for {sum(r['runs'] for r in rows)} runs"
                  f"{note}; nothing was trained")  # fmt: skip
    return 0


def cmd_calibrate(args, console):
    """``physgrad calibrate``: the calibration phase of a study alone, as a table."""
    from .calibration import CSV_COLUMNS, EXTRA_COLUMNS, Calibration, calibrate, csv_rows, write_csv
    from .config import Budget, split_methods
    from .study import plan, read_csv

    methods = split_methods(args.methods) if args.methods else None
    if args.repeats is not None and args.repeats < 1:
        raise UsageError("--repeats must be at least 1")
    if args.max_seconds is not None and not args.max_seconds > 0:
        raise UsageError("--max-seconds must be positive")
    out = Path(args.out) if args.out else None
    if out is not None and (out.is_dir() or (out.suffix not in (".csv", ".json"))):
        raise UsageError(f"--out {str(out)!r} must be a .csv or .json file")
    configs = plan(args.problem, methods, [0], Budget(steps=1), run_settings(args))
    options = {k: v for k, v in (("repeats", args.repeats), ("max_seconds", args.max_seconds)) if v is not None}
    record = calibrate({c.method: c for c in configs}, devices=args.devices, echo=console.print, **options)
    command = (
        "physgrad " + " ".join(sys.argv[1:]) if sys.argv[1:2] == ["calibrate"] else f"physgrad calibrate {args.problem}"
    )
    rows = csv_rows(Calibration(record), command=command)
    lines = [["method", "stage", "route", "batch", "ms/step (median)", "quartiles", "min-max", "rounds", "compile s"]]
    for r in rows:
        lines.append([r["spec"], str(r["stage"]), r["route"], str(r["batch"]), r["ms_per_step"],
                      f"{r['ms_q25']}-{r['ms_q75']}", f"{r['ms_min']}-{r['ms_max']}", str(r["rounds"]),
                      r["compile_seconds"]])  # fmt: skip
    _print_table(console, lines, title=f"{args.problem}: calibrated step times ({rows[0]['machine'] if rows else ''})")
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        if out.suffix == ".json":
            rundir.atomic_write(
                out, json.dumps(record, indent=2, default=str) + "\n"
            )  # the old record stays on a failed write
        else:
            if args.append and out.exists():
                rows = [*read_csv(out), *rows]
            write_csv(out, rows)
        console.print(f"wrote {out} ({', '.join(CSV_COLUMNS)}, then {', '.join(EXTRA_COLUMNS)})"
                      if out.suffix == ".csv" else f"wrote {out}")  # fmt: skip
    return 0


def cmd_demo(args, console):
    from .config import Budget

    console.print(
        "physgrad demo: the HIG paper's nonlinear oscillators (Fig. 2b) on this machine.\n"
        f"  adam: paper settings (lr 3e-4, batch 512); gn, hig: eta 1, truncation 1e-6, batch 32 (PBDL book) "
        f"instead of the paper's 128, because a 512x512 eigendecomposition dominates a batch-128 step on a few CPU cores.\n"
        f"  {args.seconds:g} s of training per method and seed, {DEMO['seeds']} seeds, full test loss every 64 steps; "
        f"settings {DEMO['settings']}\n"
        f"  The seeds are the replicates: {DEMO['seeds']} seeds give medians with 95% bootstrap intervals over seeds "
        "but no p-values (a Wilcoxon test over seeds needs 6: physgrad compare oscillators --seeds 6)."
    )
    result = _run_compare(
        console,
        DEMO["problem"],
        DEMO["methods"],
        range(DEMO["seeds"]),
        Budget(seconds=args.seconds),
        DEMO["settings"],
        args.out,
    )
    from .seeds import interval

    ratio = result.ratio("adam", "hig")  # Adam's final test loss over HIG's, per seed
    r, seeds = ratio["median"], f"median over {ratio['n']} seed{'s' if ratio['n'] != 1 else ''} of the per-seed ratio"
    spread = f"95% CI {interval(ratio, '.3g')}"
    if ratio["n"] == 0 or math.isnan(r):
        console.print("No HIG/Adam ratio: the two have no seed in common (see the table).")
    elif math.isinf(r):
        console.print(f"Adam diverged on at least half the seeds where HIG did not ({seeds}: ∞; see the table).")
    elif r == 0:
        console.print(f"HIG diverged on at least half the seeds where Adam did not ({seeds}: 0; see the table).")
    elif r >= 1:
        console.print(f"HIG's final test loss is {r:.1f}x below Adam's at equal calibrated time ({seeds}; {spread}).",
                      markup=False)  # fmt: skip
    else:
        console.print(f"HIG's final test loss is {1 / r:.1f}x above Adam's at equal calibrated time ({seeds}; {spread}).",
                      markup=False)  # fmt: skip
    return 0


def _one_line_warnings(err: Console, show):
    """``warnings.showwarning`` that prints a :class:`~physgrad.harness.plots.FigureWarning` as one
    ``physgrad: warning:`` line (and leaves every other warning to ``show``)."""
    from .plots import FigureWarning

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, FigureWarning):
            err.print(f"physgrad: warning: {message}", markup=False, highlight=False, soft_wrap=True)
        else:
            show(message, category, filename, lineno, file, line)

    return showwarning


def _damaged_files_as_one_line(command, args, console):
    """``report`` reads files it did not write (a copy, a foreign directory, a truncated
    ``.gz``): what cannot be parsed is one line naming the directory, not a traceback."""
    import csv
    import gzip
    import zlib

    try:
        return command(args, console)
    except (
        EOFError,
        gzip.BadGzipFile,
        zlib.error,
        csv.Error,
        UnicodeDecodeError,
        KeyError,
        ValueError,
        TypeError,
    ) as e:
        from ..errors import ConfigError

        raise ConfigError(f"{args.dir}: a file cannot be read ({type(e).__name__}: {str(e)[:80]}); "
                          f"{rundir.NOT_A_STUDY}") from None  # fmt: skip


def cmd_tune(args, console):  # physgrad tune: harness/tune_cli.py
    from .tune_cli import tune_command

    return tune_command(args, console)


COMMANDS = {
    "list": cmd_list,
    "train": cmd_train,
    "compare": cmd_compare,
    "report": lambda args, console: _damaged_files_as_one_line(cmd_report, args, console),
    "bench": cmd_bench,
    "calibrate": cmd_calibrate,
    "demo": cmd_demo,
    "tune": cmd_tune,
}


def main(argv=None) -> int:
    # JAX's configuration is left as the user set it (x64 off by default), as physgrad.fit
    # leaves it: a run from the command line and the same run through fit are one computation
    # (fit scopes float64 to the problems that declare needs_float64).
    from ..cpu import process_threads
    from .config import ConfigError

    # Outside a terminal (CI, pipes) rich would wrap at 80 columns; tables need more.
    console = Console(soft_wrap=True)
    if not console.is_terminal:
        console = Console(soft_wrap=True, width=140)
    err = Console(stderr=True)
    try:
        args = build_parser().parse_args(argv)
        if args.command is None:
            build_parser().print_help()
            return 2
        cache = getattr(args, "compilation_cache", None) or os.environ.get("PHYSGRAD_COMPILATION_CACHE")
        if cache and args.command != "list":
            from ..programs import use_compilation_cache

            use_compilation_cache(cache)
        # The thread pools for the command (physgrad.cpu): set before the first JAX
        # computation, so that XLA's pool is sized too; restored when the command returns.
        threads = process_threads(threads_of(args)) if hasattr(args, "threads") else contextlib.nullcontext()
        # SIGTERM stops every command as Ctrl-C does (a study's calibration too): locks released, one line
        with warnings.catch_warnings(), threads, rundir.terminate_as_interrupt():
            warnings.showwarning = _one_line_warnings(err, warnings.showwarning)
            return COMMANDS[args.command](args, console)
    except (UsageError, ConfigError) as e:  # the library's line in the command line's words where it has them
        err.print(f"physgrad: error: {command_line_words(e)}", markup=False, highlight=False, soft_wrap=True)
        return 2
    except OSError as e:  # a full disk, a read-only file system, a permission, a name too long: one line
        err.print(f"physgrad: error: {os_error_line(e)}", markup=False, highlight=False, soft_wrap=True)
        return 1
    except MemoryError:
        err.print("physgrad: error: out of memory; reduce the data (n_train, n_test) or the batch size",
                  markup=False, highlight=False, soft_wrap=True)  # fmt: skip
        return 1
    except Exception as e:
        # XLA's out of memory (RESOURCE_EXHAUSTED, or INTERNAL "Out of memory allocating N bytes" on a CPU;
        # its exception type varies by version)
        if "RESOURCE_EXHAUSTED" not in str(e) and "Out of memory" not in str(e):
            raise
        err.print("physgrad: error: the accelerator or host ran out of memory; reduce the data (n_train, n_test) "
                  "or the batch size", markup=False, highlight=False, soft_wrap=True)  # fmt: skip
        return 1
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (rundir.Terminated): runs checkpoint first
        from ..rundir import Terminated

        err.print(
            f"physgrad: {'terminated' if isinstance(e, Terminated) else 'interrupted'}; finished runs are kept, "
            "run the same command (train: with --resume) to continue",
            soft_wrap=True,
        )
        return 143 if isinstance(e, Terminated) else 130


def os_error_line(e: OSError) -> str:
    """An OS error at the edge as one line naming the file (the file physgrad was writing,
    not its temporary copy) and what to do; the run directory stays resumable."""
    import re

    name = str(e.filename or "")
    name = re.sub(r"/\.([^/]+)\.\d+\.tmp(\.npz)?$", r"/\1", name)  # rundir.atomic_file's temporary name
    why = e.strerror or type(e).__name__
    advice = {
        errno.ENOSPC: "free some space, then run the same command (train: with --resume) to continue",
        errno.EFBIG: "the file size limit (ulimit -f) was reached; raise it, then run the same command again",
        errno.EROFS: "the file system is read-only; choose a writable --out",
        errno.EACCES: "check the permissions, or choose another --out",
        errno.EPERM: "check the permissions, or choose another --out",
        errno.ENAMETOOLONG: "choose a shorter --out (a name has at most 255 bytes)",
    }.get(e.errno or 0, "finished runs are kept; run the same command again once it is fixed")
    return f"{name}: {why}; {advice}" if name else f"{why}; {advice}"


if __name__ == "__main__":
    sys.exit(main())
