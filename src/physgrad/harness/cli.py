"""The ``physgrad`` command line: a thin layer over :mod:`physgrad.harness.train` and :mod:`physgrad.harness.study`.

    physgrad list
    physgrad train PROBLEM --method M|M1:N,M2 [--seconds S | --steps N | --epochs E] [--seed K]
                   [--set name=value ...] [--out DIR] [--resume] [--devices N|all]
                   [--coordinator HOST:PORT --num-processes P --process-id I]
    physgrad compare PROBLEM [--methods a,b,...] [--seeds N] [budget] [--set ...] [--out DIR] [--devices N]
                     (--set name=a,b,c sweeps: every cell of the grid is a study)
    physgrad report DIR
    physgrad bench [--problems p1,p2|all] [--methods m1,m2|applicable] [--seeds N] [budget] [--out DIR]
                   [--quick] [--set ...]   (every applicable method on every problem, ranked; physgrad.harness.bench)
    physgrad demo

train, compare, bench and demo take --threads N|default (default 1: physgrad.cpu.process_threads).
Bad input (an unknown problem, method or setting) prints one line with the valid choices
and exits with status 2.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import sys
import warnings
from pathlib import Path

from rich.console import Console
from rich.table import Table
from rich.text import Text

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
    out = output_dir(args.out or f"runs/{args.problem}-{method_slug(args.method)}-seed{args.seed}")
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
    summary = train(config, out, resume=args.resume, progress=_progress(args, console), devices=devices)
    if before is not None and summary == before:  # a resume with nothing to do leaves every file as it was
        console.print(f"done already ({summary['status']}): {describe_run(summary)}; every file unchanged")
    else:
        console.print(f"{summary['status']}: {describe_run(summary)}")
    return 0


def _run_compare(console, problem, methods, seeds, budget, settings, out, quiet=False, devices="1"):
    from ..progress import RichProgressMeter
    from .study import compare, plan, report

    plan(problem, methods, seeds, budget, settings)  # validate every name before anything runs
    console.print(
        f"comparing on {problem}: budget {budget} per run, seeds {list(seeds)}, settings {settings or 'paper defaults'}"
    )
    meter = None if quiet or not console.is_terminal else RichProgressMeter
    compare(
        problem, methods, seeds, budget, out, settings=settings, progress=meter, echo=console.print, devices=devices
    )
    from .seeds import TABLE_NOTE

    result = report(out)
    _print_table(console, result.lines, title=f"{problem}: {budget} per run", caption=TABLE_NOTE)
    _print_paired_tests(console, out)
    console.print(f"wrote {_files(Path(out) / 'results.csv', Path(out) / 'summary.csv', result.figure)}")
    return result


def cmd_compare(args, console):
    from .config import split_methods

    methods = split_methods(args.methods) if args.methods else None
    if args.seeds < 1:
        raise UsageError("--seeds must be at least 1")
    out = output_dir(args.out or f"studies/{args.problem}")
    settings = run_settings(args)
    from .study import split_grid

    if split_grid(settings)[1]:
        _run_grid(
            console, args.problem, methods, range(args.seeds), budget_of(args), settings, out, args.quiet, args.devices
        )
    else:
        _run_compare(console, args.problem, methods, range(args.seeds), budget_of(args), settings, out, args.quiet,
                     args.devices)  # fmt: skip
    return 0


def _run_grid(console, problem, methods, seeds, budget, settings, out, quiet=False, devices="1"):
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
                 devices=devices)  # fmt: skip
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
        study = json.loads((directory / "study.json").read_text()) if (directory / "study.json").exists() else {}
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

    if (Path(args.dir) / "grid.json").exists():
        result = grid_report(args.dir, panel=args.panel, metric=args.metric, split=args.split, smooth=args.smooth)
        _print_table(console, result.lines, title=str(args.dir))
        _print_paired_tests(console, args.dir)
        console.print(f"wrote {_files(Path(args.dir) / 'grid_summary.csv', result.figure)}")
        return 0
    from .seeds import TABLE_NOTE

    result = report(args.dir)
    _print_table(console, result.lines, title=str(args.dir), caption=TABLE_NOTE)
    _print_paired_tests(console, args.dir)
    if result.figure:
        console.print(f"wrote {result.figure}")
    return 0


def cmd_bench(args, console):
    from . import bench
    from .config import Budget

    if args.seeds is not None and args.seeds < 1:
        raise UsageError("--seeds must be at least 1")
    settings = run_settings(args)
    given = any(getattr(args, k) is not None for k in ("steps", "epochs", "seconds"))
    if args.quick:
        problems = bench.choose_problems(args.problems) if args.problems else list(bench.QUICK["problems"])
        methods = bench.choose_methods(args.methods) if args.methods else list(bench.QUICK["methods"])
        settings = {**bench.quick_settings(problems, methods), **settings}
        budget = budget_of(args) if given else Budget(seconds=bench.QUICK["seconds"])
        seeds = args.seeds or bench.QUICK["seeds"]
    else:
        problems = bench.choose_problems(args.problems)
        methods = bench.choose_methods(args.methods)
        budget, seeds = budget_of(args), args.seeds or 1
    out = output_dir(args.out or ("bench-quick" if args.quick else "bench"))
    console.print(
        f"bench{' (quick profile)' if args.quick else ''}: {len(problems)} problems x {len(methods)} candidate methods, "
        f"budget {budget} per run, seeds {list(range(seeds))}, settings {settings or 'paper defaults'} -> {out}"
    )
    console.print("deciding which methods apply to which problem (from shapes; no data, no training)")
    from ..progress import RichProgressMeter

    meter = None if args.quiet or not console.is_terminal else RichProgressMeter
    result = bench.bench(problems, methods, range(seeds), budget, out, settings=settings, progress=meter,
                         echo=console.print, devices=args.devices, profile="quick" if args.quick else "")  # fmt: skip
    for problem in problems:
        table = result.tables[problem]
        _print_table(console, bench.table_lines(table, inapplicable=False), title=f"{problem}: {budget} per run")
        for status in ("skipped", "not applicable"):
            names = [t["method"] for t in table if t["status"] == status]
            if names:
                console.print(f"  {status}: {', '.join(names)} (reasons in {out / problem / 'bench_table.md'})")
    _print_table(console, result.lines, title=f"leaderboard: {budget} per run, {seeds} seed{'s' if seeds != 1 else ''}")
    files = _files(*(result.files[k] for k in ("markdown", "leaderboard", "table", "heatmap")))
    console.print(f"wrote {files} and per problem {out}/PROBLEM/bench_table.csv")
    return 0


def cmd_demo(args, console):
    from .config import Budget

    console.print(
        "physgrad demo: the HIG paper's nonlinear oscillators (Fig. 2b) on this machine.\n"
        f"  adam: paper settings (lr 3e-4, batch 512); gn, hig: eta 1, truncation 1e-6, batch 32 (PBDL book) "
        f"instead of the paper's 128, because a 512x512 eigendecomposition dominates a batch-128 step on a few CPU cores.\n"
        f"  {args.seconds:g} s of training per method and seed, {DEMO['seeds']} seeds, full test loss every 64 steps; "
        f"settings {DEMO['settings']}\n"
        f"  The seeds are the replicates: with {DEMO['seeds']} seeds the table gives medians without intervals and no "
        "p-values (an interval needs 3 seeds, a Wilcoxon test over seeds 6: physgrad compare oscillators --seeds 6)."
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
        console.print(f"HIG's final test loss is {r:.1f}x below Adam's at equal wall-clock ({seeds}; {spread}).",
                      markup=False)  # fmt: skip
    else:
        console.print(f"HIG's final test loss is {1 / r:.1f}x above Adam's at equal wall-clock ({seeds}; {spread}).",
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


COMMANDS = {
    "list": cmd_list,
    "train": cmd_train,
    "compare": cmd_compare,
    "report": cmd_report,
    "bench": cmd_bench,
    "demo": cmd_demo,
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
        with warnings.catch_warnings(), threads:  # a figure that cannot be drawn: one line, the tables stand
            warnings.showwarning = _one_line_warnings(err, warnings.showwarning)
            return COMMANDS[args.command](args, console)
    except (UsageError, ConfigError) as e:  # the library's line in the command line's words where it has them
        err.print(f"physgrad: error: {command_line_words(str(e))}", markup=False, highlight=False, soft_wrap=True)
        return 2
    except KeyboardInterrupt as e:  # Ctrl-C, or SIGTERM (rundir.Terminated): runs checkpoint first
        from ..rundir import Terminated

        err.print(
            f"physgrad: {'terminated' if isinstance(e, Terminated) else 'interrupted'}; finished runs are kept, "
            "run the same command (train: with --resume) to continue",
            soft_wrap=True,
        )
        return 143 if isinstance(e, Terminated) else 130


if __name__ == "__main__":
    sys.exit(main())
