"""Run configurations (the command line's and the studies'): names and settings resolved
against the registries, with clear errors."""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
from typing import Any

from ..checks import check_of, check_setting
from ..engine import ADDED_SETTINGS, UNGUARDED_SETTINGS, Budget, TrainSettings
from ..engine.record import CARRIED_OUT_SETTINGS, EVALUATION_CADENCE
from ..errors import ConfigError
from ..extras import MissingExtra, require
from .objects import problem_defaults
from .plugins import IMPORT_PATH, Registry
from .registry import METHODS, PROBLEMS, hyperparameters, is_optax_name, optax_method, paper_defaults

# Training-engine settings, settable with --set like problem and method settings: the batch
# size (None: the paper's for the method), every field of the engine's TrainSettings (their
# one definition, with its comments and ranges; shuffle and fresh_samples default to the
# problem's: train_settings) and no_network (optimise x itself for each test sample:
# problems/direct.py). RunConfig holds them as its ``settings`` (and ``no_network``).
TRAIN_SETTINGS: dict[str, Any] = {
    "batch_size": None,
    **{field.name: field.default for field in dataclasses.fields(TrainSettings)},
    "no_network": False,
}


def split_scope(key: str) -> tuple[str | None, str]:
    """``(method, name)`` of a ``--set`` key, the one parser of the method scope:
    ``("hig", "lr")`` for ``hig.lr``, ``(None, "lr")`` for ``lr``. (The bench adds a problem
    scope in front: ``sine.hig.lr``, :func:`physgrad.harness.bench.choices.scoped_settings`.)"""
    method, _, name = key.rpartition(".")
    return method or None, name


def choose(kind: str, name: str, choices, *, also: tuple[str, ...] = ()) -> str:
    """Return ``name`` if it is one of ``choices``, else raise a one-line ConfigError: an
    import path's or a left-out plugin's own line (:class:`~physgrad.harness.plugins.Registry`),
    or the valid choices (and the spellings ``also`` lists)."""
    if name not in choices:
        why = choices.why_not(name) if isinstance(choices, Registry) else None
        # a table of problems or methods also takes your own, by import path (docs/own-problem.md)
        own = f"; or your own: module:{'Class' if choices.kind == 'problem' else 'factory'}" if isinstance(choices, Registry) else ""  # fmt: skip
        raise ConfigError(why or f"unknown {kind} {name!r}; valid choices: {', '.join(sorted([*choices, *also]))}{own}")
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


def setting(name: str, value: Any, default: Any) -> Any:
    """A setting's value converted to its default's type (:func:`parse_value`) and checked
    by range (:func:`physgrad.checks.check_setting`; a training setting by the range its
    :class:`~physgrad.TrainSettings` field declares): one-line errors naming the valid range."""
    return check_setting(name, parse_value(name, value, default), default, check=check_of(TrainSettings, name))


@dataclasses.dataclass(frozen=True)
class Phase:
    """One stage of a run: a registered method with its hyperparameters and batch size.

    ``steps`` is the stage's length; the last stage has ``steps=None`` and runs until the
    budget is spent.
    """

    method: str
    hyperparameters: dict[str, Any]
    batch_size: int
    steps: int | None = None


def parse_method(spec: str) -> list[tuple[str, int | None]]:
    """A method or a method sequence: ``"hig"`` or ``"adam:2000,hig"`` (Adam for 2000 steps,
    then HIG from those parameters) → ``[("adam", 2000), ("hig", None)]``."""
    parts = [p.strip() for p in str(spec).split(",")]
    phases = []
    for i, part in enumerate(parts):
        name, sep, count = split_stage(part)
        if is_optax_name(name):
            try:
                optax_method(name)
            except ValueError as e:
                raise ConfigError(str(e)) from None
        else:
            choose("method", name, METHODS, also=("optax:NAME", "optax.contrib:NAME"))
        last = i == len(parts) - 1
        steps: int | None = None  # the last method's: until the budget is spent
        if sep:
            if last:
                raise ConfigError(f"the last method of {spec!r} runs until the budget is spent; drop ':{count}'")
            try:
                steps = int(count)
            except ValueError:
                raise ConfigError(f"method sequence {spec!r}: ':{count}' must be a number of steps") from None
            if steps <= 0:
                raise ConfigError(f"method sequence {spec!r}: {name} needs a positive number of steps")
        elif not last:
            raise ConfigError(f"method sequence {spec!r}: give {name}'s number of steps as {name}:N")
        phases.append((name, steps))
    return phases


def split_stage(part: str) -> tuple[str, str, str]:
    """``"adam:2000"`` → ``("adam", ":", "2000")``; an optax zoo name keeps its own colon:
    ``"optax:lion:2000"`` → ``("optax:lion", ":", "2000")``, ``"optax:lion"`` → ``("optax:lion", "", "")``;
    so does an import path: ``"mypkg.rules:my_rule:200"`` → ``("mypkg.rules:my_rule", ":", "200")``."""
    prefix = ""
    if is_optax_name(part):
        prefix, _, part = part.partition(":")
        prefix += ":"
    elif (path := IMPORT_PATH.match(part)) and part.partition(":")[0] not in METHODS:
        # an import path ``module:factory`` keeps its colon too (``adam:x`` stays Adam's count)
        rest = part[path.end() :]
        if not rest or rest.startswith(":"):
            return path.group(), rest[:1], rest[1:]
    name, sep, count = part.partition(":")
    return prefix + name, sep, count


def split_methods(text: str) -> list[str]:
    """A comma-separated list of methods where ``name:N,`` binds to the next entry:
    ``"adam,hig,adam:2000,hig"`` → ``["adam", "hig", "adam:2000,hig"]``."""
    out, pending = [], []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        pending.append(part)
        if not split_stage(part)[1]:
            out.append(",".join(pending))
            pending = []
    if pending:
        out.append(",".join(pending))  # parse_method reports the missing final method
    return out


def method_slug(spec: str) -> str:
    """A method spec as a file name: ``"adam:2000,hig"`` → ``"adam2000+hig"``."""
    return spec.replace(":", "").replace(",", "+")


def problem_slug(problem: str) -> str:
    """A problem name as a file name: an import path ``"mypkg.problems:Burgers"`` →
    ``"mypkg.problems.Burgers"`` (a ``:`` is refused by some file systems and tools)."""
    return problem.replace(":", ".")


def phase_methods(spec: str) -> list[str]:
    """The registered method names in a method (sequence) spec."""
    return [name for name, _ in parse_method(spec)]


# The settings added after run directories were first written, with the value that keeps
# the earlier behaviour: the one table of them. While they hold it they are left out of the
# digest (run directory names) and of run comparisons, so studies written before they
# existed still match and resume. Add a setting here when it joins an existing method or
# problem; a training setting declares it on its TrainSettings field (``earlier=``), which
# the engine's own records read as well (engine.ADDED_SETTINGS).
ADDED_LATER: dict[str, dict[str, dict[str, Any]]] = {
    "methods": {
        **{name: {"blocks": 8, "lanczos_steps": 64} for name in ("hig", "gn")},  # issue 7
        **{  # issue 54: the plateau schedule, off
            name: {"plateau_factor": 0.0, "plateau_patience": 10, "plateau_cooldown": 0, "plateau_every": 0}
            for name in ("one", "nog", "wig")
        },
        "khig": {"probes": 0},  # issue 51: G from every output row
    },
    "problems": {"poisson": {"dtype": "float32"}},  # issue 7
    "training": ADDED_SETTINGS,
}
_ABSENT = object()


# A configuration's training settings are resolved: ``shuffle`` and ``fresh_samples`` hold
# the problem's choice (make_config), never None. A record written without them (an older
# physgrad's) had them False.
RESOLVED_SETTINGS = TrainSettings(shuffle=False, fresh_samples=False)
_SETTING_NAMES = tuple(f.name for f in dataclasses.fields(TrainSettings))


@dataclasses.dataclass(frozen=True, init=False)
class RunConfig:
    """Everything needed to re-run a training run exactly (written as ``config.json``).

    ``method`` is the user's spec (``"hig"`` or ``"adam:2000,hig"``); ``phases`` holds each
    stage's resolved hyperparameters and batch size; ``settings`` the engine's
    :class:`~physgrad.TrainSettings`, resolved (``shuffle`` and ``fresh_samples`` as the
    problem chose them); ``no_network`` optimises x itself (problems/direct.py).

    ``config.json`` holds the settings flattened beside the other keys, as it always has
    (so every recorded run keeps its identity and its directory's name). The constructor
    takes them flattened as well (``RunConfig(..., eval_every=5)``, as ``from_dict`` and
    :func:`dataclasses.replace` pass them), and ``config.eval_every`` reads
    ``config.settings.eval_every``.
    """

    problem: str
    method: str
    seed: int
    budget: Budget
    problem_settings: dict[str, Any]
    phases: tuple[Phase, ...]
    settings: TrainSettings = RESOLVED_SETTINGS
    no_network: bool = False

    def __init__(
        self,
        problem: str,
        method: str,
        seed: int,
        budget: Budget,
        problem_settings: dict[str, Any],
        phases: tuple[Phase, ...],
        settings: TrainSettings = RESOLVED_SETTINGS,
        no_network: bool = False,
        **flat: Any,
    ):
        unknown = set(flat) - set(_SETTING_NAMES)
        if unknown:
            raise TypeError(f"RunConfig got unexpected settings {sorted(unknown)}")
        for name, value in (("problem", problem), ("method", method), ("seed", seed), ("budget", budget),
                            ("problem_settings", problem_settings), ("phases", phases),
                            ("settings", dataclasses.replace(settings, **flat) if flat else settings),
                            ("no_network", no_network)):  # fmt: skip
            object.__setattr__(self, name, value)

    def __getattr__(self, name: str) -> Any:
        # Only called for names that are not fields: a training setting reads through
        # ``settings`` (config.eval_seconds), as the flattened record spells it.
        if name in _SETTING_NAMES:
            return getattr(self.settings, name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    def to_dict(self) -> dict[str, Any]:
        """The record (``config.json``): the training settings flattened among the keys."""
        return {"problem": self.problem, "method": self.method, "seed": self.seed, "budget": self.budget.to_dict(),
                "problem_settings": copy.deepcopy(self.problem_settings),
                "phases": [dataclasses.asdict(p) for p in self.phases],
                **dataclasses.asdict(self.settings), "no_network": self.no_network}  # fmt: skip

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RunConfig:
        data = dict(data)
        data["budget"] = Budget.of(data["budget"])
        data["phases"] = tuple(Phase(**p) for p in data["phases"])
        known = {f.name for f in dataclasses.fields(cls)} | set(_SETTING_NAMES)
        return cls(**{k: v for k, v in data.items() if k in known and k != "settings"})

    def canonical_dict(self) -> dict[str, Any]:
        """``to_dict`` without the settings of :data:`ADDED_LATER` that hold their earlier
        value and without those that only guard a run (``UNGUARDED_SETTINGS``: the same run
        either way)."""
        later = ADDED_LATER["training"]
        out = {k: v for k, v in self.to_dict().items()
               if k not in UNGUARDED_SETTINGS and later.get(k, _ABSENT) != v}  # fmt: skip
        later = ADDED_LATER["problems"].get(self.problem, {})
        out["problem_settings"] = {k: v for k, v in out["problem_settings"].items() if later.get(k, _ABSENT) != v}
        for phase in out["phases"]:
            later = ADDED_LATER["methods"].get(phase["method"], {})
            phase["hyperparameters"] = {k: v for k, v in phase["hyperparameters"].items() if later.get(k, _ABSENT) != v}
        return out

    def identity(self) -> dict[str, Any]:
        """What makes this run the run it is, for resuming: the canonical configuration
        without its budget and without the settings that cannot change its numbers
        (:data:`NOT_IDENTITY`: how often it checkpoints; how often it evaluates, unless PRDP
        reads those evaluations). Compared after :func:`physgrad.engine.record.normalised`."""
        out = {k: v for k, v in self.canonical_dict().items() if k != "budget" and k not in NOT_IDENTITY}
        if not self.settings.prdp:
            out = {k: v for k, v in out.items() if k not in EVALUATION_CADENCE}
        return out

    def digest(self) -> str:
        """A stable hash of the canonical configuration (never Python's ``hash()``): the
        run directory's name in a study. The checkpoint interval is hashed at its default
        whatever it is (runs named before it left the identity keep their names)."""
        named = dataclasses.replace(self, **{k: getattr(RESOLVED_SETTINGS, k) for k in NOT_IDENTITY})
        text = json.dumps(named.canonical_dict(), sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:10]


# Settings that change how a run is carried out but never its numbers (the engine's
# record.CARRIED_OUT_SETTINGS): left out of its identity and hashed at their defaults in its
# name; the evaluation cadence is left out of the identity unless PRDP refines on it.
NOT_IDENTITY = CARRIED_OUT_SETTINGS


def valid_settings(problem: str, method: str) -> dict[str, Any]:
    """Every settable name for this problem and method (or sequence), with its default."""
    hyper = {}
    for name in phase_methods(method):
        hyper.update(hyperparameters(name))
    return {**problem_defaults(PROBLEMS[problem]), **hyper, **train_settings(problem)}


def train_settings(problem: str) -> dict[str, Any]:
    """The training settings and their defaults for ``problem`` (``shuffle`` and
    ``fresh_samples``: the problem's)."""
    cls = PROBLEMS[problem]
    return {**TRAIN_SETTINGS, "shuffle": cls.default_shuffle, "fresh_samples": cls.default_fresh_samples}


def make_config(
    problem: str,
    method: str,
    *,
    budget: Budget,
    seed: int = 0,
    settings: dict[str, Any] | None = None,
) -> RunConfig:
    """Resolve a run: paper defaults for (problem, method), then the user's ``settings``.

    ``method`` is a registered name or a sequence such as ``"adam:2000,hig"``. ``settings``
    may name problem settings, method hyperparameters or training settings; ``m.name``
    scopes a hyperparameter or batch size to the stages that use method ``m``. Values may
    be strings (from the command line) and are converted to the right type.
    """
    choose("problem", problem, PROBLEMS)
    require(PROBLEMS[problem].extra, f"the {problem} problem")  # one line naming the missing extra
    stages = parse_method(method)
    names = [name for name, _ in stages]
    valid = valid_settings(problem, method)
    scoped: dict[str, dict[str, Any]] = {}
    plain: dict[str, Any] = {}
    for key, value in (settings or {}).items():
        target, name = split_scope(key)
        if target and target not in names:
            raise ConfigError(
                f"setting {key!r}: {target!r} is not a method of {method!r}; valid choices: {', '.join(names)}"
            )
        if name not in valid:
            raise ConfigError(
                f"unknown setting {name!r} for {problem}/{method}; valid choices: {', '.join(sorted(valid))}"
            )
        if target:
            scoped.setdefault(target, {})[name] = value
        else:
            plain[name] = value
    # Problem and training settings belong to the whole run; a scoped one (e.g.
    # "hig.eval_every" in a study) applies to the runs whose method uses that stage.
    run_level = dict(plain)
    for values in scoped.values():
        run_level.update(values)
    problem_cls = PROBLEMS[problem]
    # Every value by type (parse_value) and range (physgrad.checks), before anything is built.
    problem_settings = {k: setting(k, run_level.get(k, d), d) for k, d in problem_defaults(problem_cls).items()}

    def stage_value(name, key, default, paper):
        return setting(key, scoped.get(name, {}).get(key, plain.get(key, paper.get(key, default))), default)

    phases = []
    for name, steps in stages:
        paper = paper_defaults(problem_cls, name)
        hyper = {k: stage_value(name, k, d, paper) for k, d in hyperparameters(name).items()}
        try:  # the method checks its own hyperparameters (e.g. route choices) on construction
            METHODS[name](**hyper)
        except MissingExtra:
            raise
        except (ValueError, TypeError) as e:
            raise ConfigError(str(e)) from None
        batch_size = stage_value(name, "batch_size", 0, paper)  # a positive integer (physgrad.checks.SHARED)
        phases.append(Phase(name, hyper, batch_size, steps))
    defaults = train_settings(problem)
    train = {k: setting(k, run_level.get(k, d), d) for k, d in defaults.items() if k != "batch_size"}
    if train["no_network"]:
        # Direct optimisation trains one x per test sample: a fresh draw every epoch would
        # swap the samples under their variables (the heat comparison then never converged).
        if "fresh_samples" in run_level and train["fresh_samples"]:
            raise ConfigError("fresh_samples=true cannot go with no_network: the samples are the variables' targets")
        train["fresh_samples"] = False
    no_network = train.pop("no_network")
    return RunConfig(
        problem=problem,
        method=method,
        seed=int(seed),
        budget=budget,
        problem_settings=problem_settings,
        phases=tuple(phases),
        settings=TrainSettings(**train),
        no_network=no_network,
    )
