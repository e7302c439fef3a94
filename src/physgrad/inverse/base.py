"""The local-inverse contract shared by every solver.

Source: Holl, Koltun, Thuerey, *Scale-invariant Learning by Physics Inversion*, NeurIPS
2022 (the local inverse of its §3); PBDL book, chapter "Scale-invariant physics training".

A local inverse solver maps, for ONE sample, the current prediction ``x`` (where the
simulator gives ``y = P(x)``) and a target ``y_t = y + η (y* − y)`` in y-space to

    x̃ ≈ P⁻¹(y_t; x),

the solution of ``P(x̃) = y_t`` closest to ``x`` (or the solver's best approximation). The
solver runs outside the network's autodiff (SIP applies ``stop_gradient``), so ``simulate``
is only differentiated by solvers that need derivatives in x (Gauss–Newton, Newton,
L-BFGS, Krylov). Every solver returns :class:`InverseResult` with a per-sample
``converged`` flag: a failed solve is reported, never silently used.

Internal module: the public names are those :mod:`physgrad.inverse` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Bool, PyTree


class InverseFailureWarning(RuntimeWarning):
    """Most of a batch's local inverse solves failed in a training step (those samples
    got no update): issued by :func:`physgrad.sip` from inside the jitted step."""


class InverseResult(NamedTuple):
    """``x``: the local inverse x̃ (same shape as the prediction); ``converged``: bool scalar."""

    x: Array
    converged: Bool[Array, ""]


Simulate = Callable[[Array, PyTree], Array]


class AbstractInverseSolver(eqx.Module):
    """``solver(simulate, x, y, y_target, sample) -> InverseResult`` for one sample."""

    @abc.abstractmethod
    def __call__(self, simulate: Simulate, x: Array, y: Array, y_target: Array, sample: PyTree) -> InverseResult: ...


def all_finite(x: Array) -> Bool[Array, ""]:
    return jnp.all(jnp.isfinite(x))


def flat_physics(simulate: Simulate, x: Array, sample: PyTree):
    """``simulate`` as a map between flat real vectors, and the flat x; for dense solvers."""
    shape = x.shape
    if jnp.iscomplexobj(x):
        raise ValueError("the dense inverse solvers need a real-valued prediction x")

    def forward(x_flat):
        y = simulate(x_flat.reshape(shape), sample)
        if jnp.iscomplexobj(y):  # complex outputs enter as (Re, Im) pairs
            y = jnp.stack([y.real, y.imag], axis=-1)
        return y.ravel()

    return forward, x.ravel()


def as_flat_real(y: Array) -> Array:
    if jnp.iscomplexobj(y):
        y = jnp.stack([y.real, y.imag], axis=-1)
    return y.ravel()


def half_squared_misfit(forward, y_target_flat):
    """``ℓ(x) = ½ ‖P(x) − y_t‖²``: the per-sample physics objective an optimiser inverts."""

    def objective(x_flat, _args=None):
        return 0.5 * jnp.sum((forward(x_flat) - y_target_flat) ** 2)

    return objective
