"""Runs from names: a :class:`~physgrad.harness.config.RunConfig` (what the command line and the
studies write as ``config.json``) turned into objects and handed to :func:`physgrad.fit`.

This is the edge between strings and the library: :func:`build` resolves the registered
problem and methods (:mod:`physgrad.harness.registry`) with their settings; :func:`train` runs a
configuration into a run directory with the same engine a notebook uses.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import equinox as eqx

from ..engine import (
    AbstractSplit,
    Phase,
    Setup,
    TrainSettings,
    build_setup,
    fit,
    is_complete,
    make_evaluate,
    make_step,
    read_metrics,
    read_summary,
    rundir,
)
from ..engine.programs import ProgramCache
from ..engine.progress import AbstractProgressMeter
from ..engine.record import differences
from ..engine.splits import TEST_SPLIT
from ..errors import NotRefinable, RunDirectoryRefused
from ..problems.direct import DirectOptimisation
from .config import ConfigError, RunConfig
from .objects import devices as edge_devices
from .objects import make_problem
from .registry import METHODS, PROBLEMS
from .words import command_line_words


def problem_of(config: RunConfig, overrides: dict[str, Any] | None = None):
    """The configured problem instance (wrapped for direct optimisation with ``no_network``)."""
    try:
        problem = make_problem(PROBLEMS[config.problem], {**config.problem_settings, **(overrides or {})})
    except ValueError as e:
        raise ConfigError(f"{config.problem}: {e}") from None
    return DirectOptimisation(problem) if config.no_network else problem


def phases_of(config: RunConfig) -> list[Phase]:
    """The configured methods as engine phases (name, steps, batch size).

    A method configured alike is built once per process and shared: a method object holds
    optax closures, so only the same object lets a study's seeds share one compiled step
    (:mod:`physgrad.engine.programs`). Methods are immutable, so sharing them is safe."""
    out = []
    for phase in config.phases:
        key = (phase.method, repr(sorted(phase.hyperparameters.items())))
        method, _ = _METHODS_BUILT.get(key, functools.partial(_build_method, phase.method, phase.hyperparameters))
        out.append(Phase(method, phase.steps, phase.batch_size, phase.method))
    return out


_METHODS_BUILT = ProgramCache(size=64)  # the methods phases_of built, by name and settings


def _build_method(name: str, hyperparameters: dict[str, Any]):
    try:
        return METHODS[name](**hyperparameters)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{name}: {e}") from None


def settings_of(config: RunConfig) -> TrainSettings:
    """The engine's settings of a configuration (resolved: the problem's shuffle and
    fresh_samples as make_config chose them)."""
    return config.settings


def build(config: RunConfig, overrides: dict[str, Any] | None = None) -> Setup:
    """Problem, data, network and method(s) of a configuration (deterministic per seed);
    ``overrides`` replaces problem settings."""
    return build_setup(problem_of(config, overrides), phases_of(config), config.seed)


def _same_run(recorded: dict[str, Any], config: RunConfig) -> list[str]:
    """What differs between a run directory's ``config.json`` and ``config`` in the run's
    identity (:meth:`RunConfig.identity`), ``key: old → new`` each; empty for the same run."""
    try:
        old = RunConfig.from_dict(recorded)
    except (KeyError, TypeError, ValueError, AttributeError):
        raise RunDirectoryRefused("the run directory's config.json was not written by the command line (a run of "
                                  "physgrad.fit from Python?); resume it with physgrad.fit(..., resume=True) as it "
                                  "was started, or ") from None  # fmt: skip
    return differences(old.identity(), config.identity())


def train(
    config: RunConfig,
    run_dir: str | Path,
    *,
    resume: bool = False,
    progress: AbstractProgressMeter | None = None,
    devices: int | str | None = 1,
    split: AbstractSplit = TEST_SPLIT,
) -> dict[str, Any]:
    """Train one configured run into ``run_dir`` and return its summary (:func:`physgrad.fit`).
    ``split`` as :func:`physgrad.fit`'s (a tuning trial's :class:`~physgrad.HoldOut`); its
    note joins the record (``"validation"``), which keeps the configuration's identity.

    With ``resume=True`` an existing run continues from its last checkpoint up to
    ``config.budget`` (which may be larger than the original one); a finished run whose
    budget is already met returns its summary unchanged. Runs written before settings were
    added keep matching (:data:`physgrad.harness.config.ADDED_LATER`)."""
    if config.settings.prdp and PROBLEMS[config.problem].refinable_setting is None:
        valid = [name for name, cls in PROBLEMS.items() if cls.refinable_setting]
        raise ConfigError(f"prdp needs a problem with an iterative solver; valid choices: {', '.join(valid)}")
    record = config.to_dict() | ({} if split.note is None else {"validation": split.note})
    try:
        return fit(
            problem_of(config), phases_of(config), budget=config.budget, out=run_dir, seed=config.seed,
            settings=settings_of(config), split=split, resume=resume, progress=progress,
            devices=edge_devices(devices), record=record, same_run=lambda old: _same_run(old, config),
            name=config.method,
        ).summary  # fmt: skip
    except NotRefinable as e:  # refused before any work; the remedy is a setting of the command line's
        raise ConfigError(command_line_words(e)) from None


def load_network(run_dir: str | Path, like=None):
    """The final trained network of a run directory (``params.eqx``).

    ``like`` is a network of the same structure to fill (for runs of :func:`physgrad.fit`
    on your own problem); without it the network is rebuilt from the run's ``config.json``
    (runs of the command line and of :func:`train`)."""
    run_dir = Path(run_dir)
    params = run_dir / "params.eqx"
    if not run_dir.is_dir():
        raise ConfigError(f"{run_dir} is no run directory (it does not exist); give the directory a run wrote")
    if not params.is_file():  # one line, not Equinox's traceback
        raise ConfigError(f"{params} is missing: the run has not finished (a run writes it when it ends); "
                          "resume the run to finish it")  # fmt: skip
    if like is None:
        advice = "pass like=, a network of the run's structure (runs of physgrad.fit on your own problem)"
        config = RunConfig.from_dict(rundir.read_json(run_dir / "config.json", advice))
        like = build(config).network()
    return eqx.tree_deserialise_leaves(params, like)


__all__ = ["Setup", "build", "is_complete", "load_network", "make_evaluate", "make_step", "read_metrics",
           "read_summary", "train"]  # fmt: skip
