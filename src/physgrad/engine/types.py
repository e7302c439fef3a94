"""What the caller gives and what the run carries: the engine's types.

:class:`Budget`, :class:`Phase` and :class:`TrainSettings` are :func:`physgrad.fit`'s
arguments; :class:`Stage` and :class:`Setup` are what a run builds before its first step
(:mod:`physgrad.engine.setup`); :class:`TrainState` is the loop's state (and what a
checkpoint holds); :class:`Ending` is how the loop ends.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import equinox as eqx

from .. import checks
from ..errors import BudgetOutOfRange, ConfigError, NoBudget
from ..methods import AbstractMethod, Objective
from ..problems import AbstractProblem


# --- what the caller gives -----------------------------------------------------------------
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
            raise NoBudget()
        kind, amount = given[0], getattr(self, given[0])
        check = checks.POSITIVE if kind == "seconds" else checks.POSITIVE_INT
        if not check.valid(amount):  # a NaN or infinite budget would never be met
            raise BudgetOutOfRange(kind, amount, check.text)

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
class Phase:
    """A method for ``steps`` steps (None: until the budget is spent) at ``batch_size``
    (None: the problem's ``default_batch_size``)."""

    method: AbstractMethod
    steps: int | None = None
    batch_size: int | None = None
    name: str = ""  # how tables and summaries call it (default: the method's class name)

    def __post_init__(self):
        if not isinstance(self.method, AbstractMethod):
            raise ConfigError(
                f"Phase's method must be a physgrad method (e.g. physgrad.methods.Method), got {self.method!r}"
            )
        for field, value in (("steps", self.steps), ("batch_size", self.batch_size)):
            if value is not None and not checks.POSITIVE_INT.valid(value):
                raise ConfigError(f"Phase's {field} must be {checks.POSITIVE_INT.text} or None, got {value!r}")

    @property
    def label(self) -> str:
        """``name``, or the method's class name."""
        return self.name or type(self.method).__name__


@dataclasses.dataclass(frozen=True)
class TrainSettings:
    """How a run evaluates, orders its batches, checkpoints and refines its solver.

    Every field is checked by type and range on construction (:mod:`physgrad.checks`)."""

    eval_every: int = 0  # steps between full train/test evaluations; 0 = once per epoch
    eval_seconds: float = 0.0  # if > 0: evaluate every this many training seconds instead
    eval_samples: int = 0  # evaluate the train split on its first N samples only; 0 = all
    # None: the problem's ``default_shuffle`` (the papers' fixed order; a fresh permutation
    # every epoch for the time-steppers); True/False: shuffled or fixed for any problem
    shuffle: bool | None = None
    # None: the problem's ``default_fresh_samples``; True: every epoch after the first trains
    # on a new train split drawn by ``make_data`` (a stream, as the SIP paper), False: the
    # same training set every epoch
    fresh_samples: bool | None = None
    checkpoint_seconds: float = 60.0  # wall-clock seconds between checkpoints; also at every evaluation and the end
    prdp: bool = False  # refine the solver's iteration count on validation plateaus (physgrad.prdp)
    prdp_start: int = 1
    prdp_increment: int = 1
    prdp_tau_step: float = 0.98
    prdp_tau_stop: float = 0.9
    memory_guard: bool = True  # refuse a step that cannot fit in memory before it runs (physgrad.memory)
    # if > 0: stop as well once the training wall-clock reaches this many seconds, a cap beside
    # a steps (or calibrated) budget; the summary then says ``wall_capped``
    wall_cap: float = 0.0

    def __post_init__(self):
        checks.check_fields(self, "TrainSettings field")


# Settings that change how a run is guarded, not what it computes: a run resumes under
# either value (they are not part of a run's identity).
UNGUARDED_SETTINGS = ("memory_guard", "wall_cap")
# Settings added after runs were recorded without them, with the value those runs had: a
# recorded run resumes when the setting holds that value.
ADDED_SETTINGS = {"fresh_samples": False}


# --- built before the first step -------------------------------------------------------------
@dataclasses.dataclass
class Stage:
    """One stage of a run, built: its method, batch size, length and first global step."""

    method: AbstractMethod
    batch_size: int
    steps_per_epoch: int
    start: int
    steps: int | None  # None: until the budget is spent
    label: str = ""

    def contains(self, step: int) -> bool:
        return step >= self.start and (self.steps is None or step < self.start + self.steps)

    def steps_done(self, step: int) -> int:
        """How many of the run's first ``step`` steps this stage took."""
        local = max(step - self.start, 0)
        return local if self.steps is None else min(local, self.steps)


@dataclasses.dataclass
class Setup:
    """Everything a run builds before the first step: problem, data, split network,
    the problem's :class:`Objective` and the stages."""

    problem: AbstractProblem
    data: dict[str, Any]
    params: Any
    static: Any
    objective: Objective
    stages: list[Stage]

    @property
    def method(self) -> AbstractMethod:
        """The first (for a single method: the only) stage's method."""
        return self.stages[0].method

    @property
    def steps_per_epoch(self) -> int:
        return self.stages[0].steps_per_epoch

    def stage_index(self, step: int) -> int:
        """The stage that takes global step ``step`` (0-based)."""
        return next(i for i, s in enumerate(self.stages) if s.contains(step))

    def epochs(self, step: int) -> float:
        """Epochs done after ``step`` steps (each stage counts its own batch size)."""
        return sum(s.steps_done(step) / s.steps_per_epoch for s in self.stages)

    def network(self, params=None):
        return eqx.combine(self.params if params is None else params, self.static)

    def with_problem(self, problem: AbstractProblem) -> Setup:
        """The same network, data and stages on another instance of the problem (a
        fidelity schedule changes the solver's iteration count)."""
        return dataclasses.replace(self, problem=problem, objective=problem.objective(self.static))


# --- the loop state --------------------------------------------------------------------------
class TrainState(NamedTuple):
    """Everything the loop carries from step to step (and a checkpoint holds).

    ``params``/``opt_state`` are arrays (``state.eqx``); the rest are host scalars
    (``counters.json``): global step, stage index, training and compile seconds, the best
    test loss so far, per-statistic sums over all steps, the solver's summed iteration count,
    PRDP's controller state, the per-statistic [sum, count] since the last evaluation (so a
    resumed run logs the same averages) and the last finite training loss (a diverged run
    reports it). Checkpointing all of it makes a resumed run end exactly as an
    uninterrupted one."""

    params: Any
    opt_state: Any
    step: int = 0
    stage: int = 0
    train_time: float = 0.0
    compile_seconds: float = 0.0
    best_test_loss: float = math.inf
    stat_totals: dict = {}
    solver_iterations: int = 0
    prdp: dict | None = None
    stat_window: dict = {}
    last_finite_loss: float | None = None

    def counters(self) -> dict[str, Any]:
        return {k: getattr(self, k) for k in self._fields[2:]}


class Ending(NamedTuple):
    """How the loop ended: its last state and setup (PRDP may have refined the problem),
    ``status`` (``finished``, ``diverged``, ``interrupted`` by Ctrl-C or ``terminated`` by
    SIGTERM) and the step it diverged at."""

    state: TrainState
    setup: Setup
    status: str
    diverged_step: int | None = None
