"""What a run builds before its first step: data, network, objective and stages.

:func:`build_setup` makes them (deterministic per seed) and checks every method against
the problem, with one-line errors. :func:`abstract_setup` makes the same from shapes alone
(``eqx.filter_eval_shape``: nothing is generated or initialised); the memory guard's
:func:`preflight` and the bench's applicability check (:mod:`physgrad.harness.bench`) use it.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree

from .. import distributed
from ..errors import ConfigError, MethodRefused
from ..methods import AbstractMethod, Objective
from ..methods.base import check_batch
from ..problems import AbstractProblem
from . import memory
from .splits import TEST_SPLIT, AbstractSplit
from .types import Phase, Setup, Stage

# JAX's errors for host code given a tracer (NumPy on an array, ``float(x)``, ``if x:``):
# what a problem whose data or network need concrete values raises when traced abstractly.
NOT_TRACEABLE = (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
                 jax.errors.TracerBoolConversionError, jax.errors.TracerIntegerConversionError)  # fmt: skip


def build_setup(
    problem: AbstractProblem, phases: Sequence[Phase], seed: int, split: AbstractSplit = TEST_SPLIT
) -> Setup:
    """Data (``split`` of the problem's, :func:`run_data`), network and stages
    (deterministic per seed); every method is checked against the problem's declared
    pieces, with one-line errors."""
    key = jax.random.key(seed)
    data = _made_data(problem, functools.partial(run_data, problem, split), jax.random.fold_in(key, 0))
    network = _made_network(problem, initial_network, jax.random.fold_in(key, 1), data)
    params, static = eqx.partition(network, eqx.is_inexact_array)
    objective = problem.objective(static)
    stages = build_stages(problem, phases, objective=objective, data=data)
    return Setup(problem, data, params, static, objective, stages, split)


def run_data(problem: AbstractProblem, split: AbstractSplit, key, *, check: bool = True) -> dict[str, Any]:
    """The data a run trains and evaluates on: ``split(problem.make_data(key))``, the one
    place a split is applied (the first draw, its shapes, every fresh draw). With ``check``
    the problem's own output is checked first (:func:`_check_data`), so a malformed one is
    named as ``make_data``'s, whatever the split."""
    data = problem.make_data(key)
    if check:
        _check_data(problem, data)
    return split(data)


def _made_data(problem: AbstractProblem, make: Callable, key) -> Any:
    """``make(key)`` (:func:`run_data`, concrete or abstract): a ``ValueError`` (a setting
    the data cannot be made with, a split too small to hold out from) as a one-line
    ConfigError."""
    try:
        return make(key)
    except ValueError as e:
        raise ConfigError(f"{problem.name}: {e}") from None


def _made_network(problem: AbstractProblem, make: Callable, key, data) -> Any:
    """``make(problem, key, data)`` (the initial network, concrete or abstract); its
    ``ValueError``/``TypeError`` (e.g. an activation the network does not know) as a
    one-line ConfigError. JAX's tracer errors (:data:`NOT_TRACEABLE`) pass through."""
    try:
        return make(problem, key, data)
    except (ValueError, TypeError) as e:
        if isinstance(e, NOT_TRACEABLE):
            raise
        raise ConfigError(f"{problem.name}: {' '.join(str(e).split())}") from None


def _check_data(problem: AbstractProblem, data: Any) -> None:
    """``make_data``'s result: a dict with ``train`` and ``test`` splits (``val`` optional),
    each with at least one sample and one leading (sample) axis shared by its arrays."""
    if not isinstance(data, dict) or not {"train", "test"} <= set(data):
        got = f"a dict with keys {sorted(data)}" if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{problem.name}: make_data must return {{'train': samples, 'test': samples}}, got {got}")
    for split, samples in data.items():
        if samples is None and split not in ("train", "test"):
            continue
        check_batch(samples, f"{problem.name}: make_data's {split!r} split")
        lengths = {np.shape(x)[0] if np.ndim(x) else None for x in jax.tree.leaves(samples)}
        if not lengths or lengths == {0}:
            raise ConfigError(f"{problem.name}: make_data's {split!r} split is empty (0 samples); every split needs "
                              "at least one sample")  # fmt: skip
        if len(lengths) > 1 or None in lengths:
            raise ConfigError(f"{problem.name}: the arrays of make_data's {split!r} split must share their leading "
                              f"(sample) axis, got lengths {sorted(lengths, key=str)}")  # fmt: skip
        _check_finite(problem, split, samples)


def _check_finite(problem: AbstractProblem, split: str, samples: Any) -> None:
    """A NaN or infinity in the data is refused as data, naming the split and the first
    sample that holds one; left to the loop it would read as the method diverging."""
    for path, x in jax.tree_util.tree_leaves_with_path(samples):
        if isinstance(x, jax.ShapeDtypeStruct):
            return  # abstract data (the memory guard's preflight): nothing to look at
        if not jnp.issubdtype(jnp.result_type(x), jnp.inexact):
            continue
        try:
            values = np.asarray(x)
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
            return  # data made under a trace: nothing concrete to look at
        finite = np.isfinite(values).reshape(np.shape(x)[0], -1).all(axis=1)
        if not finite.all():
            sample = int(np.argmin(finite))
            where = jax.tree_util.keystr(path) or "its array"
            raise ConfigError(f"{problem.name}: the {split!r} data hold a NaN or infinite value in sample {sample} "
                              f"({where}{'' if finite.sum() + 1 == finite.size else f'; {int((~finite).sum())} samples in all'}); "
                              "fix or drop those samples")  # fmt: skip


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


def initial_network(problem: AbstractProblem, key, data) -> PyTree:
    """``problem.initial_network(key, data)`` as one compiled program (shared by every seed
    of the problem) instead of hundreds of eagerly dispatched operations; a network built
    by host code that cannot be traced is built eagerly, as written."""
    try:
        return _initial_network_jit(problem, key, data)
    except NOT_TRACEABLE:
        return problem.initial_network(key, data)


def build_stages(
    problem: AbstractProblem, phases: Sequence[Phase], *, objective: Objective, data: Any, check: bool = True
) -> list[Stage]:
    """The phases as stages (curricula expanded), each method checked against the problem
    (unless ``check`` is False)."""
    n_train = jax.tree.leaves(data["train"])[0].shape[0]
    stages, start = [], 0
    for phase in phases:
        name = phase.label
        batch_size = phase.batch_size or problem.default_batch_size
        if batch_size > n_train:
            raise ConfigError(f"batch_size {batch_size} exceeds the {n_train} training samples")
        try:
            if check:
                phase.method.check(objective)
            phase.method.check_batch_size(batch_size)
        except ValueError as e:
            raise MethodRefused(name, problem.name, e) from None
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


# --- from shapes alone -----------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class AbstractSetup:
    """A problem's data and network as ``jax.ShapeDtypeStruct``s: nothing generated or
    initialised. ``data`` is None where ``make_data`` needs concrete values (NumPy code,
    a dataset cached on disk); the network is then the problem's ``make_network``."""

    data: dict[str, Any] | None
    params: Any
    static: Any  # the network's other leaves; its non-float arrays as zero views

    @property
    def n_train(self) -> int | None:
        """The training-set size (None where the data cannot be traced abstractly)."""
        return None if self.data is None else jax.tree.leaves(self.data["train"])[0].shape[0]

    @property
    def parameter_count(self) -> int:
        return sum(math.prod(x.shape) for x in jax.tree.leaves(self.params))


def abstract_data(problem: AbstractProblem, seed: int = 0, split: AbstractSplit = TEST_SPLIT) -> dict[str, Any] | None:
    """The run's data (:func:`run_data`) as shapes (the key :func:`build_setup` uses),
    checked as it checks them; None where the data need concrete values (:data:`NOT_TRACEABLE`)."""
    # traced whole: the split sees make_data's own objects (a direct problem's train *is* its test)
    make = functools.partial(eqx.filter_eval_shape, functools.partial(run_data, problem, split))
    try:
        return _made_data(problem, make, jax.random.fold_in(jax.random.key(seed), 0))
    except NOT_TRACEABLE:
        return None


def abstract_setup(
    problem: AbstractProblem, seed: int = 0, data: dict[str, Any] | None = None, split: AbstractSplit = TEST_SPLIT
) -> AbstractSetup:
    """The setup from shapes alone (``data``: :func:`abstract_data` of ``split``, made here
    if not given). A setting :func:`build_setup` refuses raises the same one-line
    ConfigError; a network that needs concrete values raises JAX's error (:data:`NOT_TRACEABLE`)."""
    data = abstract_data(problem, seed, split) if data is None else data
    key = jax.random.fold_in(jax.random.key(seed), 1)
    if data is not None:
        network = _made_network(problem, _abstract_network, key, data)
    else:  # every shipped problem's start unless it is direct optimisation
        network = eqx.filter_eval_shape(problem.make_network, key)
    abstract = lambda x: isinstance(x, jax.ShapeDtypeStruct) and jnp.issubdtype(x.dtype, jnp.inexact)  # noqa: E731
    params, static = eqx.partition(network, abstract)
    # Non-float arrays (indices, masks) stay with the static part as zero views of their
    # shape: objectives close over it.
    static = jax.tree.map(lambda x: memory.stand_in(x, None) if isinstance(x, jax.ShapeDtypeStruct) else x, static)
    return AbstractSetup(data, params, static)


def _abstract_network(problem: AbstractProblem, key, data):
    return eqx.filter_eval_shape(problem.initial_network, key, data)


def preflight(
    problem: AbstractProblem, phases: Sequence[Phase], *, seed: int, mesh=None, split: AbstractSplit = TEST_SPLIT
) -> None:
    """The memory guard's first look, before any data exist: every stage's footprint
    (:meth:`~physgrad.AbstractMethod.footprint`) from the shapes of the data and the
    network alone (:func:`abstract_setup`), so a step that cannot fit is refused in
    seconds, not after minutes of data generation.

    What the run will hold besides the step (the dataset, the parameters and each stage's
    optimizer state) is not in memory yet; it is counted against the available memory, so
    that a batch size suggested here passes the check after the data exist.

    Two things are skipped here, each for a reason, and every other exception surfaces:

    * JAX's tracer errors (:data:`NOT_TRACEABLE`): data, network, objective, optimizer
      state or footprint that need concrete values (NumPy code, a cache on disk). The
      run checks such a step once the data exist, before compiling it
      (:class:`~physgrad.engine.step.Steps`).
    * :class:`~physgrad.ConfigError` from building the abstract setup and its stages: a
      setting :func:`build_setup`, which runs next, refuses in the same words (after
      checking the methods, which may build solvers and so are not checked here).

    A ``ValueError`` from a footprint is the method refusing the problem (as its ``check``
    does); it is raised as that stage's one-line ConfigError, as :func:`build_stages` words it.
    """
    try:
        data = abstract_data(problem, seed, split)
        if data is None:
            return
        setup = abstract_setup(problem, seed, data)
        objective = _deferred_objective(lambda: problem.objective(setup.static))
        stages = build_stages(problem, phases, objective=objective, data=data, check=False)
    except NOT_TRACEABLE:  # checked once the data exist
        return
    except ConfigError:  # build_setup says it, in its order
        return
    for stage in stages:
        if stage.batch_size % distributed.mesh_size(mesh):
            continue  # reported by the run's own check
        batch = memory.stand_in(data["train"], stage.batch_size)
        try:
            resident = memory.tree_bytes((data, setup.params, _optimizer_state_shape(stage.method, setup.params)))
            with method_refusals(stage.label, problem):
                memory.check_step_fits(stage.method, objective, setup.params, batch, devices=mesh_devices(mesh),
                                       label=stage.label, resident=resident)  # fmt: skip
        except NOT_TRACEABLE:  # a footprint that needs concrete values: checked once they exist
            return


@contextlib.contextmanager
def method_refusals(label: str, problem: AbstractProblem) -> Iterator[None]:
    """A method's ``ValueError`` inside (it refuses this problem, as its ``check`` does) as
    the stage's one-line ConfigError, in :func:`build_stages`' words; ConfigErrors (the
    memory guard's own refusal) pass through unchanged."""
    try:
        yield
    except ConfigError:
        raise
    except ValueError as e:
        raise MethodRefused(label, problem.name, e) from None


def _optimizer_state_shape(method: AbstractMethod, params) -> Any:
    """The shapes of ``method.init(params)`` (None where they need concrete values)."""
    try:
        return jax.eval_shape(method.init, params)
    except NOT_TRACEABLE:  # an optimizer whose init needs concrete values: not counted
        return None


class _DeferredObjective:
    """An :class:`Objective` built by ``make()`` on first use of any of its pieces: a
    problem's objective may construct solvers (seconds), which only methods that estimate
    memory need. Every piece, and what is missing, is the real objective's: nothing is
    listed here, so a piece added to :class:`Objective` is never dropped."""

    def __init__(self, make: Callable[[], Objective]):
        self._make = functools.cache(make)

    @property
    def __class__(self):  # pyright: ignore[reportIncompatibleMethodOverride]
        # isinstance(_, Objective) holds, as for unittest.mock's spec: a run-time type check
        # (the test suite's --jaxtyping) takes the stand-in where an Objective is declared
        return Objective

    def __getattr__(self, name: str):
        return getattr(self._make(), name)

    def bind_static(self, static: Any) -> Objective:  # still deferred (Method.footprint binds first)
        make = self._make
        return _deferred_objective(lambda: make().bind_static(static))


def _deferred_objective(make: Callable[[], Objective]) -> Objective:
    return cast(Objective, _DeferredObjective(make))


def mesh_devices(mesh) -> list | None:
    """The devices a batch is split over (None: the default device)."""
    return None if mesh is None else list(mesh.devices.flat)
