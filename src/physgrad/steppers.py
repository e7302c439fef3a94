"""Neural time-steppers: prediction and correction compositions of a solver and a network.

List, Chen, Bali & Thuerey, "Differentiability in unrolled training of neural physics
simulators on transient dynamics", CMAME 2025.
One step u ↦ u⁺ of a stepper, with P the (coarse) numerical solver and f_θ the network:

================  ==============================  =======================================
setup             composition                     u⁺
================  ==============================  =======================================
prediction        ``full``                        f_θ(u)
prediction        ``residual``                    u + f_θ(u)
correction        ``parallel`` (List's KS)        P(u) + α f_θ(u)
correction        ``sequential``                  f_θ(P(u))
correction        ``bypass`` (List's KOLM)        P(u) + α f_θ(P(u))
================  ==============================  =======================================

α is the problem's network scale (List's KS uses Δt). The network also receives the
sample's conditioning value (domain size, Reynolds number) as a constant channel.

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
from jaxtyping import Array

SETUPS = ("prediction", "correction")
COMPOSITIONS = {"prediction": ("full", "residual"), "correction": ("parallel", "sequential", "bypass")}


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
    def __call__(self, u: Array, cond: Array) -> Array: ...

    def step(self, u: Array, cond: Array) -> tuple[Array, Array]:
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
        f"{type(solver).__name__} is not differentiable: train with a method that never "
        "differentiates the solver (one, nog)"
    )


def check_composition(setup: str, composition: str) -> None:
    """Raise a one-line ``ValueError`` for an unknown setup or composition."""
    if setup not in SETUPS:
        raise ValueError(f"unknown setup {setup!r}; valid choices: {', '.join(SETUPS)}")
    if composition not in COMPOSITIONS[setup]:
        raise ValueError(
            f"unknown composition {composition!r} for the {setup} setup; valid choices: {', '.join(COMPOSITIONS[setup])}"
        )


def stepper_step(setup: str, composition: str, solver: Solver | None, network, u_net, u_phys, cond, scale: float = 1.0):
    """One stepper step for one sample (see the module table): ``(u⁺, ok)``.

    ``network(u, cond) -> Δ`` maps a state and its conditioning value to a state-shaped
    output. In the prediction setup the solver is not called and ``u_phys`` is unused.
    """
    if setup == "prediction":
        out = network(u_net, cond)
        return (u_net + out if composition == "residual" else out), jnp.asarray(True)
    if solver is None:
        raise ValueError(f"the {setup} setup needs a solver")
    p, ok = solver.step(u_phys, cond)
    if composition == "parallel":
        return p + scale * network(u_net, cond), ok
    if composition == "sequential":
        return network(p, cond), ok
    return p + scale * network(p, cond), ok  # bypass


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
