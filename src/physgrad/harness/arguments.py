"""The command line's arguments: the parser (one-line errors, exit 2), the budget, settings
and output-directory flags, and the demo's fixed study (:mod:`physgrad.harness.cli` runs them)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

DEFAULT_SECONDS = 60.0

# `make demo`: adam, gn and hig on the oscillators on 2 CPU cores in about two minutes.
# Adam keeps the paper's settings (lr 3e-4, batch 512). GN and HIG use the PBDL book's
# batch of 32 instead of the paper's 128: on 2 cores a step at 128 is dominated by a
# 512×512 eigendecomposition (~13× the cost of a step at 32, benchmarks/hig_step.py),
# so batch 32 makes far more progress per second. HIG's lead is largest early on (at 120 s
# and the paper's batch sizes it is ~7x on 2 cores), so the demo trains 20 s of calibrated
# time per run, 3 seeds: the fewest that give the headline ratio a bootstrap interval.
DEMO = {
    "problem": "oscillators",
    "methods": ["adam", "gn", "hig"],
    "seconds": 20.0,
    "seeds": 3,
    "settings": {"gn.batch_size": "32", "hig.batch_size": "32", "eval_every": "64"},
}


# The bench profiles' one-line summaries (physgrad.harness.bench.choices.PROFILES), for --help
# without importing the registries.
QUICK_SUMMARY = ("6 fast open-loop problems, 10 candidates, small datasets, 6 s of calibrated training per run "
                 "(0.5-2 s on the 4 problems with sub-millisecond steps), 3 seeds (planned for at most 45 min on "
                 "2 CPU cores)")  # fmt: skip
STANDARD_SUMMARY = ("every problem that fits a CPU at its paper settings and batch sizes, every applicable method, "
                    "5 min of calibrated training per run (5-20 s on the 4 problems with sub-millisecond steps), 5 seeds "
                    "(a resumable long study: days on 2 CPU cores)")  # fmt: skip


class UsageError(Exception):
    pass


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (exit 2, no usage dump, no traceback)."""

    def error(self, message):
        raise UsageError(message)


def budget_of(args):
    from .config import Budget

    given: dict[str, Any] = {
        k: getattr(args, k) for k in ("steps", "epochs", "seconds") if getattr(args, k) is not None
    }
    if not given:
        given = {"seconds": DEFAULT_SECONDS}
    if len(given) > 1:
        raise UsageError("give only one of --steps, --epochs, --seconds")
    return Budget.of(given)


def run_settings(args):
    """--set pairs plus the --no-network flag."""
    settings = _settings(args.set)
    if getattr(args, "no_network", False):
        settings["no_network"] = True
    cap = getattr(args, "wall_cap", None)
    if cap is not None:
        if not cap > 0:
            raise UsageError(f"--wall-cap expects a positive number of seconds, got {cap!r}")
        settings["wall_cap"] = str(cap)
    return settings


MAX_SEED = 2**63 - 1  # jax.random.key takes a signed 64-bit integer
MAX_SEEDS = 10_000  # a study's seeds are planned as a list of runs: more is a typo, not a study


def _integer(text: str, low: int, high: int, what: str) -> int:
    """An integer argument in [low, high] (argparse's one-line error otherwise)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expects an integer, got {text!r}") from None
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"expects {what}, got {text}")
    return value


def seed_number(text: str) -> int:
    """``--seed``: an integer in [0, 2**63 - 1]."""
    return _integer(text, 0, MAX_SEED, "an integer from 0 to 2**63 - 1")


def seed_count(text: str) -> int:
    """``--seeds``: how many seeds (0..N-1), at most :data:`MAX_SEEDS` (fewer than 1 is
    refused where the seeds are planned, in the commands' own words)."""
    return _integer(text, -(2**63), MAX_SEEDS, f"a number of seeds up to {MAX_SEEDS:,}")


def output_dir(path) -> Path:
    """``--out``, refused in one line if it names a file or cannot be written (before any work)."""
    from ..checks import check_directory
    from .config import ConfigError

    try:
        return check_directory(path, "--out")
    except ConfigError as e:
        raise UsageError(str(e)) from None


def _settings(pairs):
    settings = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or not name:
            raise UsageError(f"--set expects name=value, got {pair!r}")
        if name.strip() in settings:  # the last one winning silently hides a typo
            raise UsageError(f"--set {name.strip()} is given twice ({settings[name.strip()]!r} and {value.strip()!r}); "
                             "give it once (a comma-separated value sweeps it)")  # fmt: skip
        settings[name.strip()] = value.strip()
    return settings


def _add_budget(p, calibrated: bool = False):
    g = p.add_argument_group("budget (one of; default --seconds 60)")
    if calibrated:
        g.add_argument("--seconds", type=float,
                       help="calibrated training seconds per run: each method's compiled step is timed first "
                            "(calibration.json in the study) and its runs train for seconds / (its seconds per step) "
                            "steps; curves and time-to-target use step x calibrated seconds per step")  # fmt: skip
    else:
        g.add_argument("--seconds", type=float, help="training wall-clock seconds (evaluation excluded)")
    g.add_argument("--steps", type=int, help="training steps")
    g.add_argument("--epochs", type=int, help="epochs over the training set")
    if calibrated:
        g.add_argument("--wall-cap", type=float, metavar="SECONDS",
                       help="also stop a run once its training wall-clock reaches SECONDS (a cap beside the "
                            "calibrated or steps budget, e.g. on a loaded machine; the run is recorded as wall_capped "
                            "and its time-to-target as censored; a larger cap later resumes it)")  # fmt: skip
        g.add_argument("--no-calibrate", action="store_true",
                       help="--seconds is training wall-clock instead (no calibration: the budget then depends on "
                            "the machine's load)")  # fmt: skip
    p.add_argument(
        "--no-network",
        action="store_true",
        help="direct optimisation: optimise x itself for each test sample (no network)",
    )
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a problem setting, method hyperparameter or training setting; repeatable")  # fmt: skip
    _add_compilation_cache(p)
    _add_threads(p)


# The command line's thread setting (physgrad.cpu.process_threads): one thread per pool by
# default, so that a study's timings do not depend on what else runs on the machine.
DEFAULT_THREADS = "1"


def threads_of(args) -> int | None:
    """``--threads`` (default ``$PHYSGRAD_THREADS``, else 1) as a count; None for ``default``
    (every pool at its library's default); no ``--threads`` for this command: None."""
    import os

    if not hasattr(args, "threads"):
        return None
    text = str(args.threads or os.environ.get("PHYSGRAD_THREADS") or DEFAULT_THREADS).strip()
    if text == "default":
        return None
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise UsageError(f"--threads expects a positive integer or 'default', got {text!r}")
    return n


def _add_threads(p):
    p.add_argument("--threads", metavar="N|default", default=None,
                   help="threads of the BLAS/LAPACK, OpenMP and XLA CPU pools (default $PHYSGRAD_THREADS, else 1: "
                        "timings that do not depend on the machine's load; 'default': the libraries' own, usually "
                        "one per core). Recorded in each run's env.json")  # fmt: skip


def _add_compilation_cache(p):
    p.add_argument("--compilation-cache", metavar="DIR", default=None,
                   help="keep compiled steps in JAX's persistent cache in DIR, so that a repeated study or a "
                        "resumed run does not compile them again (default: $PHYSGRAD_COMPILATION_CACHE, else off)")  # fmt: skip


def _add_workers(p, default: str):
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help=f"runs in parallel on N Dask worker processes of one thread each, an in-process LocalCluster "
                        f"(default {default}, or $PHYSGRAD_WORKERS; 1 where JAX has an accelerator; 1: one after the "
                        "other in this process); the numbers do not change")  # fmt: skip
    p.add_argument("--scheduler", metavar="tcp://HOST:8786",
                   help="send the runs to a running Dask scheduler instead (its workers need physgrad and the "
                        "output directory)")  # fmt: skip


def build_parser() -> Parser:
    parser = Parser(
        prog="physgrad", description="Train networks through physics simulators with improved update rules."
    )
    from .. import __version__

    parser.add_argument("--version", action="version", version=f"physgrad {__version__}")
    sub = parser.add_subparsers(dest="command", parser_class=Parser)
    sub.add_parser("list", help="problems and methods")

    p = sub.add_parser("train", help="train one method on one problem")
    p.add_argument("problem", help="a problem of physgrad list, or your own by import path: module:Class")
    p.add_argument(
        "--method", required=True, help="a method, or a sequence such as adam:2000,hig (Adam for 2000 steps, then HIG)"
    )
    p.add_argument("--seed", type=seed_number, default=0)
    p.add_argument("--out", help="run directory (default runs/PROBLEM-METHOD-seedK)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    g = p.add_argument_group(
        "devices and hosts (data parallel: the batch is split, the update is the single-device one)"
    )
    g.add_argument(
        "--devices",
        default=None,
        metavar="N|all",
        help="devices to split each batch over (default 1; all of them in a multi-process run)",
    )
    g.add_argument(
        "--coordinator", metavar="HOST:PORT", help="multi-process run: address of process 0 (jax.distributed)"
    )
    g.add_argument("--num-processes", type=int, metavar="P", help="multi-process run: number of processes")
    g.add_argument("--process-id", type=int, metavar="I", help="multi-process run: this process's index 0..P-1")
    _add_budget(p)

    p = sub.add_parser("compare", help="every method x seed on the same budget; table and figure")
    p.add_argument("problem")
    p.add_argument(
        "--methods", help="comma-separated, sequences allowed: adam,hig,adam:2000,hig (default: the paper's comparison)"
    )
    p.add_argument("--seeds", type=seed_count, default=1, help="number of seeds 0..N-1 (default 1)")
    p.add_argument("--devices", default="1", metavar="N|all", help="devices to split each batch over (default 1)")
    p.add_argument("--out", help="study directory (default studies/PROBLEM)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--calibrate-only", action="store_true",
                   help="time each method's step into --out (calibration.json) and train nothing: run it on a quiet "
                        "machine, then the same command without it trains with those step counts under any load")  # fmt: skip
    _add_workers(p, "the machine's cores")
    _add_budget(p, calibrated=True)

    p = sub.add_parser(
        "tune", help="tune each method on equal trials (Optuna), choose on validation, report on test",
        description="Tune each method's declared search space (physgrad.harness.spaces: lr for every method; "
                    "truncation, damping, SIP's eta, the clip threshold) with the same number of quasi-random "
                    "trials (QMC, Optuna), each an ordinary run on the same calibrated budget, trained and selected on "
                    "validation data (the problem's val split, else a held-out part of train); the chosen "
                    "configuration is re-run on --seeds seeds and reported on test. Resumable: the same command "
                    "again keeps finished trials and resumes interrupted ones.",
    )  # fmt: skip
    p.add_argument("problem")
    p.add_argument("--methods", help="comma-separated methods (default: the paper's comparison)")
    p.add_argument("--trials", type=int, default=5, help="trials per method (default 5, AlgoPerf's); trial 0 is "
                                                         "the untuned configuration")  # fmt: skip
    p.add_argument("--seeds", type=int, default=3, help="seeds of the chosen configuration's test runs (default 3)")
    p.add_argument("--out", help="tune directory (default studies/tune-PROBLEM)")
    p.add_argument("--storage", metavar="URL",
                   help="Optuna storage, e.g. postgresql://user@host/db for many machines (default: the journal "
                        "file optuna.journal in --out)")  # fmt: skip
    p.add_argument("--prune", action="store_true", help="successive halving: after each rung the best 1/eta go on")
    p.add_argument("--eta", type=int, default=3, help="--prune: the halving rate (default 3)")
    p.add_argument("--rungs", type=int, default=3, help="--prune: budgets steps/eta^(rungs-1) ... steps (default 3)")
    p.add_argument("--holdout", type=float, default=0.2,
                   help="the fraction of train held out for validation where the problem has no val split (0.2)")  # fmt: skip
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_workers(p, "the machine's cores")
    _add_budget(p, calibrated=True)

    p = sub.add_parser(
        "report",
        help="re-draw a study's (a sweep's, a bench's) tables and figures from its files",
        description="Re-draw the tables and figures of a study (physgrad compare --out DIR), a sweep (its "
        "grid.json) or a bench (its bench.json: every problem's table, the leaderboards, the heat map) from "
        "the directory's files alone; nothing trains. A bench whose problems were kept without their runs "
        "(docs/reproductions/keep_studies.py) is redrawn from the kept summary.csv and results.csv.",
    )
    p.add_argument("dir", help="the study, sweep, bench or tune directory")
    p.add_argument("--panel", help="sweeps: the swept setting with one panel per value (default: the first)")
    p.add_argument(
        "--metric",
        default="loss",
        help="sweeps: the metric to draw (default loss; e.g. step_grad_norm2 with --split train)",
    )
    p.add_argument("--split", default="test", help="sweeps: the split of --metric (default test)")
    p.add_argument("--smooth", type=int, default=1, help="sweeps: moving average over this many epochs (the paper: 30)")

    p = sub.add_parser(
        "bench", help="every applicable method on every chosen problem at equal budgets; tables, leaderboard, heat map",
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Run every applicable method on every chosen problem with the same budget per run, rank them per "
                    "problem and across problems (physgrad.harness.bench). Resumable: the same command again skips finished "
                    "runs and resumes interrupted ones.",
        epilog="profiles:\n"
               "  --quick     " + QUICK_SUMMARY + "\n"
               "  --standard  " + STANDARD_SUMMARY + "\n"
               "examples:\n"
               "  physgrad bench --quick --plan               what the quick profile runs and its estimated time\n"
               "  physgrad bench --quick                      run it (the same command again resumes it)\n"
               "  physgrad bench --standard --calibrate-only  time every step first: --plan then estimates from it\n"
               "  physgrad bench --problems sine,oscillators --methods adam,hig,optax:lion --steps 500\n"
               "  --set NAME=VALUE applies wherever the setting exists; --set PROBLEM.NAME=VALUE to one problem\n"
               "Each problem declares a target test loss; the leaderboard is a performance profile of the\n"
               "time to it (profile.png), with the final-loss ranking beside it.",
    )  # fmt: skip
    p.add_argument("--problems", help="comma-separated problems, or all (default: all shipped problems)")
    p.add_argument("--methods", help="comma-separated candidate methods, or applicable (default: every registered "
                                     "method; each problem runs those that apply)")  # fmt: skip
    p.add_argument(
        "--seeds", type=seed_count, default=None, help="number of seeds 0..N-1 (default 1; a profile: its own)"
    )
    p.add_argument("--out", help="bench directory (default bench; a profile: bench-quick, bench-standard)")
    p.add_argument("--quick", action="store_true", help="the quick profile: " + QUICK_SUMMARY)
    p.add_argument("--standard", action="store_true", help="the standard profile: " + STANDARD_SUMMARY)
    p.add_argument("--plan", action="store_true",
                   help="print what would run and its estimated time (from the calibration in --out where there is "
                        "one), and run nothing")  # fmt: skip
    p.add_argument("--calibrate-only", action="store_true",
                   help="run only each problem's calibration (into --out, which the bench then reuses), then print "
                        "the plan")  # fmt: skip
    p.add_argument("--devices", default="1", metavar="N|all", help="devices to split each batch over (default 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--tuned", action="store_true",
                   help="AlgoPerf-style external tuning: every applicable method gets --trials trials from its declared "
                        "search space on each problem (physgrad tune), chosen on validation, then the chosen "
                        "configuration on --seeds seeds (default 3) on test; leaderboard: the integrated performance "
                        "profile (capped at 4x) and the geo-mean score at half and full budget")  # fmt: skip
    p.add_argument("--trials", type=int, default=None, help="--tuned: trials per method and problem (default 5)")
    p.add_argument("--holdout", type=float, default=None,
                   help="--tuned: the fraction of train held out for validation where a problem has no val split "
                        "(default 0.2)")  # fmt: skip
    _add_workers(p, "the machine's cores")
    _add_budget(p, calibrated=True)

    p = sub.add_parser(
        "calibrate", help="time each method's compiled step on a problem; write the calibration table",
        description="Time each method's compiled training step on PROBLEM (seed 0, the paper settings and --set "
                    "values; interleaved rounds, median; compilation excluded) and write the table in the columns of "
                    "docs/reproductions/long/calibration.csv (problem, method, route, batch, ms_per_step, measured, "
                    "machine, command), then the spread. The same timing a calibrated study runs first.",
    )  # fmt: skip
    p.add_argument("problem")
    p.add_argument("--methods", help="comma-separated, sequences allowed (default: the paper's comparison)")
    p.add_argument("--out", help="CSV file to write (default: print only); FILE.json writes the full record")
    p.add_argument("--append", action="store_true", help="add the rows to an existing --out CSV")
    p.add_argument("--repeats", type=int, default=None, help="rounds of interleaved timing, at most (default 15)")
    p.add_argument("--max-seconds", type=float, default=None,
                   help="a method leaves the rounds once its timed steps add up to this, after 3 rounds (default 10)")  # fmt: skip
    p.add_argument("--devices", default="1", metavar="N|all", help="devices to split each batch over (default 1)")
    p.add_argument("--no-network", action="store_true", help="direct optimisation (as in train and compare)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a problem setting, method hyperparameter or training setting; repeatable")  # fmt: skip
    _add_compilation_cache(p)
    _add_threads(p)

    p = sub.add_parser("demo", help="adam vs gn vs hig on the oscillators in about two minutes")
    p.add_argument("--out", default="studies/demo")
    p.add_argument("--seconds", type=float, default=DEMO["seconds"], help="training seconds per method")
    _add_compilation_cache(p)
    _add_threads(p)
    return parser
