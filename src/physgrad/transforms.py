"""Gradient transformations of physgrad's own, for what optax does not provide.

They compose with optax like any of its transformations (``optax.chain``,
``optax.apply_if_finite``, schedules).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax


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
    """
    inner = optax.with_extra_args_support(inner)

    def init(params):
        return NormGuardState(inner.init(params), jnp.zeros((), jnp.float32))

    def update(updates, state, params=None, **extra_args):
        norm = optax.tree.norm(updates)
        within = (state.bound == 0) | (norm <= state.bound)
        new_updates, new_inner = inner.update(updates, state.inner_state, params, **extra_args)
        bound = jnp.where(state.bound == 0, first * norm, decay * state.bound + factor * norm).astype(state.bound.dtype)
        keep = lambda new, old: jax.tree.map(lambda a, b: jnp.where(within, a, b), new, old)  # noqa: E731
        new_updates = jax.tree.map(lambda u: jnp.where(within, u, jnp.zeros_like(u)), new_updates)
        return new_updates, NormGuardState(keep(new_inner, state.inner_state), jnp.where(within, bound, state.bound))

    return optax.GradientTransformationExtraArgs(init, update)
