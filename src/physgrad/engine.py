"""The training engine: one run of methods on a problem, with objects in and a run directory out.

    physgrad.fit(problem, method, budget=Budget(steps=2000), out="runs/mine", seed=0)

``problem`` is any :class:`physgrad.problems.AbstractProblem` instance (the user's own
too: no registry), ``method`` an engine method (:class:`physgrad.methods.Method`: a rule and
an optax transformation) or a sequence of :class:`Phase` (e.g. Adam for 1,413 steps, then
HIG from those parameters). One run::

    data    = problem.make_data(fold_in(key(seed), 0))
    network = problem.initial_network(fold_in(key(seed), 1), data)
    loop:  state = step(state, batch)                      # one jitted function per step
           every epoch / eval_every steps / eval_seconds: full train and test metrics

The loop (:func:`_loop`) reads in one screen; everything around it is a small strategy
object: :class:`StopRule` (the budget), :class:`EvalSchedule`, :class:`Placement` (devices and
processes), :class:`Steps` (the training data, batch order and each stage's compiled step,
checked by the memory guard, :mod:`physgrad.memory`), :class:`Fidelity` (PRDP's solver
refinement), :class:`Recorder` (evaluation and ``metrics.csv``), :class:`Checkpointer`, and
the progress meter. The loop state is one typed value, :class:`TrainState`, which is what a
checkpoint holds.

A run directory holds ``config.json`` (what the caller says identifies the run; the command
line writes its :class:`~physgrad.config.RunConfig`), ``metrics.csv`` (long format: step,
wall_time, split, metric, value), ``env.json``, ``summary.json``, ``test_cases.json``,
``params.eqx`` (the final network) and ``checkpoint/`` for ``resume``. Wall time counts
training steps only: compilation (``compile_seconds``) and evaluation are excluded, so equal
budgets compare update rules, not tracing.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import functools
import io
import json
import math
import os
import platform
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import checks, distributed, memory, programs, rundir
from . import prdp as prdp_control
from .errors import ConfigError
from .methods import AbstractMethod, Objective
from .nets import parameter_count
from .precision import float64_scope, x64_enabled
from .problems import AbstractProblem
from .progress import AbstractProgressMeter, NoProgressMeter

METRICS_HEADER = ("step", "wall_time", "split", "metric", "value")
FINAL_STATUSES = ("finished", "diverged")


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
            raise ConfigError("give exactly one budget: Budget(steps=N), Budget(epochs=E) or Budget(seconds=S)",
                              flags="give exactly one budget: --steps N, --epochs E or --seconds S")  # fmt: skip
        kind, amount = given[0], getattr(self, given[0])
        check = checks.POSITIVE if kind == "seconds" else checks.POSITIVE_INT
        if not check.valid(amount):  # a NaN or infinite budget would never be met
            raise ConfigError(f"Budget({kind}={amount!r}): {kind} must be {check.text}",
                              flags=f"--{kind} must be {check.text}, got {amount!r}")  # fmt: skip

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

    def __post_init__(self):
        checks.check_fields(self, "TrainSettings field")


# Settings that change how a run is guarded, not what it computes: a run resumes under
# either value (they are not part of a run's identity).
UNGUARDED_SETTINGS = ("memory_guard",)
# Settings added after runs were recorded without them, with the value those runs had: a
# recorded run resumes when the setting holds that value.
ADDED_SETTINGS = {"fresh_samples": False}
_ABSENT = object()


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


def build_setup(problem: AbstractProblem, phases: Sequence[Phase], seed: int) -> Setup:
    """Data, network and stages (deterministic per seed); every method is checked against
    the problem's declared pieces, with one-line errors."""
    key = jax.random.key(seed)
    try:
        data = problem.make_data(jax.random.fold_in(key, 0))
    except ValueError as e:
        raise ConfigError(f"{problem.name}: {e}") from None
    _check_data(problem, data)
    try:
        network = initial_network(problem, jax.random.fold_in(key, 1), data)
    except (ValueError, TypeError) as e:  # e.g. an activation the network does not know
        if isinstance(e, _NOT_TRACEABLE):
            raise
        raise ConfigError(f"{problem.name}: {' '.join(str(e).split())}") from None
    params, static = eqx.partition(network, eqx.is_inexact_array)
    objective = problem.objective(static)
    return Setup(problem, data, params, static, objective, _stages(problem, phases, objective, data))


def _check_data(problem: AbstractProblem, data: Any) -> None:
    """``make_data``'s result: a dict with ``train`` and ``test`` splits (``val`` optional),
    each with at least one sample and one leading (sample) axis shared by its arrays."""
    if not isinstance(data, dict) or not {"train", "test"} <= set(data):
        got = f"a dict with keys {sorted(data)}" if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{problem.name}: make_data must return {{'train': samples, 'test': samples}}, got {got}")
    for split, samples in data.items():
        if samples is None and split not in ("train", "test"):
            continue
        lengths = {np.shape(x)[0] if np.ndim(x) else None for x in jax.tree.leaves(samples)}
        if not lengths or lengths == {0}:
            raise ConfigError(f"{problem.name}: make_data's {split!r} split is empty (0 samples); every split needs "
                              "at least one sample")  # fmt: skip
        if len(lengths) > 1 or None in lengths:
            raise ConfigError(f"{problem.name}: the arrays of make_data's {split!r} split must share their leading "
                              f"(sample) axis, got lengths {sorted(lengths, key=str)}")  # fmt: skip


def scalar_loss(loss: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
    """``loss`` checked to return one number per sample (checked while tracing: free). A
    loss returning a vector would otherwise be averaged with the batch, silently scaling
    every direction by 1/its size."""

    def checked(y, sample):
        value = loss(y, sample)
        if jnp.shape(value) != ():
            raise ConfigError(f"the problem's loss(y, sample) must return a scalar for one sample, got shape "
                              f"{tuple(jnp.shape(value))}; reduce it inside loss (e.g. jnp.sum)")  # fmt: skip
        return value

    return checked


@eqx.filter_jit
def _initial_network_jit(problem: AbstractProblem, key, data):
    return problem.initial_network(key, data)


_NOT_TRACEABLE = (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                  jax.errors.TracerBoolConversionError, jax.errors.TracerIntegerConversionError)  # fmt: skip


def initial_network(problem: AbstractProblem, key, data) -> eqx.Module:
    """``problem.initial_network(key, data)`` as one compiled program (shared by every seed
    of the problem) instead of hundreds of eagerly dispatched operations; a network built
    by host code that cannot be traced is built eagerly, as written."""
    try:
        return _initial_network_jit(problem, key, data)
    except _NOT_TRACEABLE:
        return problem.initial_network(key, data)


def _stages(
    problem: AbstractProblem, phases: Sequence[Phase], objective: Objective, data, check: bool = True
) -> list[Stage]:
    """The phases as stages (curricula expanded), each method checked against the problem
    (unless ``check`` is False)."""
    n_train = jax.tree.leaves(data["train"])[0].shape[0]
    stages, start = [], 0
    for phase in phases:
        name = phase.name or type(phase.method).__name__
        batch_size = phase.batch_size or problem.default_batch_size
        if batch_size > n_train:
            raise ConfigError(f"batch_size {batch_size} exceeds the {n_train} training samples")
        try:
            if check:
                phase.method.check(objective)
            phase.method.check_batch_size(batch_size)
        except ValueError as e:
            raise ConfigError(f"{name} on {problem.name}: {e}") from None
        per_epoch, phase_start = n_train // batch_size, start
        expanded = phase.method.stages()
        for stage_method, epochs in expanded:
            if epochs is not None:  # a curriculum stage before the last
                steps = max(1, round(epochs * per_epoch))
            elif phase.steps is not None:  # the phase's remaining steps
                steps = max(1, phase.steps - (start - phase_start))
            else:
                steps = None
            label = name + (f"[{stage_method.stage_label()}]" if len(expanded) > 1 else "")
            stages.append(Stage(stage_method, batch_size, per_epoch, start, steps, label))
            start += steps or 0
    return stages


def preflight(problem: AbstractProblem, phases: Sequence[Phase], seed: int, mesh=None) -> None:
    """The memory guard's first look, before any data exist: every stage's footprint
    (:meth:`~physgrad.AbstractMethod.footprint`) from the shapes of the data and the
    network alone (``eqx.filter_eval_shape``: nothing is generated or initialised), so a
    step that cannot fit is refused in seconds, not after minutes of data generation.

    What the run will hold besides the step (the dataset, the parameters and each stage's
    optimizer state) is not in memory yet; it is counted against the available memory, so
    that a batch size suggested here passes the check after the data exist.

    Problems whose data cannot be traced abstractly (made by NumPy code or read from a
    cache) are skipped here; their steps are checked after the data exist, before
    compiling (:class:`Steps`); so are settings that :func:`build_setup` refuses (it says why)."""
    key = jax.random.key(seed)
    try:
        data = eqx.filter_eval_shape(problem.make_data, jax.random.fold_in(key, 0))
        network = eqx.filter_eval_shape(problem.initial_network, jax.random.fold_in(key, 1), data)
        abstract = lambda x: isinstance(x, jax.ShapeDtypeStruct) and jnp.issubdtype(x.dtype, jnp.inexact)  # noqa: E731
        params, static = eqx.partition(network, abstract)
        # Non-float arrays stay with the network's static part: zero views of their shape.
        static = jax.tree.map(lambda x: memory.stand_in(x, None) if isinstance(x, jax.ShapeDtypeStruct) else x, static)
        objective = _deferred_objective(lambda: problem.objective(static))
        # build_setup checks the methods (some checks build solvers)
        stages = _stages(problem, phases, objective, data, check=False)
    except Exception:  # noqa: BLE001 — not traceable abstractly, or a setting build_setup will report
        return
    for stage in stages:
        if stage.batch_size % distributed.mesh_size(mesh):
            continue  # reported by the run's own check
        batch = memory.stand_in(data["train"], stage.batch_size)
        try:
            resident = memory.tree_bytes((data, params, _optimizer_state_shape(stage.method, params)))
            memory.check_step_fits(stage.method, objective, params, batch, devices=_devices(mesh), label=stage.label,
                                   resident=resident)  # fmt: skip
        except ConfigError:
            raise
        except Exception:  # noqa: BLE001 — a footprint that needs concrete values: checked once they exist
            return


def _optimizer_state_shape(method: AbstractMethod, params) -> Any:
    """The shapes of ``method.init(params)`` (None where they cannot be traced abstractly)."""
    try:
        return jax.eval_shape(method.init, params)
    except Exception:  # noqa: BLE001 — an optimizer whose init needs concrete values: not counted
        return None


def _deferred_objective(make: Callable[[], Objective]) -> Objective:
    """An :class:`Objective` whose functions build ``make()`` on first use: a problem's
    objective may construct solvers (seconds), which only methods that estimate memory need."""
    real = functools.cache(make)
    deferred = lambda name: lambda *args: getattr(real(), name)(*args)  # noqa: E731
    return Objective(**{name: deferred(name) for name in ("predict", "loss", "network_output", "simulate", "target",  # pyright: ignore[reportArgumentType]  # function fields only
                                                          "inverse", "unrolled")})  # fmt: skip


def _devices(mesh) -> list | None:
    """The devices a batch is split over (None: the default device)."""
    return None if mesh is None else list(mesh.devices.flat)


def make_step(setup: Setup, batch_size: int, method: AbstractMethod | None = None):
    """The training step as one jitted function of (params, state, data, order, index).

    The mini-batch is gathered inside the jit (``order`` is the epoch's sample order,
    ``index`` the batch number), so a step is a single dispatch with no host work.
    Traced under a mesh (``jax.set_mesh``, :mod:`physgrad.distributed`) the batch is split
    over the mesh's ``"data"`` axis while parameters and state stay replicated."""
    method = method or setup.method

    def step(params, state, data, order, index):
        rows = jax.lax.dynamic_slice_in_dim(order, index * batch_size, batch_size)
        batch = distributed.shard_batch(jax.tree.map(lambda a: a[rows], data))
        objective = setup.objective
        if objective.loss is not None:
            objective = objective._replace(loss=scalar_loss(objective.loss))
        params, state, stats = method.step(objective, params, state, batch)
        return distributed.replicated(params), distributed.replicated(state), stats

    return jax.jit(step)


def make_evaluate(setup: Setup, chunk: int = 1024, per_sample: bool = False):
    """Mean per-sample loss and the problem's extra metrics over a data split (jitted, in
    chunks of ``chunk``): ``{"loss": ..., **problem.metrics}``; with ``per_sample`` every
    sample's values (for paired tests). Under a mesh the samples are split over its devices.

    Runs of the same problem and network structure share one jitted function (and so its
    compilations, :mod:`physgrad.programs`): the seeds differ in arguments only."""
    key = programs.key("evaluate", setup.problem, chunk, per_sample, static=setup.static)
    return programs.EVALUATIONS.get(key, lambda: _make_evaluate(setup, chunk, per_sample))[0]


def _make_evaluate(setup: Setup, chunk: int, per_sample: bool):
    problem = setup.problem

    def one(params, sample):
        x = problem.network_output(setup.network(params), sample)
        y = problem.simulate(x, sample)
        return {"loss": scalar_loss(problem.loss)(y, sample), **problem.metrics(x, y, sample)}

    def split_evaluate(params, data):
        n = jax.tree.leaves(data)[0].shape[0]
        devices = distributed.data_axis_size()
        if devices == 1:
            values = jax.lax.map(lambda s: one(params, s), data, batch_size=min(chunk, n))
        else:  # each device evaluates its share: (devices, n/devices) with the first axis split
            pad = -n % devices  # repeats of the last sample, cut off again below
            data = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), data)
            data = jax.tree.map(lambda a: a.reshape(devices, (n + pad) // devices, *a.shape[1:]), data)
            data = distributed.shard_batch(data)
            per_device = min(chunk, (n + pad) // devices)
            values = jax.vmap(lambda d: jax.lax.map(lambda s: one(params, s), d, batch_size=per_device))(data)
            values = jax.tree.map(lambda v: v.reshape(n + pad, *v.shape[2:])[:n], values)
        return values if per_sample else jax.tree.map(jnp.mean, values)

    return jax.jit(lambda params, data: distributed.replicated(split_evaluate(params, data)))


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


# --- strategies around the loop -------------------------------------------------------------
@dataclasses.dataclass
class StopRule:
    """The budget: steps, epochs (each stage at its own batch size) or training seconds."""

    budget: Budget
    setup: Setup

    def met(self, step: int, train_time: float) -> bool:
        kind, amount = self.budget.kind, self.budget.amount
        if kind == "seconds":
            return train_time >= amount
        if kind == "steps":
            return step >= amount
        return self.setup.epochs(step) >= amount - 1e-9


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


@dataclasses.dataclass
class Placement:
    """Where arrays live: one device, or a data mesh over devices and processes."""

    devices: int | str | None = 1

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

    def barrier(self, name: str):
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            multihost_utils.sync_global_devices(name)


class Steps:
    """The training data on the devices, each epoch's sample order, and each stage's step
    compiled ahead of time (compilation is counted in ``compile_seconds``).

    With ``settings.memory_guard`` a stage's step is checked before it first runs
    (:mod:`physgrad.memory`): the method's footprint before compiling, XLA's memory
    analysis of the compiled step after; a step that cannot fit raises ConfigError."""

    def __init__(self, setup: Setup, placement: Placement, settings: TrainSettings, seed: int):
        self.placement, self.settings = placement, settings
        self.n_train = jax.tree.leaves(setup.data["train"])[0].shape[0]
        self.data = placement.put(setup.data["train"])
        self.shuffle_key = jax.random.fold_in(jax.random.key(seed), 2)
        self.shuffle = setup.problem.default_shuffle if settings.shuffle is None else settings.shuffle
        fresh = settings.fresh_samples
        self.fresh = setup.problem.default_fresh_samples if fresh is None else fresh
        self.fresh_key = jax.random.fold_in(jax.random.key(seed), 3)
        self.first = self.data
        groups = setup.problem.batch_groups(setup.data["train"]) if self.shuffle else None
        self.groups = None if groups is None else np.asarray(groups)
        self.batch_sizes = [stage.batch_size for stage in setup.stages]

    def draw(self, setup: Setup, stage: int, epoch: int) -> None:
        """The training data of a stage's epoch in ``self.data``: the first epoch of the first
        stage trains on ``setup.data``; with ``fresh_samples`` every later epoch on a new
        train split from ``make_data`` with a key of the seed, stage and epoch (so a resumed
        run draws the same samples), of the same shapes, so the compiled step is reused."""
        if not self.fresh:
            return
        if stage == 0 and epoch == 0:
            self.data = self.first
            return
        key = jax.random.fold_in(jax.random.fold_in(self.fresh_key, stage), epoch)
        try:
            train = setup.problem.make_data(key)["train"]
        except ValueError as e:
            raise ConfigError(f"{setup.problem.name}: fresh_samples: {e}") from None
        self.data = self.placement.put(train)

    def order(self, stage: int, epoch: int):
        """The sample order of a stage's epoch: fixed, or with ``shuffle`` a permutation
        drawn from the seed, the stage and the epoch (so a resumed run takes the same
        batches). Where the problem labels its samples (``batch_groups``) the permutation
        keeps each of the stage's batches within one label (:func:`grouped_order`)."""
        if not self.shuffle:
            return self.placement.put(jnp.arange(self.n_train, dtype=jnp.int32))
        key = jax.random.fold_in(jax.random.fold_in(self.shuffle_key, stage), epoch)
        if self.groups is None:
            return self.placement.put(jax.random.permutation(key, self.n_train).astype(jnp.int32))
        rng = np.random.default_rng(np.asarray(jax.random.key_data(key)))
        return self.placement.put(jnp.asarray(grouped_order(self.groups, self.batch_sizes[stage], rng)))

    def compile(self, state: TrainState, setup: Setup) -> tuple[Any, TrainState]:
        """The current stage's step, compiled (and checked by the memory guard), or the
        same program compiled earlier in this process by a run that differs only in its
        seed (:mod:`physgrad.programs`)."""
        stage = setup.stages[state.stage]
        t0 = time.perf_counter()
        lower = lambda size: self._lower(state, setup, stage, size)  # noqa: E731
        guard = self.settings.memory_guard

        def build():
            if guard:  # the footprint alone, before spending time on compilation
                self._check(setup, stage)
            compiled = lower(stage.batch_size).compile()
            if guard:
                self._check(
                    setup, stage, compiled, lambda size: memory.compiled_bytes(lower(size).compile(), arguments=False)
                )
            return compiled

        compiled, _ = programs.STEPS.get(self._key(state, setup, stage), build)
        return compiled, state._replace(compile_seconds=state.compile_seconds + time.perf_counter() - t0)

    def _key(self, state: TrainState, setup: Setup, stage: Stage):
        """What the compiled step depends on (None: something unhashable, compile afresh).
        The epoch's sample order is not in it: its shape is the data's length, its placement
        the mesh's."""
        return programs.key("step", setup.problem, stage.method, stage.batch_size, self.placement.mesh,
                            self.settings.memory_guard, x64_enabled(), static=setup.static,
                            arguments=(state.params, state.opt_state, self.data))  # fmt: skip

    def _lower(self, state, setup, stage, batch_size):
        with self.placement.scope():
            fn = make_step(setup, batch_size, stage.method)
            return fn.lower(state.params, state.opt_state, self.data, self.order(state.stage, 0), np.int32(0))

    def _check(self, setup, stage, compiled=None, measure=None):
        batch = memory.stand_in(setup.data["train"], stage.batch_size)
        memory.check_step_fits(stage.method, setup.objective, setup.params, batch, devices=_devices(self.placement.mesh),
                               compiled=compiled, measure=measure, label=stage.label)  # fmt: skip


def grouped_order(groups: np.ndarray, batch_size: int, rng: np.random.Generator) -> np.ndarray:
    """A permutation of ``range(len(groups))`` whose consecutive blocks of ``batch_size``
    each hold samples of one group: every group's samples in random order cut into full
    batches, those batches in random order (the groups interleaved at random). A group's
    remainder (fewer than ``batch_size`` samples) goes to the end, where the epoch's last
    batches may mix groups; every sample appears once."""
    batches, rest = [], []
    for label in np.unique(groups):
        members = rng.permutation(np.flatnonzero(groups == label))
        full = len(members) // batch_size * batch_size
        batches.extend(members[:full].reshape(-1, batch_size))
        rest.append(members[full:])
    ordered = [batches[i] for i in rng.permutation(len(batches))]
    tail = np.concatenate(rest)
    return np.concatenate([*ordered, rng.permutation(tail)]).astype(np.int32)


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
        return setup.with_problem(dataclasses.replace(setup.problem, **{name: k}))

    def observe(self, state: TrainState, error: float) -> TrainState:
        s = self.settings
        new = prdp_control.update(self._controller(state), error, state.step, increment=s.prdp_increment,
                                  maximum=self._setting()[1], tau_step=s.prdp_tau_step, tau_stop=s.prdp_tau_stop)  # fmt: skip
        return state._replace(prdp=new)


class MetricsLog:
    """Appends long-format rows to ``metrics.csv``. On resume it keeps the rows up to the
    checkpoint's step (``kept``; a row torn by a kill during an append is dropped) and
    rewrites the file atomically, so a kill never leaves half a table."""

    def __init__(self, path: Path, keep_until_step: int | None = None, enabled: bool = True):
        self.path = path
        self.enabled = enabled
        self.kept: list[dict[str, str]] = []
        if not enabled:
            return
        if keep_until_step is not None and path.exists():
            self.kept = [r for r in _complete_rows(path) if int(r["step"]) <= keep_until_step]
        text = io.StringIO()
        writer = csv.writer(text)
        writer.writerow(METRICS_HEADER)
        writer.writerows([[r[k] for k in METRICS_HEADER] for r in self.kept])
        rundir.atomic_write(path, text.getvalue())

    def write(self, step: int, wall_time: float, values: dict[tuple[str, str], float]):
        if not self.enabled:
            return
        with self.path.open("a", newline="") as f:
            writer = csv.writer(f)
            for (split, metric), value in values.items():
                writer.writerow([step, f"{wall_time:.6f}", split, metric, repr(float(value))])


def _numbers(step: str, value: str) -> bool:
    """Whether a row's step and value parse (those of a torn row may not)."""
    try:
        int(step)
        float(value)
    except ValueError:
        return False
    return True


def _complete_rows(path: Path) -> list[dict[str, str]]:
    """The rows of ``metrics.csv`` that were written whole (a kill during an append can cut
    the last line anywhere, even into a shorter number)."""
    with path.open(newline="") as f:
        text = f.read()
    rows = []
    for r in csv.DictReader(io.StringIO(text[: text.rfind("\n") + 1])):
        if all(r.get(k) for k in METRICS_HEADER) and None not in r and _numbers(r["step"], r["value"]):
            rows.append(r)
    return rows


class Recorder:
    """Evaluation at the scheduled steps: full train/test (and val) metrics, the methods'
    step statistics averaged since the last evaluation (``step_<name>``), written to
    ``metrics.csv``; feeds PRDP the validation error."""

    def __init__(
        self, setup: Setup, settings: TrainSettings, placement: Placement, fidelity: Fidelity, log: MetricsLog
    ):
        self.settings, self.placement, self.fidelity, self.log = settings, placement, fidelity, log
        self.last: dict[str, float] = {}
        train = setup.data["train"]
        n_train = jax.tree.leaves(train)[0].shape[0]
        # The train-split evaluation may be limited to its first eval_samples samples (large
        # image datasets would otherwise cost more per evaluation than many training steps).
        # A problem's own default takes a strided subset: its windows are stored trajectory
        # by trajectory, so the first N would all come from one trajectory.
        n_eval = settings.eval_samples or setup.problem.default_eval_samples or None
        stride = max(1, n_train // n_eval) if n_eval and not settings.eval_samples else 1
        self.splits = {"train": placement.put(jax.tree.map(lambda a: a[::stride][:n_eval], train)),
                       "test": placement.put(setup.data["test"])}  # fmt: skip
        self.val = placement.put(setup.data.get("val"))
        self.use(setup)

    def use(self, setup: Setup):
        self.evaluate = make_evaluate(setup)

    def accumulate(self, state: TrainState, stats: dict[str, Any]) -> TrainState:
        totals, window = dict(state.stat_totals), dict(state.stat_window)
        for name, value in stats.items():
            value = float(value)
            if name == "loss" or not math.isfinite(value):  # e.g. the norm of a skipped NaN gradient
                continue
            total, count = window.get(name, (0.0, 0))
            window[name] = [total + value, count + 1]
            totals[name] = totals.get(name, 0.0) + value
        return state._replace(stat_totals=totals, stat_window=window)

    def restore(self, rows: list[dict[str, str]]) -> int | None:
        """After a resume: the metrics of the last evaluation logged (as if this recorder had
        made it, for the summary); returns its step (None without one)."""
        if not rows:
            return None
        step = max(int(r["step"]) for r in rows)
        self.last.update({f"{r['split']}_{r['metric']}": float(r["value"]) for r in rows if int(r["step"]) == step})
        return step

    def __call__(self, state: TrainState, final: bool) -> tuple[TrainState, bool]:
        """Evaluate and log at ``state.step``; returns the state and whether the losses are finite."""
        window = state.stat_window  # sorted: a resumed window (from JSON) logs in the same order
        values = {("train", f"step_{n}"): window[n][0] / window[n][1] for n in sorted(window)}
        state = state._replace(stat_window={})
        with self.placement.scope():
            for split, data in self.splits.items():
                values.update({(split, k): float(v) for k, v in self.evaluate(state.params, data).items()})
            val = self.evaluate(state.params, self.val) if self.val is not None else {}
        if state.step > 0:
            values[("train", "time_per_step")] = state.train_time / state.step
        if self.fidelity.name:
            values[("train", "solver_iterations")] = self.fidelity.iterations(state)
        values.update({("val", k): float(v) for k, v in val.items()})
        if self.settings.prdp and not final:
            state = self.fidelity.observe(state, float(val.get("rel_error", val["loss"])))
        self.log.write(state.step, state.train_time, values)
        self.last.update({f"{split}_{metric}": v for (split, metric), v in values.items()})
        test = self.last["test_loss"]
        if math.isfinite(test):
            state = state._replace(best_test_loss=min(state.best_test_loss, test))
        return state, math.isfinite(self.last["train_loss"]) and math.isfinite(test)


@dataclasses.dataclass
class Checkpointer:
    """Saves the :class:`TrainState` once ``seconds`` of wall-clock time have passed since
    the previous save (or the start), at every evaluation and at the end, so a kill loses at
    most that much work. Each save is one atomic commit of ``checkpoint/`` (arrays in
    ``state.eqx``, host scalars in ``counters.json``, sizes and checksums in
    ``manifest.json``: :func:`physgrad.rundir.save_checkpoint`).

    Loading verifies the manifest; a checkpoint of an older physgrad (no manifest) still
    loads, unverified."""

    run_dir: Path
    seconds: float
    writer: bool
    last: float = dataclasses.field(default_factory=time.monotonic)

    def maybe(self, state: TrainState):
        if time.monotonic() - self.last >= self.seconds:
            self.save(state)

    def save(self, state: TrainState):
        if self.writer:
            buffer = io.BytesIO()
            eqx.tree_serialise_leaves(buffer, distributed.to_host((state.params, state.opt_state)))
            counters = rundir.json_text(state.counters()).encode()
            rundir.save_checkpoint(
                self.run_dir, {"state.eqx": buffer.getvalue(), "counters.json": counters}, state.step
            )
        self.last = time.monotonic()  # the interval counts from the end of a save

    def exists(self) -> bool:
        return rundir.checkpoint_path(self.run_dir) is not None

    def load(self, like: Callable[[dict[str, Any]], TrainState]) -> TrainState | None:
        """The checkpointed state (None without one); ``like(counters)`` gives its structure
        (the optimizer state depends on the stage it was taken in). Damaged files are a
        one-line ConfigError (:func:`physgrad.rundir.load_checkpoint`); files that verify
        but do not fit ``like`` were written by another version of the method."""
        found = rundir.load_checkpoint(self.run_dir)
        if found is None:
            return None
        ckpt, files, verified = found
        counters = rundir.parse_counters(ckpt, files["counters.json"])
        counters.setdefault("stage", 0)
        counters.setdefault("stat_totals", {})
        counters = {k: v for k, v in counters.items() if k in TrainState._fields[2:]}
        try:
            template = like(counters)
            arrays = (template.params, template.opt_state)
            params, opt_state = eqx.tree_deserialise_leaves(io.BytesIO(files["state.eqx"]), arrays)
        except Exception as e:  # noqa: BLE001 — whatever the mismatch, one line
            why = "it was written by another version of the method" + (
                "" if verified else " (or is damaged: a checkpoint of an older physgrad has no checksums)"
            )
            raise ConfigError(f"the checkpoint {ckpt} does not match this method's state ({type(e).__name__}); "
                              f"{why}: delete {ckpt} to restart the run from step 0") from None  # fmt: skip
        return template._replace(params=params, opt_state=opt_state, **counters)


# --- the run ---------------------------------------------------------------------------------
def fit(
    problem: AbstractProblem,
    method: AbstractMethod | Phase | Sequence[Phase],
    *,
    budget: Budget,
    out: str | Path,
    seed: int = 0,
    batch_size: int | None = None,
    settings: TrainSettings = TrainSettings(),
    resume: bool = False,
    progress: AbstractProgressMeter | None = None,
    devices: int | str | None = 1,
    record: dict[str, Any] | None = None,
    same_run: Callable[[dict[str, Any]], bool] | None = None,
    label: str = "",
    name: str = "",
) -> dict[str, Any]:
    """Train ``method`` (or a sequence of phases) on ``problem`` into the run directory
    ``out`` and return the summary (also ``summary.json``).

    ``batch_size`` applies to a single method (phases carry their own; default: the
    problem's ``default_batch_size``). ``record`` is written as ``config.json`` (default: a
    description of problem, method, seed, budget and settings); with ``resume=True`` an
    existing run whose record matches (``same_run(old_record)``, default: equal apart from
    the budget) continues from its checkpoint up to ``budget``, and a finished run whose
    budget is met returns its summary. A run whose loss turns NaN or infinite stops with
    status ``"diverged"``, the step and the last finite loss. ``devices`` (a number or
    ``"all"``) splits every batch over a device mesh; in a multi-process run every process
    calls ``fit`` alike and only process 0 writes. ``name`` is the method's name in the
    summary (default: the phases' names joined by ``,``).

    A problem that declares ``needs_float64`` runs inside ``jax.enable_x64(True)``; the
    caller's JAX configuration is otherwise untouched.
    """
    _check_arguments(problem, budget, seed, batch_size, settings, out)
    phases = _phases(method, batch_size)
    record = record or _describe(problem, phases, seed, budget, settings)
    same_run = same_run or (lambda old: _identity(old) == _identity(json.loads(json.dumps(record, default=str))))
    run_dir = Path(out)
    identity = {"problem": problem.name, "method": name or ",".join(_name(p) for p in phases), "seed": seed}
    float64 = problem.needs_float64
    with float64_scope(float64):
        return _run(problem, phases, seed, budget, settings, run_dir, resume, progress or NoProgressMeter(),
                    Placement(devices), record, same_run, label or run_dir.name, identity)  # fmt: skip


def _check_arguments(problem, budget, seed, batch_size, settings, out) -> None:
    """:func:`fit`'s arguments by type and range, each refused in one line in the library's
    words before any work (the method is checked by :func:`_phases`)."""
    if not isinstance(problem, AbstractProblem):
        raise ConfigError(f"problem must be a physgrad problem (an AbstractProblem instance), got {problem!r}")
    if not isinstance(budget, Budget):
        raise ConfigError(f"budget must be a physgrad.Budget, e.g. Budget(steps={budget!r}), got {budget!r}")
    if not checks.NON_NEGATIVE_INT.valid(seed):
        raise ConfigError(f"seed must be {checks.NON_NEGATIVE_INT.text}, got {seed!r}")
    if batch_size is not None and not checks.POSITIVE_INT.valid(batch_size):
        raise ConfigError(f"batch_size must be {checks.POSITIVE_INT.text} or None (the problem's default), "
                          f"got {batch_size!r}")  # fmt: skip
    if not isinstance(settings, TrainSettings):
        raise ConfigError(f"settings must be a physgrad.TrainSettings, got {settings!r}")
    try:
        checks.check_directory(out, "out")
    except ConfigError as e:
        raise ConfigError(
            str(e), flags=str(e).replace("out '", "--out '").replace("another out", "another --out")
        ) from None


def _identity(record: dict[str, Any]) -> dict[str, Any]:
    """What must match for a run to resume: the record without its budget and without the
    settings that change only how the run is guarded."""
    settings = {k: v for k, v in record.get("settings", {}).items()
                if k not in UNGUARDED_SETTINGS and ADDED_SETTINGS.get(k, _ABSENT) != v}  # fmt: skip
    return {**record, "budget": None, "settings": settings}


def _name(phase: Phase) -> str:
    return phase.name or type(phase.method).__name__


def _phases(method, batch_size) -> list[Phase]:
    if isinstance(method, AbstractMethod):
        return [Phase(method, None, batch_size)]
    phases = [method] if isinstance(method, Phase) else list(method)
    if not phases or not all(isinstance(p, Phase) for p in phases):
        raise ConfigError("method must be a physgrad method (e.g. physgrad.methods.Method) or a list of Phase")
    if any(p.steps is None for p in phases[:-1]) or phases[-1].steps is not None and len(phases) > 1:
        raise ConfigError("every phase but the last needs steps; the last runs until the budget is spent")
    return phases


def _describe(problem, phases, seed, budget, settings) -> dict[str, Any]:
    """A readable record of a run given as objects (memory addresses removed, so the same
    objects describe alike in every process and session)."""
    text = lambda obj: re.sub(r" at 0x[0-9a-f]+", "", repr(obj))  # noqa: E731
    return {"problem": text(problem), "phases": [text(p) for p in phases], "seed": seed,
            "budget": budget.to_dict(), "settings": _resolved(settings, problem)}  # fmt: skip


def _resolved(settings: TrainSettings, problem: AbstractProblem) -> dict[str, Any]:
    """The settings as recorded: ``shuffle`` and ``fresh_samples`` None stand for the
    problem's defaults."""
    out = dataclasses.asdict(settings)
    out["shuffle"] = problem.default_shuffle if settings.shuffle is None else settings.shuffle
    out["fresh_samples"] = problem.default_fresh_samples if settings.fresh_samples is None else settings.fresh_samples
    return out


def _run(
    problem, phases, seed, budget, settings, run_dir, resume, progress, placement, record, same_run, label, identity
):
    """One run while its writer process holds the run directory's lock, with SIGTERM
    handled as Ctrl-C (a checkpoint, then stop)."""
    with _writer_lock(run_dir, placement), rundir.terminate_as_interrupt():
        return _run_locked(problem, phases, seed, budget, settings, run_dir, resume, progress, placement, record,
                           same_run, label, identity)  # fmt: skip


@contextlib.contextmanager
def _writer_lock(run_dir: Path, placement: Placement):
    """The writer process locks the run directory (:func:`physgrad.rundir.one_writer`); in a
    multi-process run every process learns whether it got the lock, so that none waits at a
    collective for a writer that was refused."""
    with contextlib.ExitStack() as stack:
        refused = None
        try:
            stack.enter_context(rundir.one_writer(run_dir, "run", enabled=placement.writer))
        except ConfigError as e:
            refused = e
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            flags = np.asarray(multihost_utils.process_allgather(np.array([int(refused is not None)])))
            if refused is None and flags.any():
                refused = ConfigError(f"the writer process could not lock {run_dir} (see its error)")
        if refused is not None:
            raise refused
        yield


def _run_locked(
    problem, phases, seed, budget, settings, run_dir, resume, progress, placement, record, same_run, label, identity
):
    config_path = run_dir / "config.json"
    old = None
    if config_path.exists():
        if not resume:
            raise ConfigError(f"run directory {run_dir} exists; resume it (resume=True) or choose another run directory",
                              flags=f"run directory {run_dir} exists; pass --resume or choose another --out")  # fmt: skip
        old = _read_json(config_path)
        if not same_run(old):
            raise ConfigError(f"run directory {run_dir} holds a different configuration; choose another run directory",
                              flags=f"run directory {run_dir} holds a different configuration; choose another --out")  # fmt: skip
    checkpointer = Checkpointer(run_dir, settings.checkpoint_seconds, placement.writer)
    has_ckpt = resume and checkpointer.exists()
    placement.barrier(f"physgrad.fit:{run_dir}")  # every process has looked before process 0 writes
    if not placement.writer:  # other processes compute alike and write nothing
        progress = NoProgressMeter()
    done = _done_already(run_dir, budget) if resume else None
    if done is not None:
        return done  # every file unchanged (checked before building data and network)

    fidelity = Fidelity.of(problem, settings)
    if settings.memory_guard:
        preflight(problem, phases, seed, placement.mesh)  # before minutes of data generation
    setup = build_setup(problem, phases, seed)
    for stage in setup.stages:
        distributed.check_batch(stage.batch_size, placement.mesh)
    fresh = TrainState(setup.params, setup.method.init(setup.params), prdp=fidelity.initial())
    like = lambda c: fresh._replace(opt_state=setup.stages[c["stage"]].method.init(setup.params))  # noqa: E731
    state = (checkpointer.load(like) if has_ckpt else None) or fresh
    if jax.process_count() > 1:  # every process must resume from the same checkpoint
        from jax.experimental import multihost_utils

        seen = multihost_utils.process_allgather(np.array([int(has_ckpt), state.step]))
        if len({tuple(row) for row in np.asarray(seen).reshape(-1, 2)}) > 1:
            raise ConfigError(f"the processes see different checkpoints in {run_dir}; a multi-process resume "
                              "needs the run directory on a file system every process shares")  # fmt: skip
    met = state.step > 0 and _budget_met(budget, (old or {}).get("budget"), state.step, state.train_time,
                                         setup.epochs, run_dir)  # fmt: skip
    if met:  # a kill came after the final checkpoint: nothing to train, maybe the summary to write
        summary = read_summary(run_dir)
        if summary and _complete(summary) and summary.get("steps") == state.step:
            return summary
    setup = fidelity.problem_at(setup, state)
    state = state._replace(params=placement.put(state.params), opt_state=placement.put(state.opt_state))
    steps, compiled = None, None
    if not met:
        steps = Steps(setup, placement, settings, seed)
        compiled, state = steps.compile(state, setup)  # a step the memory guard refuses leaves no files behind
    if placement.writer:
        run_dir.mkdir(parents=True, exist_ok=True)  # made by the lock already, unless the caller holds none
        write_json(config_path, record)
        write_json(run_dir / "env.json", {**environment(), "mesh_devices": distributed.mesh_size(placement.mesh)})
    # a checkpoint at step 0 precedes the first evaluation, which the resumed loop makes again
    keep = state.step if has_ckpt and state.step > 0 else None
    log = MetricsLog(run_dir / "metrics.csv", keep_until_step=keep, enabled=placement.writer)
    recorder = Recorder(setup, settings, placement, fidelity, log)
    evaluated = recorder.restore(log.kept)
    if met:
        status, diverged_step = "finished", None
        if evaluated != state.step:  # the final evaluation was not logged before the kill
            state, finite = recorder(state, final=True)
            status, diverged_step = ("finished", None) if finite else ("diverged", state.step)
    else:
        progress.start(budget=budget, steps_per_epoch=setup.steps_per_epoch, step=state.step,
                       train_time=state.train_time, label=label)  # fmt: skip
        try:
            state, setup, status, diverged_step = _loop(
                state, setup, steps, compiled, StopRule(budget, setup), EvalSchedule(settings), placement, fidelity,
                recorder, checkpointer, progress,
            )  # fmt: skip
        finally:
            progress.close()
    if status in ("interrupted", "terminated"):  # Ctrl-C or SIGTERM: keep what was done, then stop
        checkpointer.save(state)
        if placement.writer:
            write_json(
                run_dir / "summary.json",
                {"status": "interrupted", "steps": state.step, "train_seconds": state.train_time},
            )
        raise rundir.Terminated if status == "terminated" else KeyboardInterrupt
    summary = {**identity, **_finish(state, setup, status, diverged_step, recorder, checkpointer, placement, budget,
                                     run_dir)}  # fmt: skip
    if placement.writer:
        write_json(run_dir / "summary.json", summary)
    return summary


def _done_already(run_dir: Path, budget: Budget) -> dict[str, Any] | None:
    """The summary of a run that needs nothing more for ``budget`` (diverged, or finished
    exactly at it), read before any work; None if it must train on or finish (a
    ``summary.json`` without its final losses, as an older physgrad wrote after a resume,
    is finished again from the checkpoint)."""
    summary = read_summary(run_dir)
    if summary is None or not _complete(summary):
        return None
    if summary["status"] == "diverged":
        return summary
    if not isinstance(summary.get("steps"), int):
        return None
    met = _budget_met(budget, summary.get("budget"), summary["steps"], summary.get("train_seconds", 0.0), None, run_dir)
    return summary if met else None


def _budget_met(budget, recorded, step, seconds, epochs, run_dir) -> bool | None:
    """Whether a run at ``step`` (after ``seconds`` of training) is done with ``budget``:
    False (train on), True (met at exactly this step, or ``budget`` is the ``recorded`` one
    it ran to), None (cannot tell without ``epochs``, the data's step-to-epoch map). A budget
    the run went past is refused: a resumed run cannot undo steps."""
    kind, amount = budget.kind, budget.amount
    if kind == "epochs" and epochs is None:
        return True if recorded == budget.to_dict() else None
    done = epochs(step) if kind == "epochs" else step if kind == "steps" else seconds
    if done < amount - (1e-9 if kind == "epochs" else 0.0):
        return False
    if recorded == budget.to_dict():
        return True
    if kind == "steps" and step == amount or kind == "epochs" and epochs(step - 1) < amount - 1e-9:
        return True
    what = {"steps": f"{step} steps", "epochs": f"{done:g} epochs", "seconds": f"{seconds:.4g} training seconds"}[kind]
    raise ConfigError(f"the run in {run_dir} has already trained {what}, more than the budget of {budget}; "
                      "resume it with at least that budget, or choose another run directory")  # fmt: skip


def _loop(state, setup, steps, compiled, stop, schedule, placement, fidelity, recorder, checkpointer, progress):
    """Steps until the budget is met or the loss stops being finite (the training loop);
    ``compiled`` is the current stage's step. Returns the state, the setup, the status and
    the step it diverged at."""
    if state.step == 0:
        state, _ = recorder(state, final=False)
    schedule.start(state.train_time)
    order_key, order = None, None
    try:
        while not stop.met(state.step, state.train_time):
            index = setup.stage_index(state.step)
            if index != state.stage:  # switch method: the parameters carry over, the new method starts fresh
                opt_state = placement.put(setup.stages[index].method.init(distributed.to_host(state.params)))
                compiled, state = steps.compile(state._replace(stage=index, opt_state=opt_state), setup)
            stage = setup.stages[index]
            epoch, batch = divmod(state.step - stage.start, stage.steps_per_epoch)
            if (index, epoch) != order_key:
                steps.draw(setup, index, epoch)
                order, order_key = steps.order(index, epoch), (index, epoch)
            t_start = time.perf_counter()
            params, opt_state, stats = compiled(state.params, state.opt_state, steps.data, order, np.int32(batch))
            loss = float(stats["loss"])  # waits for the step: the timing is honest
            train_time = placement.clock(state.train_time + time.perf_counter() - t_start)
            if not math.isfinite(loss) and not float(stats.get("skipped", 0.0)):
                return state, setup, "diverged", state.step
            last_finite = loss if math.isfinite(loss) else state.last_finite_loss
            state = recorder.accumulate(state, stats)._replace(params=params, opt_state=opt_state, step=state.step + 1,
                                                                train_time=train_time, last_finite_loss=last_finite)  # fmt: skip
            if fidelity.name:
                state = state._replace(solver_iterations=state.solver_iterations + fidelity.iterations(state))
            boundary = stop.met(state.step, state.train_time) or (
                stage.steps is not None and state.step == stage.start + stage.steps
            )
            if schedule.due(state.step, state.train_time, stage, boundary):
                state, finite = recorder(state, final=stop.met(state.step, state.train_time))
                if not finite:
                    return state, setup, "diverged", state.step
                refined = fidelity.problem_at(setup, state)
                if refined is not setup:  # PRDP refined the solver: new problem, new step
                    setup = refined
                    recorder.use(setup)
                    compiled, state = steps.compile(state, setup)
                checkpointer.save(state)  # an evaluation is work too: never lost to a kill
            else:
                checkpointer.maybe(state)
            rundir.fault("step")
            progress.update(step=state.step, train_time=state.train_time, loss=loss)
    except KeyboardInterrupt as e:
        return state, setup, "terminated" if isinstance(e, rundir.Terminated) else "interrupted", None
    except ConfigError:  # the memory guard refused a later stage's step: keep what was done for a resume
        checkpointer.save(state)
        raise
    return state, setup, "finished", None


def _finish(state, setup, status, diverged_step, recorder, checkpointer, placement, budget, run_dir):
    """The final checkpoint, ``params.eqx``, ``test_cases.json`` and the summary (which the
    caller writes last: a run with a final ``summary.json`` has all its files)."""
    checkpointer.save(state)
    rundir.fault("before-summary")
    params = state.params
    if placement.writer:
        network = io.BytesIO()
        eqx.tree_serialise_leaves(network, setup.network(distributed.to_host(params)))
        rundir.atomic_write(run_dir / "params.eqx", network.getvalue())
    # Every test case's final metrics, for paired tests between methods (same seeds and cases).
    with placement.scope():
        cases = distributed.to_host(make_evaluate(setup, per_sample=True)(params, recorder.splits["test"]))
    if placement.writer:
        write_json(run_dir / "test_cases.json", {k: [float(v) for v in vals] for k, vals in cases.items()})
    last = recorder.last
    summary = {
        "status": status,
        "budget": budget.to_dict(),
        "steps": state.step,
        "epochs": setup.epochs(state.step),
        "stage_steps": {
            s.label if len(setup.stages) == 1 else f"{i}:{s.label}": s.steps_done(state.step)
            for i, s in enumerate(setup.stages)
        },
        "train_seconds": state.train_time,
        "compile_seconds": state.compile_seconds,
        "time_per_step": state.train_time / state.step if state.step else None,
        "final_train_loss": last.get("train_loss"),
        "final_test_loss": last.get("test_loss"),
        "final_test_metrics": {k[5:]: v for k, v in last.items() if k.startswith("test_") and k != "test_loss"},
        "best_test_loss": state.best_test_loss if math.isfinite(state.best_test_loss) else None,
        "diverged_step": diverged_step,
        "last_finite_loss": state.last_finite_loss if status == "diverged" else None,
        "n_params": parameter_count(setup.params),
        "devices": distributed.mesh_size(placement.mesh),
        "solver_iterations": state.solver_iterations if recorder.fidelity.name else None,
        "prdp": state.prdp,
        "step_stat_totals": state.stat_totals,
    }
    return summary


# --- run directories -------------------------------------------------------------------------
# Every package whose version can change a run's numbers (None in env.json: not installed).
# exponax's steppers make the time-stepper data; optimistix and lineax solve SIP's inverses.
ENV_PACKAGES = ("physgrad", "jax", "jaxlib", "equinox", "optax", "numpy", "scipy", "jaxtyping", "lineax", "optimistix",
                "exponax", "kfac-jax", "phiflow", "phiml")  # fmt: skip


def environment() -> dict[str, Any]:
    """Versions and devices, written as ``env.json``."""
    from importlib.metadata import PackageNotFoundError, version

    versions = {}
    for name in ENV_PACKAGES:
        try:
            versions[name] = version(name)
        except PackageNotFoundError:
            versions[name] = None
    return {
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "devices": [str(d) for d in jax.devices()],
        "backend": jax.default_backend(),
        "x64": x64_enabled(),
        "versions": versions,
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }


def write_json(path: Path, data: dict[str, Any]):
    """Write ``data`` as JSON all at once (:func:`physgrad.rundir.atomic_write`)."""
    rundir.atomic_write(path, rundir.json_text(data))


def read_metrics(path: Path) -> list[dict[str, Any]]:
    """``metrics.csv`` as a list of typed rows."""
    with Path(path).open() as f:
        return [
            {"step": int(r["step"]), "wall_time": float(r["wall_time"]), "split": r["split"], "metric": r["metric"],
             "value": float(r["value"])}
            for r in csv.DictReader(f)
        ]  # fmt: skip


def read_summary(run_dir: str | Path) -> dict[str, Any] | None:
    """A run's ``summary.json``, or None if it has none."""
    path = Path(run_dir) / "summary.json"
    return _read_json(path) if path.exists() else None


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise ConfigError(f"{path} cannot be read ({type(e).__name__}); the run directory is damaged: move it "
                          "away and run again") from None  # fmt: skip
    if not isinstance(data, dict):
        raise ConfigError(f"{path} is not a JSON object; the run directory is damaged: move it away and run again")
    return data


def is_complete(run_dir: str | Path) -> bool:
    """Whether a run finished or diverged (so a study can skip it). A finished summary
    without its final test loss (as an older physgrad wrote after resuming a finished run)
    is not complete: resuming finishes it again from its checkpoint."""
    summary = read_summary(run_dir)
    return summary is not None and _complete(summary)


def _complete(summary: dict[str, Any]) -> bool:
    """A final summary: diverged, or finished with its final losses."""
    if summary.get("status") not in FINAL_STATUSES:
        return False
    return summary["status"] == "diverged" or summary.get("final_test_loss") is not None
