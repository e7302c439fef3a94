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
import os
import sys
import warnings
from pathlib import Path

from rich.console import Console

from ..errors import ConfigError
from .arguments import DEMO, UsageError, build_parser, output_dir, threads_of
from .words import command_line_words

# Only the parser and what every command needs are imported here: ``physgrad --version`` and
# ``physgrad --help`` answer without importing JAX (tests/test_startup.py checks it); each
# command imports its body, which imports the library.


def cmd_list(args, console):
    from ..extras import method_extra, missing_note
    from .papers import protocol
    from .plugins import PluginWarning
    from .registry import METHODS, PROBLEMS, describe

    with warnings.catch_warnings():  # the plugins left out are listed at the end, not warned about too
        warnings.simplefilter("ignore", PluginWarning)
        PROBLEMS.load_plugins()
        METHODS.load_plugins()
    console.print("[bold]problems[/bold]")
    for name, cls in PROBLEMS.items():
        note = missing_note(cls.extra)  # a problem whose optional extra is not installed
        paper = protocol(name)
        # a plugin's problem (physgrad.harness.plugins): its docstring's first line and its package
        text = paper.description if name in PROBLEMS.builtin else _plugin_line(cls)
        console.print(f"  {name:<19} {text}" + (f" {note}" if note else ""), markup=False)
        console.print(f"  {'':<19} paper comparison: {', '.join(paper.methods)}", markup=False)
        if paper.target is not None:
            console.print(f"  {'':<19} target test loss: {paper.target.loss:g} ({paper.target.origin})", markup=False)
    console.print("[bold]methods[/bold]")
    for name in METHODS:
        note = missing_note(method_extra(name))
        plugin = "" if name in METHODS.builtin else f" (plugin: {_plugin_module(METHODS[name])})"
        console.print(f"  {name:<19} {describe(name)}{plugin}" + (f" {note}" if note else ""), markup=False)
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
    console.print("[bold]your own[/bold] (docs/own-problem.md)")
    console.print("  a problem or method by import path: physgrad train mypkg.problems:MyProblem --method mypkg.rules:my_rule",
                  markup=False)  # fmt: skip
    console.print("  an installed package's entry points (groups physgrad.problems, physgrad.methods) add names above",
                  markup=False)  # fmt: skip
    left_out = {**PROBLEMS.left_out, **METHODS.left_out}
    if left_out:
        console.print("[bold]plugins left out[/bold]")
        for line in left_out.values():
            console.print(f"  {line}", markup=False)
    return 0


def _plugin_module(value) -> str:
    return getattr(value, "__module__", None) or "?"


def _plugin_line(cls) -> str:
    """A plugin problem's line in ``physgrad list``: its docstring's first line, its module."""
    doc = (cls.__doc__ or "").strip().splitlines()
    return (f"{doc[0]} " if doc else "") + f"(plugin: {_plugin_module(cls)})"


def _progress(args, console):
    from ..engine.progress import NoProgressMeter, RichProgressMeter

    return NoProgressMeter() if args.quiet or not console.is_terminal else RichProgressMeter()


def _start_processes(args) -> str:
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
    from .config import make_config, method_slug, problem_slug
    from .console import describe_run
    from .options import TrainOptions
    from .train import read_summary, train

    options = TrainOptions.from_args(args, devices=args.devices)  # main() joined the processes
    devices = options.devices
    config = make_config(options.problem, options.method, budget=options.budget, seed=options.seed,
                         settings=options.settings)  # fmt: skip
    out = output_dir(
        options.out
        if options.out is not None
        else f"runs/{problem_slug(options.problem)}-{method_slug(options.method)}-seed{options.seed}"
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
    before = read_summary(out) if options.resume else None
    from ..engine.recording import kept_path
    from ..engine.resume import FINAL_FILES

    missing = [name for name in FINAL_FILES if not kept_path(out / name).exists()]
    summary = train(config, out, resume=options.resume, progress=_progress(options, console), devices=devices)
    if before is not None and summary == before and missing:  # a finished run's deleted files, made again
        console.print(f"done already ({summary['status']}): {describe_run(summary)}; made again from its final "
                      f"checkpoint: {', '.join(missing)}")  # fmt: skip
    elif before is not None and summary == before:  # a resume with nothing to do leaves every file as it was
        console.print(f"done already ({summary['status']}): {describe_run(summary)}; every file unchanged")
    else:
        console.print(f"{summary['status']}: {describe_run(summary)}")
    return 0


def cmd_compare(args, console):
    from .options import StudyOptions
    from .study import split_grid
    from .study.console import calibrate_only, run_compare, run_grid

    options = StudyOptions.from_args(args)
    if options.calibrate_only:
        return calibrate_only(console, options)
    if split_grid(options.settings)[1]:
        run_grid(console, options)
    else:
        from .tune_cli import executor_of  # --workers / --scheduler (harness/workers.py)

        with executor_of(options) as executor:
            run_compare(console, options, executor=executor)
    return 0


def cmd_report(args, console):
    from .options import ReportOptions

    options = ReportOptions.from_args(args)
    if (Path(options.dir) / "tune.json").exists():  # a tune directory (harness/tune_report.py)
        from .tune_cli import report_command

        return report_command(options, console)
    if (Path(options.dir) / "bench.json").exists():  # a bench directory: every problem's table, the leaderboard
        import json

        from . import bench
        from .bench.console import print_bench

        info = json.loads((Path(options.dir) / "bench.json").read_text())
        if isinstance(info, dict) and info.get("tuned"):  # bench --tuned (a foreign file: bench.report's line)
            from .bench.console import print_tuned
            from .bench.tuned_report import tuned_report

            print_tuned(console, tuned_report(options.dir))
            return 0

        print_bench(console, bench.report(options.dir))
        return 0
    from .study.console import print_report

    return print_report(console, options)


def cmd_bench(args, console):
    from .bench.console import bench_command
    from .options import BenchOptions

    return bench_command(console, BenchOptions.from_args(args))


def cmd_calibrate(args, console):
    """``physgrad calibrate``: the calibration phase of a study alone, as a table."""
    from .options import CalibrateOptions
    from .study.console import calibrate_command

    return calibrate_command(console, CalibrateOptions.from_args(args))


def cmd_demo(args, console):
    from .options import StudyOptions
    from .study.console import print_demo_verdict, run_compare

    console.print(
        "physgrad demo: the HIG paper's nonlinear oscillators (Fig. 2b) on this machine.\n"
        f"  adam: paper settings (lr 3e-4, batch 512); gn, hig: eta 1, truncation 1e-6, batch 32 (PBDL book) "
        f"instead of the paper's 128, because a 512x512 eigendecomposition dominates a batch-128 step on a few CPU cores.\n"
        f"  {args.seconds:g} s of training per method and seed, {DEMO['seeds']} seeds, full test loss every 64 steps; "
        f"settings {DEMO['settings']}\n"
        f"  The seeds are the replicates: {DEMO['seeds']} seeds give medians with 95% bootstrap intervals over seeds "
        "but no p-values (a Wilcoxon test over seeds needs 6: physgrad compare oscillators --seeds 6)."
    )
    result = run_compare(console, StudyOptions.demo(args.seconds, args.out))
    print_demo_verdict(console, result)
    return 0


def _one_line_warnings(err: Console, show):
    """``warnings.showwarning`` that prints a :class:`~physgrad.harness.plots.FigureWarning` or a
    :class:`~physgrad.harness.plugins.PluginWarning` as one ``physgrad: warning:`` line (and leaves
    every other warning to ``show``)."""
    from .plots import FigureWarning
    from .plugins import PluginWarning

    def showwarning(message, category, filename, lineno, file=None, line=None):
        if issubclass(category, (FigureWarning, PluginWarning)):
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

    from ..engine import rundir

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
            from ..engine.programs import use_compilation_cache

            use_compilation_cache(cache)
        # A multi-process run joins before anything starts JAX's backend (jax.distributed
        # refuses afterwards), and so before the thread setting below, which starts it.
        if hasattr(args, "coordinator"):
            args.devices = _start_processes(args)
        # The thread pools for the command (physgrad.cpu): set before the first JAX
        # computation, so that XLA's pool is sized too; restored when the command returns.
        from ..cpu import process_threads

        threads = process_threads(threads_of(args)) if hasattr(args, "threads") else contextlib.nullcontext()
        # SIGTERM stops every command as Ctrl-C does (a study's calibration too): locks released, one line
        from ..engine import rundir  # here, not at the top: the engine package imports JAX

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
        from ..engine.rundir import Terminated

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
