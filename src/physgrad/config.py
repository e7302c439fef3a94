"""Run configurations: names and settings resolved against the registries, with clear errors."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any

from .methods import METHODS, hyperparameters
from .problems import PROBLEMS


class ConfigError(ValueError):
    """A wrong problem, method, setting or budget; the message is one line with the choices."""


# Training-engine settings, settable with --set like problem and method settings.
TRAIN_SETTINGS: dict[str, Any] = {
    "batch_size": None,  # None: the problem's default for the method (the paper's)
    "eval_every": 0,  # steps between full train/test evaluations; 0 = once per epoch
    "eval_seconds": 0.0,  # if > 0: evaluate every this many training seconds instead
    "shuffle": False,  # the papers take mini-batches in fixed order
    "checkpoint_seconds": 60.0,  # training seconds between checkpoints (and one at the end)
}


def choose(kind: str, name: str, choices) -> str:
    """Return ``name`` if it is one of ``choices``, else raise a one-line ConfigError."""
    if name not in choices:
        raise ConfigError(f"unknown {kind} {name!r}; valid choices: {', '.join(sorted(choices))}")
    return name


def parse_value(name: str, text: Any, default: Any) -> Any:
    """Convert a ``--set`` string to the type of the setting's default."""
    if not isinstance(text, str):
        return text
    try:
        if isinstance(default, bool):
            lowered = text.lower()
            if lowered not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return lowered in ("true", "1", "yes")
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            return float(text)
        return text
    except ValueError:
        kind = {bool: "true or false", int: "an integer", float: "a number"}.get(type(default), "a string")
        raise ConfigError(f"setting {name!r} expects {kind}, got {text!r}") from None


@dataclasses.dataclass(frozen=True)
class Budget:
    """How long to train: exactly one of steps, epochs or training seconds.

    Seconds count training steps only (evaluation excluded, as in the HIG paper); the run
    stops at the first step that reaches the budget.
    """

    steps: int | None = None
    epochs: int | None = None
    seconds: float | None = None

    def __post_init__(self):
        given = [k for k in ("steps", "epochs", "seconds") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ConfigError("give exactly one budget: --steps N, --epochs E or --seconds S")
        if getattr(self, given[0]) <= 0:
            raise ConfigError(f"the budget --{given[0]} must be positive")

    @property
    def kind(self) -> str:
        return next(k for k in ("steps", "epochs", "seconds") if getattr(self, k) is not None)

    @property
    def amount(self) -> float:
        return getattr(self, self.kind)

    def to_dict(self) -> dict[str, float]:
        """``{kind: amount}``, as written in config.json, summary.json and study.json."""
        return {self.kind: self.amount}

    def __str__(self):
        return f"{self.amount:g} {self.kind}"


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """Everything needed to re-run a training run exactly (written as ``config.json``)."""

    problem: str
    method: str
    seed: int
    budget: Budget
    problem_settings: dict[str, Any]
    hyperparameters: dict[str, Any]
    batch_size: int
    eval_every: int = 0
    eval_seconds: float = 0.0
    shuffle: bool = False
    checkpoint_seconds: float = 60.0

    def to_dict(self) -> dict[str, Any]:
        out = dataclasses.asdict(self)
        out["budget"] = self.budget.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunConfig:
        data = dict(data)
        data["budget"] = Budget(**data["budget"])
        fields = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in fields})

    def digest(self) -> str:
        """A stable hash of the canonical configuration (never Python's ``hash()``)."""
        text = json.dumps(self.to_dict(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:10]


def valid_settings(problem: str, method: str) -> dict[str, Any]:
    """Every settable name for this problem and method, with its default."""
    return {**PROBLEMS[problem].settings(), **hyperparameters(method), **TRAIN_SETTINGS}


def make_config(
    problem: str,
    method: str,
    *,
    budget: Budget,
    seed: int = 0,
    settings: dict[str, Any] | None = None,
) -> RunConfig:
    """Resolve a run: paper defaults for (problem, method), then the user's ``settings``.

    ``settings`` may name problem settings, method hyperparameters or training settings;
    values may be strings (from the command line) and are converted to the right type.
    """
    choose("problem", problem, PROBLEMS)
    choose("method", method, METHODS)
    settings = dict(settings or {})
    valid = valid_settings(problem, method)
    for name in settings:
        if name not in valid:
            raise ConfigError(
                f"unknown setting {name!r} for {problem}/{method}; valid choices: {', '.join(sorted(valid))}"
            )
    problem_cls = PROBLEMS[problem]
    paper = problem_cls.defaults_for(method)
    problem_settings = {
        k: parse_value(k, settings.get(k, d), d) for k, d in problem_cls.settings().items()
    }
    hyper = {
        k: parse_value(k, settings.get(k, paper.get(k, d)), d) for k, d in hyperparameters(method).items()
    }
    train = {
        k: parse_value(k, settings.get(k, paper.get(k, d)), d if d is not None else 0)
        for k, d in TRAIN_SETTINGS.items()
    }
    try:  # the method checks its own hyperparameters (e.g. route choices) on construction
        METHODS[method](**hyper)
    except (ValueError, TypeError) as e:
        raise ConfigError(str(e)) from None
    if train["batch_size"] <= 0:
        raise ConfigError(f"batch_size must be positive, got {train['batch_size']}")
    return RunConfig(
        problem=problem,
        method=method,
        seed=int(seed),
        budget=budget,
        problem_settings=problem_settings,
        hyperparameters=hyper,
        **train,
    )
