"""Each command's options as one frozen value, built from the parsed arguments
(:mod:`physgrad.harness.arguments`) and passed whole to the command's body, so that no body
takes a row of positional parameters. Building one checks the flags that the parser cannot
(``--seeds 0``, two budgets, a bad ``--out``) in the command line's words (exit 2)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from .arguments import DEMO, UsageError, budget_of, output_dir, run_settings

if TYPE_CHECKING:
    from .config import Budget


def _methods(text: str | None) -> tuple[str, ...] | None:
    """``--methods a,b,adam:2000,hig`` as method specs (None: the command's default)."""
    from .config import split_methods

    return tuple(split_methods(text)) if text else None


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    """``physgrad train``: one method (or sequence) on one problem into a run directory."""

    problem: str
    method: str
    seed: int
    budget: Budget
    settings: dict[str, Any]
    out: str | None  # None: runs/PROBLEM-METHOD-seedK (checked after the configuration, as before)
    resume: bool
    quiet: bool
    devices: str

    @classmethod
    def from_args(cls, args, devices: str) -> TrainOptions:
        return cls(args.problem, args.method, args.seed, budget_of(args), run_settings(args), args.out,
                   args.resume, args.quiet, devices)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class StudyOptions:
    """``physgrad compare`` (and the demo's fixed study): every method × seed on one problem
    at one budget, into ``out``; a comma-separated setting sweeps a grid of studies."""

    problem: str
    methods: tuple[str, ...] | None  # None: the paper's comparison
    seeds: range
    budget: Budget
    settings: dict[str, Any]
    out: Path
    quiet: bool = False
    devices: str = "1"
    calibrate: bool = True  # a --seconds budget is calibrated (--no-calibrate: wall-clock)
    calibrate_only: bool = False
    workers: int | None = None
    scheduler: str | None = None

    @classmethod
    def from_args(cls, args) -> StudyOptions:
        methods = _methods(args.methods)
        if args.seeds < 1:
            raise UsageError("--seeds must be at least 1")
        from .config import problem_slug

        out = output_dir(args.out if args.out is not None else f"studies/{problem_slug(args.problem)}")
        settings = run_settings(args)
        return cls(args.problem, methods, range(args.seeds), budget_of(args), settings, out, args.quiet,
                   args.devices, not args.no_calibrate, args.calibrate_only, args.workers, args.scheduler)  # fmt: skip

    @classmethod
    def demo(cls, seconds: float, out: str) -> StudyOptions:
        """The demo's study (:data:`physgrad.harness.arguments.DEMO`) at ``seconds`` per run."""
        from ..engine.types import Seconds

        return cls(DEMO["problem"], tuple(DEMO["methods"]), range(DEMO["seeds"]), Seconds(seconds),
                   DEMO["settings"], Path(out))  # fmt: skip


@dataclasses.dataclass(frozen=True)
class ReportOptions:
    """``physgrad report DIR``: a study's, sweep's, bench's or tune's tables redrawn from its files."""

    dir: str
    panel: str | None = None  # the options below are the sweeps'
    metric: str = "loss"
    split: str = "test"
    smooth: int = 1

    @classmethod
    def from_args(cls, args) -> ReportOptions:
        return cls(args.dir, args.panel, args.metric, args.split, args.smooth)


@dataclasses.dataclass(frozen=True)
class BenchOptions:
    """``physgrad bench``: the flags as given; :func:`physgrad.harness.bench.console.bench_command`
    resolves a profile's problems, methods, budgets and seeds from them."""

    problems: str | None
    methods: str | None
    seeds: int | None  # None: 1, or the profile's
    profile: str  # "quick", "standard" or "" (none)
    settings: dict[str, Any]
    budget: Budget | None  # None: no budget flag (the default 60 s, or the profile's)
    out: str | None
    plan: bool
    calibrate_only: bool
    no_calibrate: bool
    devices: str
    quiet: bool
    workers: int | None = None
    scheduler: str | None = None
    tuned: bool = False  # --tuned: each method tuned per problem first (harness/bench/tuned.py)
    trials: int = 5
    holdout: float = 0.2

    @classmethod
    def from_args(cls, args) -> BenchOptions:
        if args.seeds is not None and args.seeds < 1:
            raise UsageError("--seeds must be at least 1")
        if args.quick and args.standard:
            raise UsageError("give only one of --quick, --standard")
        tuned = getattr(args, "tuned", False)
        trials, holdout = getattr(args, "trials", None), getattr(args, "holdout", None)
        if not tuned and (trials is not None or holdout is not None):
            raise UsageError("--trials and --holdout need --tuned")
        if trials is not None and trials < 1:
            raise UsageError(f"--trials must be at least 1, got {trials}")
        if holdout is not None and not 0 < holdout < 1:
            raise UsageError(f"--holdout is a fraction in (0, 1), got {holdout}")
        if tuned and str(args.devices) != "1":
            raise UsageError("--tuned runs each trial on one device; --devices applies to the untuned bench")
        if tuned and args.no_calibrate:
            raise UsageError("--tuned trials train calibrated step budgets; --no-calibrate would tie them to the load")
        profile = "quick" if args.quick else "standard" if args.standard else ""
        settings = run_settings(args)
        given = any(getattr(args, k) is not None for k in ("steps", "epochs", "seconds"))
        return cls(args.problems, args.methods, args.seeds, profile, settings, budget_of(args) if given else None,
                   args.out, args.plan, args.calibrate_only, args.no_calibrate, args.devices, args.quiet,
                   args.workers, args.scheduler, tuned, trials or 5, holdout or 0.2)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class CalibrateOptions:
    """``physgrad calibrate PROBLEM``: each method's step timed; the table, and ``out`` if given."""

    problem: str
    methods: tuple[str, ...] | None
    settings: dict[str, Any]
    out: Path | None  # a .csv or .json file; None: print only
    append: bool
    repeats: int | None
    max_seconds: float | None
    devices: str
    command: str  # the command as typed, recorded in the CSV rows

    @classmethod
    def from_args(cls, args) -> CalibrateOptions:
        methods = _methods(args.methods)
        if args.repeats is not None and args.repeats < 1:
            raise UsageError("--repeats must be at least 1")
        if args.max_seconds is not None and not args.max_seconds > 0:
            raise UsageError("--max-seconds must be positive")
        out = Path(args.out) if args.out else None
        if out is not None and (out.is_dir() or (out.suffix not in (".csv", ".json"))):
            raise UsageError(f"--out {str(out)!r} must be a .csv or .json file")
        command = (
            "physgrad " + " ".join(sys.argv[1:])
            if sys.argv[1:2] == ["calibrate"]
            else f"physgrad calibrate {args.problem}"
        )
        return cls(args.problem, methods, run_settings(args), out, args.append, args.repeats, args.max_seconds,
                   args.devices, command)  # fmt: skip
