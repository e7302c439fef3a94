"""Running a study: its plan (method x seed run configurations, validated before anything
runs), the runs' deterministic names, the calibration of a seconds budget and the loop that
trains every run into ``runs/<method>-seed<k>-<hash>/``, skipping finished ones and resuming
interrupted ones (:func:`compare`)."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ...engine import rundir
from ...engine.progress import AbstractProgressMeter
from ...engine.types import Seconds, Steps
from ...errors import ConfigError
from ..config import (
    Budget,
    RunConfig,
    choose,
    make_config,
    method_slug,
    parse_method,
    phase_methods,
    split_scope,
    valid_settings,
)
from ..console import describe_run
from ..failures import FailureLog, recordable
from ..papers import protocol
from ..registry import PROBLEMS
from ..train import is_complete, read_summary, train
from .tables import collect


def settings_for(problem: str, method: str, methods: Sequence[str], settings: dict[str, Any]) -> dict[str, Any]:
    """The subset of a study's ``--set`` values that applies to one method (or sequence).

    ``name=value`` applies to every method that has the setting (it must exist for at least
    one); ``m.name=value`` applies to method ``m``, also where ``m`` is a stage of a
    sequence such as ``adam:2000,hig``.
    """
    names = set(phase_methods(method))
    everywhere = sorted(set().union(*(phase_methods(m) for m in methods)))
    out = {}
    for key, value in settings.items():
        target, name = split_scope(key)
        if target:
            choose("method in a scoped setting", target, everywhere)
            if target in names:
                out[key] = value  # validated by make_config
        elif name in valid_settings(problem, method):
            out[name] = value
        elif not any(name in valid_settings(problem, m) for m in methods):
            valid = sorted(set().union(*(valid_settings(problem, m) for m in methods)))
            raise ConfigError(f"unknown setting {name!r} for {problem}; valid choices: {', '.join(valid)}")
    return out


def plan(
    problem: str,
    methods: Sequence[str] | None,
    seeds: Sequence[int],
    budget: Budget,
    settings: dict[str, Any] | None = None,
) -> list[RunConfig]:
    """The run configurations of a study, validated before anything runs (``methods`` None: its defaults)."""
    choose("problem", problem, PROBLEMS)
    methods = list(protocol(problem).methods if methods is None else methods)
    for m in methods:
        parse_method(m)
    settings = settings or {}
    return [
        make_config(problem, m, budget=budget, seed=s, settings=settings_for(problem, m, methods, settings))
        for m in methods
        for s in seeds
    ]


def run_name(config: RunConfig) -> str:
    """A readable, deterministic run directory name: method, seed and a config hash
    (a sequence ``adam:2000,hig`` reads ``adam2000+hig``)."""
    return f"{method_slug(config.method)}-seed{config.seed}-{config.digest()}"


def compare(
    problem: str,
    methods: Sequence[str] | None,
    seeds: Sequence[int],
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    progress: Callable[[], AbstractProgressMeter] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    record_failures: bool = False,
    calibrate: bool = True,
    calibration_options: dict[str, Any] | None = None,
    executor=None,
) -> list[dict[str, Any]]:
    """Train every method × seed on the same budget into ``out``; return the summary rows.
    ``devices``: each run's batch is split over that many devices (``train``). One study
    writes to ``out`` at a time (a second is refused in one line naming the first).
    ``record_failures``: a run that raises is recorded and the study goes on (the bench's
    choice: one crashing method must not cost the others' runs; :mod:`physgrad.harness.failures`);
    without it the first error stops the study, as bad input and KeyboardInterrupt always do.

    A seconds budget is calibrated (``calibrate``, the default; :mod:`physgrad.harness.calibration`):
    each method's compiled step is timed first (or the study's recorded calibration read
    back), and its runs train for ``seconds / calibrated seconds per step`` steps, their
    ``eval_seconds`` becoming the same cadence in steps. ``calibrate=False`` keeps the
    wall-clock budget (the run stops when its training wall-clock reaches the seconds).
    ``calibration_options``: :func:`~physgrad.harness.calibration.calibrate`'s ``repeats``,
    ``max_seconds``, ``clock`` or ``programs``. ``executor``: where the runs go, all at once
    (:mod:`physgrad.harness.workers`: Dask workers; None: one after the other here)."""
    out = Path(out)
    configs = plan(problem, methods, seeds, budget, settings)
    with rundir.one_writer(out, "study"):  # one writer per study directory, for the whole study
        calibrated = isinstance(budget, Seconds) and calibrate
        if calibrated:
            calibration = _calibration(out, configs, echo=echo, devices=devices, record_failures=record_failures,
                                       **(calibration_options or {}))  # fmt: skip
            configs = [calibrated_config(c, calibration, float(budget.amount)) for c in configs]
        names = [run_name(c) for c in configs]
        rundir.atomic_write(out / "study.json", json.dumps({
            "problem": problem, "methods": list(dict.fromkeys(c.method for c in configs)), "seeds": list(seeds),
            "budget": budget.to_dict(), "settings": settings or {}, "runs": names, "calibrated": calibrated,
            "run_budgets": {c.method: c.budget.to_dict() for c in configs},
        }, indent=2) + "\n")  # fmt: skip
        log = FailureLog(out, names, write=record_failures)
        pending = []  # --- executor injection (harness/workers.py): the runs left, handed over at once
        for i, (config, name) in enumerate(zip(configs, names), 1):
            run_dir = out / "runs" / name
            prefix = f"[{i}/{len(configs)}] {config.method} seed {config.seed}"
            if is_complete(run_dir) and not cap_raised(read_summary(run_dir) or {}, config.wall_cap):
                echo(f"{prefix}: done already ({(read_summary(run_dir) or {}).get('status')}), skipped")
                continue
            if executor is not None:
                pending.append((prefix, config, run_dir))
                continue
            try:
                summary = train(config, run_dir, resume=True, progress=progress and progress(), devices=devices)
            except Exception as e:  # KeyboardInterrupt is no Exception: it always stops the study
                if not (record_failures and recordable(e)):
                    raise
                echo(f"{prefix}: failed, recorded ({log.record(name, config.method, config.seed, e)})")
                continue
            log.clear(name)
            echo(f"{prefix}: {describe_run(summary)}")
        if pending:
            from ..workers import run_pending

            run_pending(executor, pending, log, record_failures=record_failures, echo=echo, devices=devices)
        return collect(out)  # --- end of the executor injection


def calibrate_study(
    problem: str,
    methods: Sequence[str] | None,
    budget: Budget,
    out: str | Path,
    *,
    settings: dict[str, Any] | None = None,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
) -> dict[str, list[Any]]:
    """The calibration phase of :func:`compare` alone: each method's step timed into
    ``out/calibration.json`` (or the recorded one read back), nothing trained. ``compare``
    on the same directory then reuses it, so a study calibrated on a quiet machine trains
    with the same step counts under any load. Returns each method's stage costs."""
    out = Path(out)
    configs = plan(problem, methods, [0], budget, settings)
    out.mkdir(parents=True, exist_ok=True)
    with rundir.one_writer(out, "study"):
        calibration = _calibration(out, configs, echo=echo, devices=devices)
    return {c.method: calibration.stages(c.method) for c in configs if calibration.has(c.method)}


def _calibration(out: Path, configs: Sequence[RunConfig], **options: Any):
    """The study's calibration (:func:`physgrad.harness.calibration.study_calibration`) of
    each method's seed-0 run: the seeds share its step program."""
    from ..calibration import study_calibration

    firsts: dict[str, RunConfig] = {}
    for c in configs:
        firsts.setdefault(c.method, dataclasses.replace(c, seed=0))
    return study_calibration(out, firsts, **options)


def cap_raised(summary: dict[str, Any], wall_cap: float) -> bool:
    """Whether a run that a wall-clock cap stopped may train on: the cap is now higher, or gone."""
    return bool(summary.get("wall_capped")) and (wall_cap <= 0 or wall_cap > summary.get("train_seconds", 0.0))


def calibrated_config(config: RunConfig, calibration, seconds: float) -> RunConfig:
    """A run of a calibrated study: ``seconds`` of calibrated time as a step budget, and its
    ``eval_seconds`` (training seconds between evaluations) as ``eval_every`` steps at its
    last stage's calibrated cost, so that evaluations fall at the same calibrated times
    whatever the load. A method without a calibration (its step could not be built) keeps
    the wall-clock budget: its run meets the same error and is recorded."""
    if not calibration.has(config.method):
        return config
    changes: dict[str, Any] = {"budget": Steps(calibration.steps(config.method, seconds))}
    if config.eval_seconds > 0:
        every = max(1, round(config.eval_seconds / calibration.seconds_per_step(config.method)))
        changes.update(eval_every=every, eval_seconds=0.0)
    return dataclasses.replace(config, **changes)
