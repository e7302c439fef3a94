"""What a bench is asked: its problems, candidate methods and ``--set`` values, and the quick profile.

A bench's ``--set`` values reach farther than a study's: ``p.name=value`` with ``p`` a
problem applies to that problem only, and a setting applies only where it exists (a
candidate that lacks it runs without it); :func:`check_settings` refuses, before anything
runs, a name that no chosen pairing has.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from ..arguments import QUICK_SUMMARY, STANDARD_SUMMARY
from ..config import ConfigError, choose, parse_method, phase_methods, split_methods, split_scope, valid_settings
from ..registry import METHODS, PROBLEMS

# The optax optimizers a default bench adds to the registered methods: Adam with decoupled
# weight decay, and two newer first-order methods (sign momentum; orthogonalised momentum).
ZOO = ("optax:adamw", "optax:lion", "optax.contrib:muon")

# The named profiles (``physgrad bench --quick`` / ``--standard``): problems, candidates,
# settings, seconds of calibrated training per run (harness/calibration.py) and seeds.
# ``physgrad bench --quick --plan`` prints what a profile runs and its estimated time
# (harness/bench/estimate.py) without running it.
#
# quick: at most 45 minutes on 2 CPU cores, 3 seeds (the fewest with a bootstrap interval).
# The fastest open-loop problems, measured on 2 CPU cores (setup and compilation of every
# method in seconds). The two problems with 65,536 training samples get 4,096 (an epoch, and
# so a full evaluation, every ~40 steps instead of ~650); the Jacobian methods on the
# oscillators take the demo's batch of 32 instead of the paper's 128 (at 128 a step costs
# ~5 s on 2 cores: two steps in a 10 s run). Evaluation every 0.5 s of calibrated time
# (0.02-0.1 s on the problems with the shorter budgets below): about 12-25 evaluations per run,
# which is the resolution of the time-to-target (the first evaluation at or below it). The
# first quick profile (2 seeds, 10 s, 12 candidates: 140 runs) took 43 minutes on 2 loaded
# cores; at 3 seeds the candidates drop SGD, Newton and Lion (SGD and Lion below Adam on
# none of the six problems, Newton diverged on 8 of 12 runs: docs/benchmark.md) and each run
# gets 6 s.
QUICK: dict[str, Any] = {
    "problems": ("hig_toy", "toy2d", "exp_inverse", "sine", "linear_oscillators", "oscillators"),
    # The DP baselines Adam and RMSprop (the best of the HIG paper's comparison), every
    # curvature and inversion method (Kronecker-factored HIG included), AdamW and Muon (the
    # rollout methods apply to none).
    "methods": ("adam", "rmsprop", "gn", "hig", "khig", "lm", "kfac", "sip", "optax:adamw", "optax.contrib:muon"),
    "settings": {
        "exp_inverse.n_train": "4096", "sine.n_train": "4096", "eval_seconds": "0.5", "toy2d.eval_seconds": "0.02",
        "hig_toy.eval_seconds": "0.05", "exp_inverse.eval_seconds": "0.1", "sine.eval_seconds": "0.1",
        "oscillators.gn.batch_size": "32", "oscillators.hig.batch_size": "32", "oscillators.lm.batch_size": "32",
    },
    "seconds": 6.0,
    "problem_seconds": {"toy2d": 0.5, "hig_toy": 1.0, "exp_inverse": 2.0, "sine": 2.0},
    "seeds": 3,
    "summary": QUICK_SUMMARY,
}  # fmt: skip

# standard: every problem that fits a CPU, at its paper settings (batch sizes included),
# every applicable method, 5 minutes of calibrated training per run, 5 seeds; a long study
# (days on 2 cores) that resumes run by run. Left out, with the reason (calibration.csv):
STANDARD_EXCLUDED = {
    "poisson_hig": "a HIG step at the paper's batch 64 costs 18.8 s on one core (structured route; 43.5 s gram): "
                   "a 5-minute run makes 16 updates",
    "navier_stokes": "an Adam step at the paper's batch 64 costs 7.4 s on one core (SIP 4.8 s): a 5-minute run "
                     "makes about 40 updates",
}  # fmt: skip
# The four problems with sub-millisecond steps get the budgets of their reproductions (the HIG
# toy figure's 20 s; the SIP studies' 20 s on exp_inverse and sine; 5 s on toy2d) and their
# evaluation intervals: at 300 s, toy2d's LM step (7 µs) would be 40 million steps.
STANDARD: dict[str, Any] = {
    "problems": None,  # every shipped problem but STANDARD_EXCLUDED (standard_problems())
    "methods": None,  # every registered method and the zoo (choose_methods(None)); each problem runs those that apply
    "settings": {
        "eval_seconds": "10", "toy2d.eval_seconds": "0.1", "hig_toy.eval_seconds": "0.2",
        "exp_inverse.eval_seconds": "1", "sine.eval_seconds": "1",
    },
    "seconds": 300.0,
    "problem_seconds": {"toy2d": 5.0, "hig_toy": 20.0, "exp_inverse": 20.0, "sine": 20.0},
    "seeds": 5,
    "summary": STANDARD_SUMMARY,
}  # fmt: skip
PROFILES: dict[str, dict[str, Any]] = {"quick": QUICK, "standard": STANDARD}


def profile_budgets(profile: dict[str, Any], problems: Sequence[str]) -> dict[str, Any]:
    """A profile's per-problem seconds (``problem_seconds``) as budgets, for ``problems``."""
    from ...engine.types import Seconds

    return {p: Seconds(s) for p, s in profile.get("problem_seconds", {}).items() if p in problems}


def standard_problems() -> list[str]:
    """The standard profile's problems: every shipped problem but :data:`STANDARD_EXCLUDED`."""
    return [p for p in PROBLEMS if p not in STANDARD_EXCLUDED]


def profile_choice(name: str) -> dict[str, Any]:
    """A named profile with its problems and methods resolved (a one-line error naming the
    valid profiles otherwise)."""
    choose("bench profile", name, PROFILES)
    profile = dict(PROFILES[name])
    profile["problems"] = list(profile["problems"] or standard_problems())
    profile["methods"] = list(profile["methods"] or choose_methods(None))
    return profile


def _unscoped(key: str) -> tuple[str | None, str]:
    """(problem, rest) of a ``--set`` key: ``("sine", "lr")`` for ``sine.lr``, ``(None, key)``
    where the key does not start with a problem's name."""
    head, _, rest = key.partition(".")
    return (head, rest) if head in PROBLEMS and rest else (None, key)


def quick_settings(problems: Sequence[str], methods: Sequence[str], profile: str = "quick") -> dict[str, Any]:
    """A profile's settings (default the quick one's) that concern ``problems`` and the
    candidate ``methods`` (those scoped to another problem or to a method not among the
    candidates dropped)."""
    stages = {m for spec in methods for m in phase_methods(spec)}
    keep = {}
    for key, value in PROFILES[profile]["settings"].items():
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
