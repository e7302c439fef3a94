"""Acceptance tests: whether a training step is taken, as objects a method composes.

A method proposes a step — the rule's direction d, the optimizer's updates Δ and the
candidate θ + Δ (a :class:`Proposal`) — and its acceptance decides whether to take it. A
refused step leaves the parameters *and* the optimizer's state as they were
(:func:`keep_where`), so a refused update never happened, as ``optax.apply_if_finite``
does for its inner state. Each acceptance is an Equinox module with ``init(params) ->
state`` and ``acceptance(proposal, state) -> (accepted, stats, state)``::

    method = physgrad.Method(rule, optax.adam(1e-3), acceptance=All(FiniteGradient(), NormBound()))

The tests here, each one reason to refuse a step (:class:`AbstractTest`):

- :class:`FiniteGradient`: every entry of d finite (``optax.apply_if_finite``'s test).
- :class:`NormBound`: ‖d‖ within a running bound, the rule of
  :func:`physgrad.transforms.norm_guard` (List et al., CMAME 2025, §5.4), the bound in
  this test's own state.
- :class:`SolverSuccess`: the rule reports no solver failure (``stats["solver_ok"]``).

:class:`All` takes a step that passes all of its tests and reports ``skipped`` (1 for a
refused step) and ``skip_<name>`` per test (1 where that test objected to a refused step);
a single test reports the same two. Levenberg–Marquardt's gain-ratio test, which also
adapts the damping, is :class:`physgrad.methods.lm.GainRatio`.
"""

# No `from __future__ import annotations`: Equinox reads `AbstractVar` fields from evaluated annotations.

import abc
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from equinox import AbstractClassVar, AbstractVar
from jaxtyping import Array, PyTree

Stats = dict[str, Array]

SKIPPED = "skipped"
"""The statistic that is 1 for a refused step (:class:`All`; the engine does not call a
refused step with a non-finite loss a divergence)."""


class Proposal(NamedTuple):
    """A step as proposed, for an acceptance to judge (all over the trainable arrays)."""

    objective: Any  # the problem's pieces, bound to the array leaves (physgrad.methods.Objective)
    params: PyTree  # θ before the step
    batch: PyTree
    direction: PyTree  # d, the rule's direction
    updates: PyTree  # Δ, the optimizer's updates
    candidate: PyTree  # θ + Δ
    stats: Stats  # the rule's statistics: loss (at θ), grad_norm, solver_ok, …


def keep_where(accepted: Array, new: PyTree, old: PyTree) -> PyTree:
    """``new`` where the step is ``accepted``, else ``old``, leaf by leaf (parameters,
    optimizer states, acceptance states: the one place a refusal is written)."""
    return jax.tree.map(lambda a, b: jnp.where(accepted, a, b), new, old)


class AbstractAcceptance(eqx.Module):
    """``init(params) -> state``; ``acceptance(proposal, state) -> (accepted, stats, state)``.

    ``accepted`` is a boolean scalar; ``stats`` a dict of scalars the method adds to the
    step's statistics; ``state`` the acceptance's state after the verdict."""

    @abc.abstractmethod
    def init(self, params: PyTree) -> Any:
        """The state before the first step."""

    @abc.abstractmethod
    def __call__(self, proposal: Proposal, state: Any) -> tuple[Array, Stats, Any]: ...


class AbstractTest(AbstractAcceptance):
    """One reason to refuse a step, reported as ``skip_<name>``; combine several with :class:`All`.

    A test's state advances only with a step that is taken (by all of :class:`All`'s
    tests): a refused step taught nothing. With ``enforce=False`` a test never refuses but
    is still judged, so ``skip_<name>`` says whether it would have objected to a step that
    another test refused."""

    name: AbstractClassVar[str]
    enforce: AbstractVar[bool]

    def init(self, params):
        """The state before the first step (default: none)."""
        return ()

    @abc.abstractmethod
    def judge(self, proposal: Proposal, state: Any) -> tuple[Array, Array, Any]:
        """``(passes, objects, state)``: whether the step passes; whether a refusal is to be
        reported as this test's (usually ``~passes``); the state if the step is taken."""

    def __call__(self, proposal, state):
        accepted, stats, (state,) = All(self)(proposal, (state,))
        return accepted, stats, state


class All(AbstractAcceptance):
    """A step is taken when every test passes (tests with ``enforce=False`` always do).

    State: the tuple of the tests' states. Stats, as float32 0/1: ``skipped`` and, per
    test, ``skip_<name>`` = skipped and that test objects (several may)."""

    tests: tuple[AbstractTest, ...]

    def __init__(self, *tests: AbstractTest):
        names = [t.name for t in tests]
        if len(set(names)) != len(names):
            raise ValueError(f"acceptance tests need distinct names, got {names}")
        self.tests = tests

    def init(self, params):
        return tuple(t.init(params) for t in self.tests)

    def __call__(self, proposal, state):
        verdicts = [t.judge(proposal, s) for t, s in zip(self.tests, state)]
        accepted = jnp.asarray(True)
        for test, (passes, _, _) in zip(self.tests, verdicts):
            if test.enforce:
                accepted = accepted & passes
        skipped = ~accepted
        stats = {SKIPPED: skipped.astype(jnp.float32)}
        for test, (_, objects, _) in zip(self.tests, verdicts):
            stats[f"skip_{test.name}"] = (skipped & objects).astype(jnp.float32)
        new = tuple(keep_where(accepted, after, before) for (_, _, after), before in zip(verdicts, state))
        return accepted, stats, new


class FiniteGradient(AbstractTest):
    """Refuse a direction with a NaN or infinite entry (``skip_nan``), the test of
    ``optax.apply_if_finite``; unlike it, never gives up after many refusals (a run whose
    gradient stays NaN is the engine's to stop)."""

    name: ClassVar[str] = "nan"
    enforce: bool = eqx.field(static=True, default=True)

    def judge(self, proposal, state):
        leaves = jax.tree.leaves(proposal.direction)
        finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.asarray(True)
        return finite, ~finite, state


class NormBoundState(NamedTuple):
    """The running bound c on the direction's norm (0: not set yet)."""

    bound: Array


def running_bound(bound: Array, norm: Array, factor: float, decay: float, first: float) -> tuple[Array, Array]:
    """``(within, bound after taking the step)`` of the running norm bound::

        within  ⇔  c = 0  or  ‖d‖ ≤ c,      c ← decay·c + factor·‖d‖   (the first: c = first·‖d‖)

    so c settles near factor / (1 − decay) = 100× the typical norm (defaults 10, 0.9)."""
    within = (bound == 0) | (norm <= bound)
    after = jnp.where(bound == 0, first * norm, decay * bound + factor * norm).astype(bound.dtype)
    return within, after


class NormBound(AbstractTest):
    """Refuse a direction whose norm exceeds a running bound (``skip_norm``): a spike two
    orders above the recent gradients is dropped, as the unrolling study of List et al.
    (CMAME 2025, §5.4) does for the Kolmogorov flow (:func:`running_bound`). A norm that is
    not finite is refused too once a bound is set, but reported as ``skip_nan``'s, not as
    an outlier. State: :class:`NormBoundState` (float32)."""

    name: ClassVar[str] = "norm"
    factor: float = eqx.field(static=True, default=10.0)
    decay: float = eqx.field(static=True, default=0.9)
    first: float = eqx.field(static=True, default=100.0)
    enforce: bool = eqx.field(static=True, default=True)

    def init(self, params):
        return NormBoundState(jnp.zeros((), jnp.float32))

    def judge(self, proposal, state):
        norm = optax.tree.norm(proposal.direction)
        within, bound = running_bound(state.bound, norm, self.factor, self.decay, self.first)
        return within, ~within & jnp.isfinite(norm), NormBoundState(bound)


class SolverSuccess(AbstractTest):
    """Refuse a step where the rule reports a solver failure (``skip_solver``): its
    ``stats["solver_ok"]`` is False (:class:`physgrad.methods.UnrolledGradient` reports
    it from the rollout's final state)."""

    name: ClassVar[str] = "solver"
    enforce: bool = eqx.field(static=True, default=True)

    def judge(self, proposal, state):
        if "solver_ok" not in proposal.stats:
            raise ValueError("SolverSuccess needs a rule that reports stats['solver_ok'] (e.g. UnrolledGradient)")
        ok = jnp.asarray(proposal.stats["solver_ok"], bool)
        return ok, ~ok, state


__all__ = ["SKIPPED", "AbstractAcceptance", "AbstractTest", "All", "FiniteGradient", "NormBound", "NormBoundState",
           "Proposal", "SolverSuccess", "keep_where", "running_bound"]  # fmt: skip
