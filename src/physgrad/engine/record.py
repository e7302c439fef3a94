"""The record of a run given as objects (``config.json``): :func:`describe` writes it,
and :func:`identity` and :func:`like` say whether a recorded run is the same run (so that
``resume=True`` continues it).

The record is readable JSON: the problem's and the phases' ``repr`` (memory addresses
removed), the method's name, each phase's optimizer hyperparameters where optax exposes them
(:mod:`physgrad.engine.hyperparams`), the seed, the budget and the settings as resolved.
"""

from __future__ import annotations

import dataclasses
import re
from collections.abc import Sequence
from typing import Any

from ..problems import AbstractProblem
from .hyperparams import optimizer_record
from .types import ADDED_SETTINGS, UNGUARDED_SETTINGS, Budget, Phase, TrainSettings

_ABSENT = object()
# Keys of the default record that an older physgrad did not write: a recorded run without
# one still resumes (the key is left out of the comparison).
ADDED_RECORD_KEYS = ("optimizers",)
# Keys of the default record that name the run without changing what it computes.
UNCOMPARED_RECORD_KEYS = ("method",)


def describe(
    problem: AbstractProblem,
    *,
    phases: Sequence[Phase],
    seed: int,
    budget: Budget,
    settings: TrainSettings,
    name: str,
) -> dict[str, Any]:
    """A readable record of a run given as objects (memory addresses removed, so the same
    objects describe alike in every process and session): the method's ``name`` and each
    phase's optimizer hyperparameters where optax exposes them (:func:`optimizer_record`)."""
    text = lambda obj: re.sub(r" at 0x[0-9a-f]+", "", repr(obj))  # noqa: E731
    return {"problem": text(problem), "method": name, "phases": [text(p) for p in phases],
            "optimizers": [optimizer_record(p.method) for p in phases], "seed": seed,
            "budget": budget.to_dict(), "settings": resolved(settings, problem)}  # fmt: skip


def like(record: dict[str, Any], old: dict[str, Any]) -> dict[str, Any]:
    """``record`` as comparable with ``old``: without the keys an older physgrad did not
    write where ``old`` lacks them (:data:`ADDED_RECORD_KEYS`)."""
    return {k: v for k, v in record.items() if k not in ADDED_RECORD_KEYS or k in old}


def resolved(settings: TrainSettings, problem: AbstractProblem) -> dict[str, Any]:
    """The settings as recorded: ``shuffle`` and ``fresh_samples`` None stand for the
    problem's defaults."""
    out = dataclasses.asdict(settings)
    out["shuffle"] = problem.default_shuffle if settings.shuffle is None else settings.shuffle
    out["fresh_samples"] = problem.default_fresh_samples if settings.fresh_samples is None else settings.fresh_samples
    return out


def identity(record: dict[str, Any]) -> dict[str, Any]:
    """What must match for a run to resume: the record without its budget, its method's
    name and the settings that change only how the run is guarded."""
    settings = {k: v for k, v in record.get("settings", {}).items()
                if k not in UNGUARDED_SETTINGS and ADDED_SETTINGS.get(k, _ABSENT) != v}  # fmt: skip
    named = {k: v for k, v in record.items() if k not in UNCOMPARED_RECORD_KEYS}
    return {**named, "budget": None, "settings": settings}
