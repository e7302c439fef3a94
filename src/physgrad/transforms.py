"""Gradient transformations of physgrad's own, for what optax does not provide.

They compose with optax like any of its transformations (``optax.chain``,
``optax.apply_if_finite``, schedules).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from .acceptance import keep_where, running_bound


class NormGuardState(NamedTuple):
    """``inner_state`` of the wrapped transformation and the running bound (0: not set)."""

    inner_state: Any
    bound: jax.Array


def norm_guard(
    inner: optax.GradientTransformation, *, factor: float = 10.0, decay: float = 0.9, first: float = 100.0
) -> optax.GradientTransformationExtraArgs:
    """Skip an update whose gradient norm exceeds a running bound.

        accept  ⇔  c = 0  or  ‖g‖ ≤ c,      after an accepted update:  c ← decay·c + factor·‖g‖
                                            (the first sets c = first·‖g‖),

    i.e. c settles near factor / (1 − decay) = 100× the typical norm: a spike two orders
    above the recent gradients is dropped (the inner state and the bound stay, the update
    is zero), as the unrolling study of List et al. (CMAME 2025, §5.4) does for the
    Kolmogorov flow. Extra keyword arguments are passed on to ``inner``.

    The same rule as an acceptance test of a method (its bound in the test's own state,
    the parameters and the whole optimizer state kept on a skip) is
    :class:`physgrad.acceptance.NormBound`; this transformation is for optax chains of
    one's own.
    """
    inner = optax.with_extra_args_support(inner)

    def init(params):
        return NormGuardState(inner.init(params), jnp.zeros((), jnp.float32))

    def update(updates, state, params=None, **extra_args):
        within, bound = running_bound(state.bound, optax.tree.norm(updates), factor, decay, first)
        new_updates, new_inner = inner.update(updates, state.inner_state, params, **extra_args)
        new_updates = keep_where(within, new_updates, optax.tree.zeros_like(new_updates))
        return new_updates, keep_where(within, NormGuardState(new_inner, bound), state)

    return optax.GradientTransformationExtraArgs(init, update)
