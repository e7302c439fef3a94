"""What a bench is asked: its problems, candidate methods and ``--set`` values, and the quick profile.

A bench's ``--set`` values reach farther than a study's: ``p.name=value`` with ``p`` a
problem applies to that problem only, and a setting applies only where it exists (a
candidate that lacks it runs without it); :func:`check_settings` refuses, before anything
runs, a name that no chosen pairing has.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..config import ConfigError, choose, parse_method, phase_methods, split_methods, split_scope, valid_settings
from ..registry import METHODS, PROBLEMS

# The optax optimizers a default bench adds to the registered methods: Adam with decoupled
# weight decay, and two newer first-order methods (sign momentum; orthogonalised momentum).
ZOO = ("optax:adamw", "optax:lion", "optax.contrib:muon")

# The quick profile (``physgrad bench --quick``): the fastest open-loop problems, measured on
# 2 CPU cores (setup and compilation of every method in seconds), 10 s of training per run
# and 2 seeds. Measured on 2 cores shared with other jobs (load ~6): a 10 s run costs ~18 s
# of wall-clock (setup, compilation, evaluation); the first version's 118 runs took 36
# minutes, so the curated list below (142 runs) takes about 43. The two problems with 65,536 training samples get
# 4,096 (an epoch, and so a full evaluation, every ~40 steps instead of ~650); the Jacobian
# methods on the oscillators take the demo's batch of 32 instead of the paper's 128 (at 128 a
# step costs ~5 s on 2 cores: two steps in a 10 s run). Evaluation every 2 training seconds
# gives every curve a few points.
QUICK: dict[str, Any] = {
    "problems": ("hig_toy", "toy2d", "exp_inverse", "sine", "linear_oscillators", "oscillators"),
    # The candidates of the quick profile: the DP baselines that did best in the HIG paper's
    # comparison (Adam, RMSprop, SGD; Adagrad and Adadelta trail them) plus every
    # curvature and inversion method and the zoo (the rollout methods apply to none of them).
    "methods": ("adam", "sgd", "rmsprop", "gn", "hig", "lm", "kfac", "sip", "newton", *ZOO),
    "settings": {
        "exp_inverse.n_train": "4096", "sine.n_train": "4096", "eval_seconds": "2",
        "oscillators.gn.batch_size": "32", "oscillators.hig.batch_size": "32", "oscillators.lm.batch_size": "32",
    },
    "seconds": 10.0,
    "seeds": 2,
}  # fmt: skip


def _unscoped(key: str) -> tuple[str | None, str]:
    """(problem, rest) of a ``--set`` key: ``("sine", "lr")`` for ``sine.lr``, ``(None, key)``
    where the key does not start with a problem's name."""
    head, _, rest = key.partition(".")
    return (head, rest) if head in PROBLEMS and rest else (None, key)


def quick_settings(problems: Sequence[str], methods: Sequence[str]) -> dict[str, Any]:
    """The quick profile's settings that concern ``problems`` and the candidate ``methods``
    (those scoped to another problem or to a method not among the candidates dropped)."""
    stages = {m for spec in methods for m in phase_methods(spec)}
    keep = {}
    for key, value in QUICK["settings"].items():
        problem, rest = _unscoped(key)
        if problem is not None and problem not in problems:
            continue
        target, _ = split_scope(rest)
        if not target or target in stages:
            keep[key] = value
    return keep


def choose_problems(text: str | None) -> list[str]:
    """``None``/``"all"`` → every shipped problem; else the comma-separated names, checked
    (a one-line :class:`ConfigError` with the valid choices)."""
    if text is None or text.strip() == "all":
        return list(PROBLEMS)
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise ConfigError(f"--problems is empty; valid choices: all, {', '.join(sorted(PROBLEMS))}")
    for name in names:
        choose("problem", name, PROBLEMS)
    return list(dict.fromkeys(names))


def choose_methods(text: str | None) -> list[str]:
    """``None``/``"applicable"`` → every registered method and the optax optimizers of
    :data:`ZOO` (each problem keeps those that apply); else the listed specs, each checked
    by ``config.parse_method`` (which owns the method names, colon names such as
    ``optax:lion`` included)."""
    if text is None or text.strip() == "applicable":
        return [*METHODS, *ZOO]
    specs = split_methods(text)
    if not specs:
        raise ConfigError(f"--methods is empty; valid choices: applicable, {', '.join(sorted(METHODS))}")
    for spec in specs:
        parse_method(spec)
    return list(dict.fromkeys(specs))


def scoped_settings(problem: str, settings: dict[str, Any]) -> dict[str, Any]:
    """The bench's ``--set`` values as ``problem`` sees them: its own ``problem.name`` keys
    unscoped, other problems' keys dropped."""
    out = {}
    for key, value in settings.items():
        scope, rest = _unscoped(key)
        if scope is None or scope == problem:
            out[rest] = value
    return out


def problem_settings(problem: str, method: str, settings: dict[str, Any]) -> dict[str, Any]:
    """The subset of a bench's ``--set`` values for one (problem, method) run.

    ``name=value`` applies where the setting exists (a problem setting, a method
    hyperparameter or a training setting); ``m.name=value`` to method ``m`` (or the stage
    ``m`` of a sequence); ``p.name=value`` with ``p`` a problem to that problem only (and
    ``p.m.name`` to method ``m`` on problem ``p``). Names that exist nowhere are refused by
    :func:`check_settings` before anything runs."""
    names = set(phase_methods(method))
    valid = valid_settings(problem, method)
    out = {}
    for key, value in scoped_settings(problem, settings).items():
        target, name = split_scope(key)
        if name in valid and (not target or target in names):
            out[key] = value
    return out


def study_settings(problem: str, methods: Sequence[str], settings: dict[str, Any]) -> dict[str, Any]:
    """The bench's ``--set`` values as one problem's study (:func:`physgrad.harness.study.compare`
    of its applicable ``methods``) takes them: :func:`scoped_settings`, less what none of
    the methods has (compare refuses such a name; the bench drops it): the study gives each
    method the same settings as :func:`problem_settings`, and records them in ``study.json``."""
    kept = set().union(*(problem_settings(problem, m, settings) for m in methods))
    return {k: v for k, v in scoped_settings(problem, settings).items() if k in kept}


def check_settings(problems: Sequence[str], methods: Sequence[str], settings: dict[str, Any]) -> None:
    """Refuse (one line) a setting that no chosen problem/method pairing has, or a scope
    that names no chosen problem or method."""
    everywhere: set[str] = set()
    for problem in problems:
        for method in methods:
            everywhere |= set(valid_settings(problem, method))
    stages = sorted({m for spec in methods for m in phase_methods(spec)})
    for key in settings:
        scope, key = _unscoped(key)
        if scope is not None:
            choose("problem in a scoped setting", scope, problems)
        target, name = split_scope(key)
        if target:
            choose("method in a scoped setting", target, stages)
        if name not in everywhere:
            raise ConfigError(f"unknown setting {name!r}; valid choices: {', '.join(sorted(everywhere))}")
