"""Update rules as direction estimators plus optax, and what a rule sees of a problem.

physgrad's part of an update rule is the **direction**: the DP gradient, the κ-power of
the joint Jacobian (Gauss–Newton, HIG), SIP's proxy gradient, a rollout gradient under a
gradient-flow policy. Applying it is optax's job, with whatever chain the user chooses::

    estimate = physgrad.hig(predict, loss, truncation=1e-6)      # (params, batch) -> (d, stats)
    optimizer = optax.chain(optax.clip_by_global_norm(1.0), optax.sgd(schedule))

    @jax.jit
    def step(params, opt_state, batch):
        d, stats = estimate(params, batch)                        # d has params' structure
        updates, opt_state = optimizer.update(d, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, stats

The direction plays the role of a gradient: the optimizer steps *against* it, so
``optax.sgd(η)`` gives θ ← θ − η d, the papers' step.

Three layers of objects:

- :class:`AbstractRule`: the direction as a pure function of the problem's pieces
  (an :class:`Objective`), the parameters and a batch; holds only the rule's settings.
- :class:`Estimator`: a rule bound to a user's functions (what ``physgrad.hig(...)`` and
  friends return): ``estimate(params, batch) -> (direction, stats)``.
- :class:`AbstractMethod`: what the training engine runs, ``init`` and one pure ``step``.
  :class:`physgrad.methods.method.AbstractOptaxMethod` writes them once for a rule applied
  by an optax transformation, with an optional acceptance test that may refuse a step
  (:mod:`physgrad.acceptance`) and an optional control that hands the rule a value from
  the state; :class:`physgrad.methods.Method` (the pairing), Levenberg–Marquardt, unrolled
  training and KHIG with running factors are its final classes, which only fill its fields.

Parameters may be a whole Equinox module (an ``eqx.nn.MLP`` with its activation
functions, a convolution with its settings): estimators and methods differentiate its
inexact-array leaves only and leave every other leaf as it is, as ``eqx.filter_grad``
does. The direction then holds None at the other leaves, the structure
``eqx.apply_updates`` and an optax state from ``opt.init(eqx.filter(model,
eqx.is_inexact_array))`` expect::

    opt_state = optimizer.init(eqx.filter(model, eqx.is_inexact_array))
    d, stats = estimate(model, batch)
    updates, opt_state = optimizer.update(d, opt_state, eqx.filter(model, eqx.is_inexact_array))
    model = eqx.apply_updates(model, updates)

Rules themselves (:class:`AbstractRule`) see the array leaves alone: :func:`trainable`
splits the parameters and :meth:`Objective.bind_static` puts the rest back inside the
user's functions.

Rules and methods may also estimate the memory of their own large arrays
(``footprint``, from shapes alone) and name lighter variants of themselves (``lighter``):
the engine's memory guard (:mod:`physgrad.engine.memory`) checks a step against the device
before the first step and says what would fit.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array, PyTree

from ..errors import ConfigError, MissingPieces, SolverNotDifferentiable

Stats = dict[str, Array]
_T = TypeVar("_T")


STACK_SAMPLES = "jax.tree.map(lambda *x: jnp.stack(x), *samples)"


def check_batch(batch: PyTree, what: str = "the batch") -> None:
    """Refuse, in one line naming the fix, a batch given as a Python list of samples.

    A batch is one pytree whose arrays carry a leading sample axis, shape ``(B, ...)``
    (``{"x": (B, d)}``); the rules ``vmap`` over that axis. A list of per-sample pytrees
    (``[{"x": (d,)}, ...]``) is a pytree too, so ``vmap`` would hand the user's simulator
    a list of slices and fail inside it. Refused: a list whose items are containers of one
    structure (dicts, tuples, modules: samples), or numbers without an axis. A list of
    arrays with an axis (``[x, y]``, each ``(B, d)``) is a valid batch and passes.
    """
    if not isinstance(batch, list) or not batch:
        return
    structures = {jax.tree.structure(item) for item in batch}
    leaves_only = all(jax.tree_util.treedef_is_leaf(s) for s in structures)
    scalars = leaves_only and all(jnp.ndim(item) == 0 for item in batch)
    if (leaves_only and not scalars) or len(structures) > 1:
        return
    raise ConfigError(f"{what} is a list of {len(batch)} samples; stack them into one pytree with a leading sample "
                      f"axis first: {STACK_SAMPLES}")  # fmt: skip


def trainable(params: PyTree) -> tuple[PyTree, PyTree]:
    """``(arrays, static)``: the inexact-array leaves of ``params`` (floating or complex,
    what the rules differentiate) and everything else (functions, integers, Python
    scalars), each with None in the other's places, as ``eqx.partition(params,
    eqx.is_inexact_array)``; ``eqx.combine(arrays, static)`` is ``params`` again. Abstract
    stand-ins of such arrays (``jax.ShapeDtypeStruct``, as the memory guard's footprints
    see the parameters before they exist) count as arrays."""
    return eqx.partition(params, _is_trainable)


def _is_trainable(x: Any) -> bool:
    if isinstance(x, jax.ShapeDtypeStruct):
        return bool(jnp.issubdtype(x.dtype, jnp.inexact))
    return eqx.is_inexact_array(x)


def required(piece: _T | None, name: str) -> _T:
    """An :class:`Objective`'s ``piece``, or a one-line ``ValueError`` naming it if the
    problem does not provide it (rules check what they need in ``check``)."""
    if piece is None:
        raise ValueError(f"this method needs the problem's {name}, which it does not provide")
    return piece


def _solver_differentiable(objective: Objective) -> bool:
    return objective.differentiable


def _rollout_differentiable(objective: Objective) -> bool:
    return objective.rollout.differentiable_physics


def _unrolled_differentiable(objective: Objective) -> bool:
    return required(objective.unrolled, "unrolled")(None, False).differentiable_physics


#: The rules that stop the gradient at a time-stepper's solver (no-gradient unrolling and
#: one-step training), what a rule that differentiates through a non-differentiable one
#: is told to use instead.
STOP_AT_SOLVER = ("UnrolledGradient(policy=S())", "UnrolledGradient(teacher_forcing=True)")


class Part(NamedTuple):
    """One group of :class:`Objective` pieces: what a family of rules needs from a problem.

    A rule declares its part (``AbstractRule.part``, a class variable, or a property where
    the rule's settings decide it) and :meth:`AbstractRule.check` refuses, in one line, a
    problem whose objective lacks any of ``fields``
    (:class:`~physgrad.errors.MissingPieces`: ``"<rule> needs a problem with <words>[;
    <instead>]"``), after the pieces of ``base`` (a part this one extends). ``solver``
    reads from the objective whether the solver the part runs through is differentiable
    (asked on every check: for an unrolled system it also checks the window length); where
    ``differentiable`` is true the rule back-propagates through that solver and refuses a
    non-differentiable one (:class:`~physgrad.errors.SolverNotDifferentiable`, naming the
    rules of ``stop``).
    """

    fields: tuple[str, ...]
    words: str
    instead: str = ""
    differentiable: bool = False
    solver: Callable[[Objective], bool] = _solver_differentiable
    stop: tuple[str, ...] = STOP_AT_SOLVER
    base: Part | None = None


#: ``predict`` and ``loss``: the open-loop chain network → simulator → loss, differentiated
#: as one (DP, Gauss–Newton, HIG, Levenberg–Marquardt, Newton, K-FAC, Kronecker HIG).
OPEN_LOOP = Part(("predict", "loss"), "predict(params, sample) and loss(y, sample)",
                 "use a rollout rule (RolloutGradient, UnrolledGradient)", True)  # fmt: skip
#: The network and the physics apart, and a y-space target (SIP; ``inverse`` is optional).
SPLIT = Part(("network_output", "simulate", "target"),
             "network_output, simulate and a y-space target (define target(sample))")  # fmt: skip
#: SPLIT with the problem's analytic local inverse (SIP with ``Analytic()`` and no function).
ANALYTIC_INVERSE = Part(("inverse",), "an analytic local inverse (define inverse(x, y, y_target, sample))",
                        "choose another solver: GaussNewton(), SaddleFreeNewton(), LBFGS() or LinearSolve()",
                        base=SPLIT)  # fmt: skip
#: A rollout system whose transition takes the parameters (BPTT and its variants).
ROLLOUT = Part(("rollout",), "a rollout system",
               "use a closed-loop problem (physgrad.problems.AbstractClosedLoop)",
               solver=_rollout_differentiable, stop=("RolloutGradient(policy=S())",))  # fmt: skip
#: Windows of a time-stepper's trajectories, unrolled over m steps (ONE / NOG / WIG).
UNROLLED = Part(("unrolled",), "unrolled windows of a neural time-stepper",
                "use a time-stepper problem (physgrad.problems.AbstractTimeStepper)",
                solver=_unrolled_differentiable)  # fmt: skip


class Objective(NamedTuple):
    """The per-sample pieces of a problem, as pure functions of the trainable parameters.

    Each rule uses only the pieces of its :class:`Part` (:data:`OPEN_LOOP`,
    :data:`SPLIT`, :data:`ROLLOUT`, :data:`UNROLLED`); the others may stay None.

    - ``predict(params, sample) -> y`` runs network and simulator for one sample and
      ``loss(y, sample) -> L_i`` is the per-sample loss; rules use the batch mean
      ``L = (1/b) Σ_i L_i``, as the HIG paper's code does (DP, Gauss–Newton, HIG, Newton).
    - ``network_output(params, sample) -> x``, ``simulate(x, sample) -> y``,
      ``target(sample) -> y*`` and ``inverse(x, y, y_target, sample) -> x̃`` (the problem's
      analytic local inverse, or None): the network and the physics apart (SIP).
    - ``rollout``: a :class:`physgrad.rollout.System` whose transition takes the trainable
      parameters; a batch of samples is a batch of initial states (BPTT and its variants).
    - ``unrolled(m, teacher_forcing) -> System``: the rollout over the first m steps of
      each window (None: the problem's m), teacher-forced for the one-step modality
      (neural time-steppers).
    - ``differentiable``: False when ``predict`` runs a solver without derivatives (an
      external code): rules that back-propagate through it refuse.
    """

    predict: Callable[[PyTree, PyTree], Array] | None = None
    loss: Callable[[Array, PyTree], Array] | None = None
    network_output: Callable[[PyTree, PyTree], Array] | None = None
    simulate: Callable[[Array, PyTree], Array] | None = None
    target: Callable[[PyTree], Array] | None = None
    inverse: Callable | None = None
    rollout: Any = None
    unrolled: Callable[[int | None, bool], Any] | None = None
    differentiable: bool = True

    def provides(self, part: Part) -> bool:
        """Whether every piece of ``part`` is here."""
        return all(getattr(self, name) is not None for name in part.fields)

    def require(self, part: Part, who: str) -> None:
        """Raise the one-line error of rule ``who`` when a piece of ``part`` (or of its
        ``base``) is missing, or when the part back-propagates through a solver that is
        not differentiable (:class:`Part`)."""
        if part.base is not None:
            self.require(part.base, who)
        if not self.provides(part):
            raise MissingPieces(who, part.fields, part.words, part.instead)
        differentiable = part.solver(self)  # asked either way: it may check more (window lengths)
        if part.differentiable and not differentiable:
            raise SolverNotDifferentiable(part.stop)

    def require_differentiable(self) -> None:
        """Raise the one-line error of a rule that back-propagates through ``predict``
        when the problem declares its solver non-differentiable."""
        if not self.differentiable:
            raise SolverNotDifferentiable(OPEN_LOOP.stop)

    def bind_static(self, static: PyTree) -> Objective:
        """This objective as a function of the inexact-array leaves of the parameters
        alone: each piece that takes the parameters (``predict``, ``network_output``, the
        rollout's transition) gets ``eqx.combine(arrays, static)``. Itself when ``static``
        holds nothing (parameters that are arrays throughout)."""
        if not jax.tree.leaves(static):
            return self

        def bound(fn):
            if fn is None:
                return None
            return lambda arrays, *args: fn(eqx.combine(arrays, static), *args)

        def bound_system(system):
            return None if system is None else system._replace(transition=bound(system.transition))

        unrolled = self.unrolled
        return self._replace(
            predict=bound(self.predict),
            network_output=bound(self.network_output),
            rollout=bound_system(self.rollout),
            unrolled=None
            if unrolled is None
            else (lambda m, teacher_forcing: bound_system(unrolled(m, teacher_forcing))),
        )

    def sample_losses(self, params: PyTree, batch: PyTree) -> Array:
        predict, loss = required(self.predict, "predict"), required(self.loss, "loss")
        return jax.vmap(lambda s: loss(predict(params, s), s))(batch)

    def batch_loss(self, params: PyTree, batch: PyTree) -> Array:
        return jnp.mean(self.sample_losses(params, batch))


class AbstractRule(eqx.Module):
    """``rule(objective, params, batch) -> (direction, stats)``.

    ``direction`` has the structure of ``params`` and is used like a gradient (the
    optimizer steps against it); ``stats`` is a dict of scalars with at least ``"loss"``,
    the batch-mean loss at ``params``.

    ``part`` is the group of the objective's pieces the rule uses (:class:`Part`) and
    ``name`` how its errors call it; the default :meth:`check` refuses an objective without
    them.
    """

    part: ClassVar[Part | None] = None
    name: ClassVar[str] = "this method"

    @abc.abstractmethod
    def __call__(self, objective: Objective, params: PyTree, batch: PyTree) -> tuple[PyTree, Stats]: ...

    def check(self, objective: Objective) -> None:
        """Raise ``ValueError`` (one line, saying what to use instead) if the rule cannot
        run on ``objective``: when a piece of the rule's :attr:`part` is missing, or the
        part back-propagates through a non-differentiable solver (:meth:`Objective.require`).
        A rule whose needs depend on its settings declares ``part`` as a property."""
        if self.part is not None:
            objective.require(self.part, self.name)

    def check_batch_size(self, batch_size: int) -> None:
        """Raise ``ValueError`` if the rule cannot take batches of this size."""

    def footprint(self, objective: Objective, params: PyTree, batch: PyTree, devices: int = 1) -> int:
        """Bytes per device of the rule's own large arrays for this (global) batch split
        over ``devices`` devices, from shapes alone (``batch`` may hold stand-ins of the
        right shapes); 0, the default, when the rule cannot tell."""
        return 0

    def footprint_note(self, objective: Objective, params: PyTree, batch: PyTree) -> str:
        """What :meth:`footprint` counts, in a few words for the memory guard's message
        (e.g. ``route gram: 4096 × 37249 Jacobian``); empty by default."""
        return ""

    def lighter(self, batch_size: int) -> list[AbstractRule]:
        """Variants of this rule that may need less memory at ``batch_size`` (e.g. another
        half-inverse route), the most faithful first; none by default."""
        return []

    def describe(self, objective: Objective, params: PyTree, batch: PyTree) -> dict[str, Any]:
        """What the rule decides from shapes alone for this batch, as Python values (e.g.
        the half-inverse route ``Auto()`` takes); nothing is computed. Empty by default."""
        return {}


class AbstractJacobianRule(AbstractRule):
    """A rule on the joint Jacobian ``J = ∂y/∂θ`` of the open-loop chain (:data:`OPEN_LOOP`),
    whose large arrays and choices follow from the step's shapes: ``J``'s ``(rows, P)`` and
    the network's layers (:class:`physgrad.routes.JointJacobian`). It says them, from shapes
    alone, for the memory guard (:meth:`footprint`, :meth:`footprint_note`) and for the
    user (:meth:`describe`): HIG and Gauss–Newton (:class:`physgrad.methods.JacobianPower`)
    and KHIG (:class:`physgrad.methods.KroneckerPower`)."""

    part: ClassVar[Part | None] = OPEN_LOOP

    @abc.abstractmethod
    def footprint(self, objective: Objective, params: PyTree, batch: PyTree, devices: int = 1) -> int: ...

    @abc.abstractmethod
    def footprint_note(self, objective: Objective, params: PyTree, batch: PyTree) -> str: ...

    @abc.abstractmethod
    def describe(self, objective: Objective, params: PyTree, batch: PyTree) -> dict[str, Any]: ...


class Estimator(eqx.Module):
    """A rule bound to a user's functions: ``estimate(params, batch) -> (direction, stats)``.

    Returned by the public entry points (:func:`physgrad.hig`, :func:`physgrad.sip`, …);
    pure and traceable, so it goes inside the user's ``jax.jit`` with their optax update.
    ``params`` may be a whole Equinox module: the rule sees its inexact-array leaves and
    the direction holds None elsewhere (:func:`trainable`, as ``eqx.filter_grad``).
    """

    rule: AbstractRule
    objective: Objective

    def __check_init__(self):
        self.rule.check(self.objective)

    # An estimator is a function, and `jax.jit(estimate)` hashes it as one: by identity. The
    # field-wise hash a Module would get fails on the arrays some objectives hold (a rollout
    # system's per-step weights), so `jax.jit(physgrad.bptt(...))` raised "unhashable type".
    # Equality stays identity too, so two equal-hash estimators are never confused.
    __hash__ = object.__hash__
    __eq__ = object.__eq__

    def __call__(self, params: PyTree, batch: PyTree) -> tuple[PyTree, Stats]:
        check_batch(batch)  # before the user's simulator sees a list of slices
        arrays, static = trainable(params)
        return self.rule(self.objective.bind_static(static), arrays, batch)

    def describe(self, params: PyTree, batch: PyTree) -> dict[str, Any]:
        """The rule's choices for these shapes, without computing (:meth:`AbstractRule.describe`;
        for :func:`physgrad.hig`: the name of the route that runs and J's ``(rows, P)``)."""
        check_batch(batch)
        arrays, static = trainable(params)
        return self.rule.describe(self.objective.bind_static(static), arrays, batch)


def with_extra_args(optimizer: optax.GradientTransformation) -> optax.GradientTransformationExtraArgs:
    """``optimizer`` accepting keyword extras (``value=``), so a chain that needs the loss
    (``optax.contrib.reduce_on_plateau``, line searches) gets it and one that does not
    ignores it."""
    return optax.with_extra_args_support(optimizer)


class AbstractMethod(eqx.Module):
    """What the engine runs: ``init(params) -> state`` and a pure ``step``.

    ``step(objective, params, state, batch) -> (params, state, stats)`` does everything a
    training step needs and is jit-compiled by the engine as one function. ``stats``
    holds ``"loss"`` (at the parameters *before* the update) and the rule's statistics.
    ``check`` refuses a problem the method cannot run on and ``footprint`` estimates the
    step's own large arrays; a method may declare ``stages()``: a curriculum of methods
    (default: itself alone). :class:`AbstractOptaxMethod` implements all of it once for a
    rule applied by optax; :class:`physgrad.methods.kfac.KFAC` is the other kind.
    """

    @abc.abstractmethod
    def init(self, params: PyTree) -> Any: ...

    @abc.abstractmethod
    def step(self, objective: Objective, params: PyTree, state: Any, batch: PyTree) -> tuple[PyTree, Any, Stats]: ...

    @abc.abstractmethod
    def check(self, objective: Objective) -> None:
        """Raise ``ValueError`` if this method cannot run on ``objective``."""

    @abc.abstractmethod
    def footprint(self, objective: Objective, params: PyTree, batch: PyTree, devices: int = 1) -> int:
        """Bytes per device of the step's own large arrays, from shapes alone (see
        :meth:`AbstractRule.footprint`); 0 when the method cannot tell."""

    def check_batch_size(self, batch_size: int) -> None:
        """Raise ``ValueError`` if this method cannot take batches of this size."""

    def footprint_note(self, objective: Objective, params: PyTree, batch: PyTree) -> str:
        """What :meth:`footprint` counts, in a few words; empty by default."""
        return ""

    def lighter(self, batch_size: int) -> list[AbstractMethod]:
        """Variants of this method that may need less memory at ``batch_size``, the most
        faithful first; none by default."""
        return []

    def stages(self) -> list[tuple[AbstractMethod, float | None]]:
        """``(method, epochs)`` stages; the last runs until the budget is spent."""
        return [(self, None)]

    def stage_label(self) -> str:
        """What distinguishes this stage in a curriculum (e.g. ``m=2``); empty by default."""
        return ""


class Stepper(eqx.Module):
    """A method bound to a user's functions: ``init(params)`` and ``step(params, state,
    batch) -> (params, state, stats)``.

    For the rules whose update is more than a direction for the user's chain (Levenberg–
    Marquardt measures the loss at the candidate and refuses bad steps): the user's optax
    chain goes in as the method's optimizer, and the acceptance test is part of ``step``.
    Pure and traceable like :class:`Estimator`; ``jax.jit(stepper.step)`` works as it is,
    and ``params`` may be a whole Equinox module.
    """

    method: AbstractMethod
    objective: Objective

    def __check_init__(self):
        self.method.check(self.objective)

    __hash__ = object.__hash__  # a function to jax.jit, as Estimator
    __eq__ = object.__eq__

    def init(self, params: PyTree) -> Any:
        return self.method.init(params)

    def step(self, params: PyTree, state: Any, batch: PyTree) -> tuple[PyTree, Any, Stats]:
        check_batch(batch)
        return self.method.step(self.objective, params, state, batch)
