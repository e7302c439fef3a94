"""What the caller gives and what the run carries: the engine's types.

:class:`Budget` (:class:`Steps`, :class:`Epochs` or :class:`Seconds`), :class:`Phase` and
:class:`TrainSettings` are :func:`physgrad.fit`'s arguments; :class:`Stage` and
:class:`Setup` are what a run builds before its first step (:mod:`physgrad.engine.setup`);
:class:`TrainState` is the loop's state (and what a checkpoint holds); :class:`Ending` is
how the loop ends.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple, final

import equinox as eqx

from .. import checks
from ..errors import BudgetOutOfRange, ConfigError, NoBudget
from ..methods import AbstractMethod, Objective
from ..problems import AbstractProblem
from .splits import TEST_SPLIT, AbstractSplit


# --- what the caller gives -----------------------------------------------------------------
class _KeywordSpelling(abc.ABCMeta):
    """``Budget(steps=N)`` is ``Steps(N)``: the keyword spelling, as ``config.json`` writes a
    budget (``{"steps": N}``), builds the final class it names (:meth:`Budget.of`)."""

    def __call__(cls, *args: Any, **kwargs: Any) -> Any:  # Any: Budget(...) is one of its final classes
        if cls is Budget:
            given = dict(zip(("steps", "epochs", "seconds"), args), **kwargs)
            return Budget.of({k: v for k, v in given.items() if v is not None})
        return super().__call__(*args, **kwargs)


@dataclasses.dataclass(frozen=True)
class Budget(metaclass=_KeywordSpelling):
    """How long to train: a number of steps (:class:`Steps`), of epochs (:class:`Epochs`,
    each stage counted at its own batch size) or of training seconds (:class:`Seconds`).

    Seconds count training steps only (evaluation excluded, as in the HIG paper); the run
    stops at the first step that reaches the budget. ``Budget(steps=N)`` builds ``Steps(N)``.

    Each budget answers, for a run after ``step`` steps and ``seconds`` training seconds
    (``epochs_at``: the run's step-to-epochs map, :meth:`Setup.epochs`), whether it is met
    (:meth:`met`) and how many steps are left (:meth:`steps_left`)."""

    amount: Any
    kind: ClassVar[str]  # its key in config.json, summary.json and study.json
    check: ClassVar[checks.Check]  # the range of its amount

    def __post_init__(self):
        if not self.check.valid(self.amount):  # a NaN or infinite budget would never be met
            raise BudgetOutOfRange(self.kind, self.amount, self.check.text)

    @staticmethod
    def of(record: dict[str, Any]) -> Budget:
        """The budget a record writes as ``{kind: amount}`` (``{"steps": 2000}``)."""
        if len(record) != 1 or not set(record) <= set(_BUDGETS):
            unknown = set(record) - set(_BUDGETS)
            if unknown:
                raise TypeError(f"Budget() got an unexpected keyword argument {sorted(unknown)[0]!r}")
            raise NoBudget()
        ((kind, amount),) = record.items()
        return _BUDGETS[kind](amount)

    @abc.abstractmethod
    def done(self, step: int, seconds: float, epochs_at: Callable[[int], float]) -> float:
        """How much of the budget a run after ``step`` steps and ``seconds`` training seconds
        has spent, in the budget's unit."""

    @abc.abstractmethod
    def spent(self, step: int, seconds: float, epochs_at: Callable[[int], float]) -> str:
        """What a run after ``step`` steps and ``seconds`` training seconds has spent, in words
        ("12 steps")."""

    @abc.abstractmethod
    def met(self, step: int, seconds: float, epochs_at: Callable[[int], float]) -> bool:
        """Whether a run after ``step`` steps and ``seconds`` training seconds has spent it."""

    @abc.abstractmethod
    def first_met_at(self, step: int, epochs_at: Callable[[int], float]) -> bool:
        """Whether ``step`` is the first step that meets it (a recorded run ended exactly at
        this budget); a seconds budget cannot tell (False)."""

    @abc.abstractmethod
    def steps_left(self, step: int, limit: int, epochs_at: Callable[[int], float]) -> int:
        """The fewest steps after ``step`` that meet it, at most ``limit`` (a seconds budget:
        ``limit``; time is for :meth:`seconds_left` to bound)."""

    @abc.abstractmethod
    def seconds_left(self, seconds: float) -> float:
        """Training seconds left after ``seconds`` (inf for a budget counted in steps)."""

    @abc.abstractmethod
    def meter_total(self, steps_per_epoch: int) -> float:
        """The progress meter's full length: steps, or seconds for a seconds budget."""

    @abc.abstractmethod
    def meter(self, step: int, seconds: float, total: float) -> tuple[float, float]:
        """The progress meter's ``(done, seconds left)`` out of ``total`` (:meth:`meter_total`)."""

    def to_dict(self) -> dict[str, float]:
        """``{kind: amount}``, as written in config.json, summary.json and study.json."""
        return {self.kind: self.amount}

    def __str__(self):
        return f"{self.amount:g} {self.kind}"


def _step_meter(step: int, seconds: float, total: float) -> tuple[float, float]:
    """A budget counted in steps: done steps, and the seconds left at the mean time per step."""
    return step, (total - step) * seconds / max(step, 1)


@final
@dataclasses.dataclass(frozen=True)
class Steps(Budget):
    """``amount`` training steps."""

    amount: int
    kind: ClassVar[str] = "steps"
    check: ClassVar[checks.Check] = checks.POSITIVE_INT

    def done(self, step, seconds, epochs_at):
        return step

    def spent(self, step, seconds, epochs_at):
        return f"{step} steps"

    def met(self, step, seconds, epochs_at):
        return step >= self.amount

    def first_met_at(self, step, epochs_at):
        return step == self.amount

    def steps_left(self, step, limit, epochs_at):
        return max(1, min(limit, int(self.amount) - step))

    def seconds_left(self, seconds):
        return math.inf

    def meter_total(self, steps_per_epoch):
        return self.amount

    def meter(self, step, seconds, total):
        return _step_meter(step, seconds, total)


# Epochs are sums of fractions (each stage at its own batch size): met within this much.
_EPOCH_TOLERANCE = 1e-9


@final
@dataclasses.dataclass(frozen=True)
class Epochs(Budget):
    """``amount`` epochs: passes over the training split, each stage counted at its own
    batch size (:meth:`Setup.epochs`)."""

    amount: int
    kind: ClassVar[str] = "epochs"
    check: ClassVar[checks.Check] = checks.POSITIVE_INT

    def done(self, step, seconds, epochs_at):
        return epochs_at(step)

    def spent(self, step, seconds, epochs_at):
        return f"{epochs_at(step):g} epochs"

    def met(self, step, seconds, epochs_at):
        return epochs_at(step) >= self.amount - _EPOCH_TOLERANCE

    def first_met_at(self, step, epochs_at):
        return epochs_at(step - 1) < self.amount - _EPOCH_TOLERANCE

    def steps_left(self, step, limit, epochs_at):
        low, high = 1, limit  # epochs_at(step) grows with step: the first step that meets it
        if not self.met(step + high, 0.0, epochs_at):
            return limit
        while low < high:
            middle = (low + high) // 2
            low, high = (low, middle) if self.met(step + middle, 0.0, epochs_at) else (middle + 1, high)
        return low

    def seconds_left(self, seconds):
        return math.inf

    def meter_total(self, steps_per_epoch):
        return self.amount * steps_per_epoch

    def meter(self, step, seconds, total):
        return _step_meter(step, seconds, total)


@final
@dataclasses.dataclass(frozen=True)
class Seconds(Budget):
    """``amount`` seconds of training (evaluation and compilation excluded)."""

    amount: float
    kind: ClassVar[str] = "seconds"
    check: ClassVar[checks.Check] = checks.POSITIVE

    def done(self, step, seconds, epochs_at):
        return seconds

    def spent(self, step, seconds, epochs_at):
        return f"{seconds:.4g} training seconds"

    def met(self, step, seconds, epochs_at):
        return seconds >= self.amount

    def first_met_at(self, step, epochs_at):
        return False

    def steps_left(self, step, limit, epochs_at):
        return limit

    def seconds_left(self, seconds):
        return self.amount - seconds

    def meter_total(self, steps_per_epoch):
        return self.amount

    def meter(self, step, seconds, total):
        return seconds, max(total - seconds, 0.0)


_BUDGETS: dict[str, type[Budget]] = {cls.kind: cls for cls in (Steps, Epochs, Seconds)}


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

    Every field declares its range (:func:`physgrad.checks.declared`) and is checked by type
    and range on construction."""

    # steps between full train/test evaluations; 0 = once per epoch
    eval_every: int = checks.declared(0, checks.NON_NEGATIVE_INT)
    # if > 0: evaluate every this many training seconds instead
    eval_seconds: float = checks.declared(0.0, checks.NON_NEGATIVE)
    # evaluate the train split on its first N samples only; 0 = all
    eval_samples: int = checks.declared(0, checks.NON_NEGATIVE_INT)
    # None: the problem's ``default_shuffle`` (the papers' fixed order; a fresh permutation
    # every epoch for the time-steppers); True/False: shuffled or fixed for any problem
    shuffle: bool | None = checks.declared(None, checks.FLAG)
    # None: the problem's ``default_fresh_samples``; True: every epoch after the first trains
    # on a new train split drawn by ``make_data`` (a stream, as the SIP paper), False: the
    # same training set every epoch. Runs recorded before it existed had False.
    fresh_samples: bool | None = checks.declared(None, checks.FLAG, earlier=False)
    # wall-clock seconds between checkpoints; also at every evaluation and the end
    checkpoint_seconds: float = checks.declared(60.0, checks.NON_NEGATIVE)
    # refine the solver's iteration count on validation plateaus (physgrad.engine.prdp)
    prdp: bool = checks.declared(False, checks.FLAG)
    prdp_start: int = checks.declared(1, checks.POSITIVE_INT)
    prdp_increment: int = checks.declared(1, checks.POSITIVE_INT)
    prdp_tau_step: float = checks.declared(0.98, checks.UNIT)
    prdp_tau_stop: float = checks.declared(0.9, checks.UNIT)
    # refuse a step that cannot fit in memory before it runs (physgrad.engine.memory)
    memory_guard: bool = checks.declared(True, checks.FLAG, guards=True)
    # if > 0: stop as well once the training wall-clock reaches this many seconds, a cap beside
    # a steps (or calibrated) budget; the summary then says ``wall_capped``
    wall_cap: float = checks.declared(0.0, checks.NON_NEGATIVE, guards=True)

    def __post_init__(self):
        checks.check_fields(self, "TrainSettings field")


# Settings that change how a run is guarded, not what it computes: a run resumes under
# either value (they are not part of a run's identity). Read from the fields' declarations.
UNGUARDED_SETTINGS = tuple(f.name for f in dataclasses.fields(TrainSettings) if f.metadata["guards"])
# Settings added after runs were recorded without them, with the value those runs had: a
# recorded run resumes when the setting holds that value. Read from the fields' declarations.
ADDED_SETTINGS = {f.name: f.metadata["earlier"] for f in dataclasses.fields(TrainSettings) if "earlier" in f.metadata}


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
    """Everything a run builds before the first step: problem, data (``split`` of the
    problem's), split network, the problem's :class:`Objective` and the stages."""

    problem: AbstractProblem
    data: dict[str, Any]
    params: Any
    static: Any
    objective: Objective
    stages: list[Stage]
    split: AbstractSplit = TEST_SPLIT  # applied again to every fresh draw of training data

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
    uninterrupted one.

    ``cpu_seconds`` and ``cpu_steps`` are the run's CPU seconds in this process
    (:func:`~physgrad.engine.cpu_clock.run_cpu_time`) over the training chunks it ran and
    the steps they took (:data:`SESSION_COUNTERS`: not checkpointed, so a resumed run counts
    its own session's steps only; CPU seconds are a process's own, and a checkpoint written
    before they existed loads alike)."""

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
    cpu_seconds: float = 0.0
    cpu_steps: int = 0

    def counters(self) -> dict[str, Any]:
        """The host scalars a checkpoint keeps (``counters.json``): all but the arrays and
        :data:`SESSION_COUNTERS`."""
        return {k: getattr(self, k) for k in self._fields[2:] if k not in SESSION_COUNTERS}


# TrainState's counters of one process's session, never checkpointed: a resumed run starts them at 0.
SESSION_COUNTERS = ("cpu_seconds", "cpu_steps")


class Ending(NamedTuple):
    """How the loop ended: its last state and setup (PRDP may have refined the problem),
    ``status`` (``finished``, ``diverged``, ``interrupted`` by Ctrl-C or ``terminated`` by
    SIGTERM) and the step it diverged at."""

    state: TrainState
    setup: Setup
    status: str
    diverged_step: int | None = None
