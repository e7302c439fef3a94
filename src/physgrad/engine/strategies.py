"""The strategies around the training loop, one decision each: :class:`StopRule` (when the
budget is spent), :class:`EvalSchedule` (when to evaluate), :class:`ChunkSize` (how many
steps one dispatch takes), :class:`Placement` (where arrays live: one device or a data
mesh over devices and processes) and :class:`Fidelity` (PRDP's solver refinement). The
progress meter is :mod:`physgrad.engine.progress`'s.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import numpy as np

from .. import distributed
from ..errors import ConfigError
from ..problems import AbstractProblem
from . import prdp as prdp_control
from .types import Budget, Setup, Stage, TrainSettings, TrainState


@dataclasses.dataclass
class StopRule:
    """The budget: steps, epochs (each stage at its own batch size) or training seconds;
    with ``wall_cap`` > 0 also the training wall-clock reaching that many seconds."""

    budget: Budget
    setup: Setup
    wall_cap: float = 0.0

    def met(self, step: int, train_time: float) -> bool:
        return self.budget_met(step, train_time) or self.capped(train_time)

    def capped(self, train_time: float) -> bool:
        return self.wall_cap > 0 and train_time >= self.wall_cap

    def budget_met(self, step: int, train_time: float) -> bool:
        return self.budget.met(step, train_time, self.setup.epochs)

    def steps_left(self, step: int, limit: int) -> int:
        """The fewest steps after ``step`` that meet a steps or epochs budget, at most
        ``limit`` (a seconds budget: ``limit``; time is :class:`ChunkSize`'s to bound)."""
        return self.budget.steps_left(step, limit, self.setup.epochs)

    def seconds_left(self, train_time: float) -> float:
        """Training seconds left to a seconds budget (else inf)."""
        return self.budget.seconds_left(train_time)


@dataclasses.dataclass
class EvalSchedule:
    """Every ``eval_seconds`` of training time if set (equal points per curve in a
    wall-clock comparison), else every ``eval_every`` steps, else every epoch of the
    current stage; always at the end of a stage and of the budget."""

    settings: TrainSettings
    next_time: float = 0.0

    def start(self, train_time: float):
        self.next_time = self._after(train_time)

    def _after(self, train_time: float) -> float:
        every = self.settings.eval_seconds
        return every * (1 + math.floor(train_time / every)) if every > 0 else math.inf

    def due(self, step: int, train_time: float, stage: Stage, boundary: bool) -> bool:
        if boundary:
            return True
        if self.settings.eval_seconds > 0:
            if train_time < self.next_time:
                return False
            self.next_time = self._after(train_time)
            return True
        if self.settings.eval_every:
            return step % self.settings.eval_every == 0
        return (step - stage.start) % stage.steps_per_epoch == 0

    def steps_left(self, step: int, stage: Stage) -> int | None:
        """Steps after ``step`` to the next evaluation a step schedule makes (every
        ``eval_every`` steps, else every epoch of ``stage``); None for ``eval_seconds``."""
        if self.settings.eval_seconds > 0:
            return None
        if self.settings.eval_every:
            return self.settings.eval_every - step % self.settings.eval_every
        return stage.steps_per_epoch - (step - stage.start) % stage.steps_per_epoch

    def seconds_left(self, train_time: float) -> float:
        """Training seconds to the next evaluation of an ``eval_seconds`` schedule (else inf)."""
        return self.next_time - train_time if self.settings.eval_seconds > 0 else math.inf


@dataclasses.dataclass
class ChunkSize:
    """How many steps the next dispatch takes (:func:`physgrad.engine.step.make_steps`).

    As many as fit in ``target_seconds`` of training at the last chunk's time per step,
    at most ``limit`` (what the step-counted events allow: the budget, the epoch, the stage,
    the next evaluation) and within half the time left to a time-counted event (a seconds
    budget, ``eval_seconds``, the next checkpoint), so a chunk never runs past one: the
    chunks halve towards it and the last steps before it are taken one at a time, as a
    step-by-step loop takes them. The first chunk after a new compiled step is one step
    (its time per step is not known yet).

    Why ``target_seconds`` (0.25 s): long enough that one dispatch and one read-back per
    chunk cost nothing per step, short enough that Ctrl-C, SIGTERM and the progress meter
    answer within it."""

    target_seconds: float = 0.25
    per_step: float | None = None  # training seconds per step of the last chunk

    def reset(self):
        """A new compiled step (a stage switch, PRDP's refinement): its speed is unknown."""
        self.per_step = None

    def observe(self, steps: int, seconds: float):
        if steps > 0:
            self.per_step = seconds / steps

    def size(self, limit: int, *, seconds_left: float = math.inf) -> int:
        """The next chunk's steps: ``1 <= size <= limit``."""
        if self.per_step is None:
            return 1
        seconds = min(self.target_seconds, seconds_left / 2)
        return max(1, min(limit, int(seconds / max(self.per_step, 1e-9))))


@dataclasses.dataclass
class Placement:
    """Where arrays live: one device, or a data mesh over devices and processes."""

    devices: int | Sequence[jax.Device] | None = 1  # pyright: ignore[reportInvalidTypeForm]

    def __post_init__(self):
        self.mesh = distributed.make_mesh(self.devices)
        self.writer = distributed.is_writer()

    def put(self, tree):
        return distributed.replicate(tree, self.mesh)

    def scope(self):
        return distributed.use_mesh(self.mesh)

    def clock(self, seconds: float) -> float:
        """Process 0's training time on every process, so that seconds budgets and
        ``eval_seconds`` stop and evaluate all processes at the same step."""
        if jax.process_count() == 1:
            return seconds
        from jax.experimental import multihost_utils

        return float(multihost_utils.broadcast_one_to_all(np.float64(seconds)))

    def agree(self, count: int) -> int:
        """Process 0's ``count`` on every process: every process must dispatch the same
        chunk (its collectives run once per step)."""
        if jax.process_count() == 1:
            return count
        from jax.experimental import multihost_utils

        return int(multihost_utils.broadcast_one_to_all(np.int32(count)))

    def barrier(self, name: str):
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices(name)


@dataclasses.dataclass
class Fidelity:
    """PRDP (Bhatia et al., ICLR 2025): start an iterative solver at few iterations and
    refine on validation plateaus; the problem declares the setting (``refinable_setting``)."""

    settings: TrainSettings
    name: str | None  # the refinable problem setting, or None
    full: int | None  # its value as given (the cap)

    @classmethod
    def of(cls, problem: AbstractProblem, settings: TrainSettings) -> Fidelity:
        name = problem.refinable_setting
        if settings.prdp and name is None:
            raise ConfigError("prdp needs a problem with an iterative solver (one that declares refinable_setting)")
        if settings.prdp:
            try:
                problem.check_refinable()
            except ConfigError:  # a typed refusal (errors.NotRefinable) keeps its type and fields
                raise
            except ValueError as e:
                raise ConfigError(str(e)) from None
        if settings.prdp and (settings.prdp_start < 1 or settings.prdp_increment < 1):
            raise ConfigError("prdp_start and prdp_increment must be >= 1")
        if settings.prdp and not (0 < settings.prdp_tau_stop <= 1 and 0 < settings.prdp_tau_step <= 1):
            raise ConfigError("prdp_tau_step and prdp_tau_stop must be in (0, 1]")
        return cls(settings, name, getattr(problem, name) if name else None)

    def _setting(self) -> tuple[str, int]:
        """The refinable setting and its cap; only for a problem that declares one (with prdp
        on, ``of`` checked that it does)."""
        assert self.name is not None and self.full is not None
        return self.name, self.full

    @staticmethod
    def _controller(state: TrainState) -> dict:
        assert state.prdp is not None  # with prdp on, initial() made it
        return state.prdp

    def initial(self) -> dict | None:
        return (
            prdp_control.initial_state(min(self.settings.prdp_start, self._setting()[1]))
            if self.settings.prdp
            else None
        )

    def iterations(self, state: TrainState) -> int:
        """The solver's iteration count at ``state``; only for a problem with a refinable setting."""
        return self._controller(state)["K"] if self.settings.prdp else self._setting()[1]

    def problem_at(self, setup: Setup, state: TrainState) -> Setup:
        if not self.settings.prdp:
            return setup
        name, k = self._setting()[0], self._controller(state)["K"]
        if getattr(setup.problem, name) == k:
            return setup
        return setup.with_problem(setup.problem.with_refined(k))

    def observe(self, state: TrainState, error: float) -> TrainState:
        s = self.settings
        new = prdp_control.update(self._controller(state), error, state.step, increment=s.prdp_increment,
                                  maximum=self._setting()[1], tau_step=s.prdp_tau_step, tau_stop=s.prdp_tau_stop)  # fmt: skip
        return state._replace(prdp=new)
