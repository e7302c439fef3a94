"""The record of a run given as objects (``config.json``): :func:`describe` writes it,
and :func:`identity` and :func:`like` say whether a recorded run is the same run (so that
``resume=True`` continues it).

The record is readable JSON: the problem's and the phases' ``repr`` (memory addresses
removed), the method's name, each phase's optimizer hyperparameters where optax exposes them
(:mod:`physgrad.engine.hyperparams`), the seed, the budget and the settings as resolved.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Sequence
from typing import Any

from ..problems import AbstractProblem
from .hyperparams import optimizer_record
from .splits import TEST_SPLIT, AbstractSplit
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
    split: AbstractSplit = TEST_SPLIT,
) -> dict[str, Any]:
    """A readable record of a run given as objects (memory addresses removed, so the same
    objects describe alike in every process and session): the method's ``name``, each
    phase's optimizer hyperparameters where optax exposes them (:func:`optimizer_record`)
    and, for a split other than the problem's own, its note (key ``validation``)."""
    text = lambda obj: re.sub(r" at 0x[0-9a-f]+", "", repr(obj))  # noqa: E731
    note = {} if split.note is None else {"validation": split.note}
    return {"problem": text(problem), "method": name, "phases": [text(p) for p in phases],
            "optimizers": [optimizer_record(p.method) for p in phases], "seed": seed,
            "budget": budget.to_dict(), "settings": resolved(settings, problem), **note}  # fmt: skip


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


# Settings that change how a run is carried out, never its numbers: a resume may change them.
CARRIED_OUT_SETTINGS = ("checkpoint_seconds",)
# Where the curve is sampled (the steps between evaluations run as one compiled program
# whatever their count); part of the identity only where PRDP refines on the evaluations.
EVALUATION_CADENCE = ("eval_every", "eval_seconds")


def identity(record: dict[str, Any]) -> dict[str, Any]:
    """What must match for a run to resume: the record without its budget, its method's
    name and the settings that change only how the run is guarded or carried out
    (:data:`CARRIED_OUT_SETTINGS`, :data:`EVALUATION_CADENCE` without PRDP); compare it
    after :func:`normalised` (:func:`differences`)."""
    recorded = record.get("settings", {})
    carried_out = (*UNGUARDED_SETTINGS, *CARRIED_OUT_SETTINGS, *(() if recorded.get("prdp") else EVALUATION_CADENCE))
    settings = {k: v for k, v in recorded.items()
                if k not in carried_out and ADDED_SETTINGS.get(k, _ABSENT) != v}  # fmt: skip
    named = {k: v for k, v in record.items() if k not in UNCOMPARED_RECORD_KEYS}
    return {**named, "budget": None, "settings": settings}


def normalised(data: Any) -> Any:
    """``data`` in one form for comparisons: tuples as lists (``config.json`` holds lists
    where the live configuration holds tuples), numbers written as text as numbers, ints and
    floats of one value alike (``3`` and ``3.0``), and dict keys as text."""
    if isinstance(data, dict):
        return {str(k): normalised(v) for k, v in data.items()}
    if isinstance(data, (list, tuple)):
        return [normalised(v) for v in data]
    if isinstance(data, bool) or data is None:
        return data
    if isinstance(data, (int, float)):
        return float(data) if math.isfinite(data) else str(float(data))  # nan == nan as text
    if isinstance(data, str):
        try:
            number = float(data)
        except ValueError:
            return data
        return number if math.isfinite(number) else str(number)
    return normalised(json.loads(json.dumps(data, default=str)))


def differences(old: Any, new: Any) -> list[str]:
    """What differs between two records, one ``key: old → new`` entry per leaf (nested
    keys dotted, list items by index), after :func:`normalised`; empty where they agree."""
    a, b = _leaves(normalised(old)), _leaves(normalised(new))
    return [f"{key}: {_shown(a.get(key, _ABSENT))} → {_shown(b.get(key, _ABSENT))}"
            for key in sorted(a.keys() | b.keys()) if a.get(key, _ABSENT) != b.get(key, _ABSENT)]  # fmt: skip


def _leaves(data: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(data, dict) and data:
        out = {}
        for k, v in data.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else k))
        return out
    if isinstance(data, list) and data and any(isinstance(v, (dict, list)) for v in data):
        out = {}
        for i, v in enumerate(data):
            out.update(_leaves(v, f"{prefix}[{i}]"))
        return out
    return {prefix: data}


def _shown(value: Any) -> str:
    if value is _ABSENT:
        return "(unset)"
    if isinstance(value, float) and value.is_integer() and abs(value) < 1e15:
        return str(int(value))
    return json.dumps(value) if not isinstance(value, str) else value
