"""Neural time-steppers: prediction and correction compositions of a solver and a network.

List, Chen, Bali & Thuerey, "Differentiability in unrolled training of neural physics
simulators on transient dynamics", CMAME 2025.
One step u ↦ u⁺ of a stepper, with P the (coarse) numerical solver and f_θ the network, is
one of five composition objects, passed to a time-stepper problem as diffrax takes its
``adjoint=`` (each object computes its own step):

===========================  =======================  =======================================
setup                        composition              u⁺
===========================  =======================  =======================================
prediction                   :class:`Prediction`      f_θ(u)
prediction                   :class:`Residual`        u + f_θ(u)
correction                   :class:`Parallel` (α)    P(u) + α f_θ(u)       (List's KS)
correction                   :class:`Sequential`      f_θ(P(u))
correction                   :class:`Bypass` (α)      P(u) + α f_θ(P(u))    (List's KOLM)
===========================  =======================  =======================================

α is the problem's network scale (List's KS uses the substep Δt). The network also
receives the sample's conditioning value (domain size, Reynolds number) as a constant
channel.

A :class:`Solver` declares whether it can be differentiated. The state enters a step twice,
as the network sees it (``u_net``) and as the solver sees it (``u_phys``), so a gradient-flow
policy (:mod:`physgrad.rollout.policy`) can stop the solver's input statically: the
no-temporal-gradient modality never calls the solver's derivative, and a solver that
cannot be differentiated (:class:`NonDifferentiable`, or an external code) trains under it.
In the sequential compositions the network's input is the solver's output, so it follows
the solver's input path.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import ArrayLike
from jaxtyping import Array


class Solver(eqx.Module):
    """A numerical solver step per sample: ``step(u, cond) -> (u⁺, ok)``.

    ``u`` has shape (C, *N); ``cond`` is the sample's conditioning scalar (e.g. an index
    into per-condition operators); ``ok`` is False when the solver reports a failure (the
    unrolled methods then skip the update, as List et al.'s KOLM code does for a
    non-converged linear solve). ``differentiable`` declares whether reverse-mode
    derivatives of the step exist.
    """

    differentiable: ClassVar[bool] = True

    @abc.abstractmethod
    def __call__(self, u: Array, cond: ArrayLike) -> Array: ...

    def step(self, u: Array, cond: ArrayLike) -> tuple[Array, Array]:
        """One step and whether it succeeded (default: the result is finite)."""
        u_next = self(u, cond)
        return u_next, jnp.all(jnp.isfinite(u_next))


class NotDifferentiableError(TypeError):
    """Raised when a solver declared non-differentiable is differentiated."""


class NonDifferentiable(Solver):
    """A solver whose reverse-mode derivative raises: a stand-in for an external or legacy
    solver (List et al.'s point: such a solver still trains under ``nog`` and ``one``)."""

    differentiable: ClassVar[bool] = False
    solver: Solver

    def __call__(self, u, cond):
        return self.step(u, cond)[0]

    def step(self, u, cond):
        """The wrapped solver's step and its failure flag; differentiating it raises."""
        return _no_vjp(u, self.solver, cond)


@eqx.filter_custom_vjp
def _no_vjp(u, solver, cond):
    return solver.step(u, cond)


@_no_vjp.def_fwd
def _no_vjp_fwd(perturbed, u, solver, cond):
    return solver.step(u, cond), None


@_no_vjp.def_bwd
def _no_vjp_bwd(residuals, g, perturbed, u, solver, cond):
    raise NotDifferentiableError(
        f"{type(solver).__name__} is not differentiable: train with a gradient-flow policy that stops the "
        "solver's input (physgrad.rollout.S(), or teacher_forcing=True)"
    )


Network = Callable[[Array, ArrayLike], Array]  # f_θ(u, cond) -> a state-shaped output


class AbstractComposition(eqx.Module):
    """How one stepper step combines the solver P and the network f_θ (module table).

    ``composition(solver, network, u_net, u_phys, cond) -> (u⁺, ok)`` for one sample: ``u_net``
    is the state as the network sees it, ``u_phys`` as the solver sees it (the same array
    unless a gradient-flow policy stops one of them), ``ok`` the solver's success flag.
    ``uses_solver`` declares whether the step calls P at all (the prediction setup does
    not: its problems then build no solver and declare the rollout differentiable).
    """

    uses_solver: ClassVar[bool]

    @abc.abstractmethod
    def __call__(
        self, solver: Solver | None, network: Network, u_net: Array, u_phys: Array, cond: ArrayLike
    ) -> tuple[Array, Array]: ...


class AbstractPrediction(AbstractComposition):
    """The prediction setup: the network alone steps the state; ``u_phys`` is unused."""

    uses_solver: ClassVar[bool] = False

    @abc.abstractmethod
    def predict(self, network: Network, u: Array, cond: ArrayLike) -> Array:
        """u⁺ from the state ``u`` as the network sees it."""

    def __call__(self, solver, network, u_net, u_phys, cond):
        return self.predict(network, u_net, cond), jnp.asarray(True)


class AbstractCorrection(AbstractComposition):
    """The correction setup: the solver steps the state and the network corrects it."""

    uses_solver: ClassVar[bool] = True

    @abc.abstractmethod
    def correct(self, network: Network, u: Array, p: Array, cond: ArrayLike) -> Array:
        """u⁺ from the state ``u`` as the network sees it and the solver's step ``p = P(u)``."""

    def __call__(self, solver, network, u_net, u_phys, cond):
        if solver is None:
            raise ValueError(f"{type(self).__name__} corrects a solver; the problem gave none")
        p, ok = solver.step(u_phys, cond)
        return self.correct(network, u_net, p, cond), ok


class Prediction(AbstractPrediction):
    """u⁺ = f_θ(u): the network replaces the solver (List et al.'s prediction setup)."""

    def predict(self, network, u, cond):
        return network(u, cond)


class Residual(AbstractPrediction):
    """u⁺ = u + f_θ(u): the network predicts the change of the state."""

    def predict(self, network, u, cond):
        return u + network(u, cond)


class Parallel(AbstractCorrection):
    """u⁺ = P(u) + α f_θ(u): solver and network side by side (List et al.'s KS setup, with
    α the solver's substep Δt)."""

    scale: float = eqx.field(static=True, default=1.0)  # α

    def correct(self, network, u, p, cond):
        return p + self.scale * network(u, cond)


class Sequential(AbstractCorrection):
    """u⁺ = f_θ(P(u)): the network post-processes the solver's step."""

    def correct(self, network, u, p, cond):
        return network(p, cond)


class Bypass(AbstractCorrection):
    """u⁺ = P(u) + α f_θ(P(u)): sequential with a bypass of the solver's step (List et al.'s
    Kolmogorov setup)."""

    scale: float = eqx.field(static=True, default=1.0)  # α

    def correct(self, network, u, p, cond):
        return p + self.scale * network(p, cond)


def stack_solvers(solvers):
    """Solvers that differ only in array values (e.g. one per domain size), stacked into one
    whose arrays have a leading axis; :func:`select` picks one inside a vmap."""
    parts = [eqx.partition(s, eqx.is_array) for s in solvers]
    arrays = jax.tree.map(lambda *a: jnp.stack(a), *[a for a, _ in parts])
    return arrays, parts[0][1]


def select(stacked, index):
    """The ``index``-th solver of :func:`stack_solvers`' output."""
    arrays, static = stacked
    return eqx.combine(jax.tree.map(lambda a: a[index], arrays), static)


def single_precision(tree):
    """Float64/complex128 arrays of a pytree cast to float32/complex64: solvers built in
    float64 (inside :func:`physgrad.precision.float64_scope`, for accurate coefficients)
    would otherwise promote the float32 states."""

    def cast(a):
        if eqx.is_array(a) and a.dtype == jnp.float64:
            return a.astype(jnp.float32)
        if eqx.is_array(a) and a.dtype == jnp.complex128:
            return a.astype(jnp.complex64)
        return a

    return jax.tree.map(cast, tree)


class Repeated(Solver):
    """``substeps`` applications of a per-sample stepper (e.g. an exponax ETDRK stepper on
    one state (C, *N)); the conditioning value is not used (select the stepper instead).

    The state keeps its dtype: a stepper built with x64 on (exponax then holds float64
    coefficients) would promote a float32 state to float64 at every step, which a rollout's
    ``lax.scan`` refuses (its carry changes type); each step's result is cast back to the
    state's dtype (:func:`single_precision` rounds the coefficients themselves instead)."""

    stepper: Callable[[Array], Array]  # an equinox module
    substeps: int = eqx.field(static=True, default=1)

    def __call__(self, u, cond):
        dtype = u.dtype
        for _ in range(self.substeps):
            u = self.stepper(u).astype(dtype)
        return u
