"""Newton's method on the network (or free-variable) parameters, for small problems.

    Δθ = −η (H + λ I)⁻¹ ∇_θ L,      H = ∇²_θ L  (dense, dim θ × dim θ)

with L the batch-mean loss. This is the "Newton" baseline of the SIP paper's 2D toy
(η = 1/3, sip.md §2.1) and is meant for direct optimisation of a few variables
(``--no-network``): the dense Hessian costs O(dim θ²) memory. A singular H gives a
non-finite step, which the engine records as divergence.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jax.flatten_util import ravel_pytree

from .base import AbstractMethod


class Newton(AbstractMethod):
    """``θ ← θ − η (H + λI)⁻¹ ∇L`` with the exact dense Hessian of the batch loss."""

    lr: float = eqx.field(static=True)
    damping: float = eqx.field(static=True)

    def init(self, params):
        return optax.EmptyState()

    def step(self, objective, params, state, batch):
        flat, unravel = ravel_pytree(params)

        def loss_fn(theta):
            return objective.batch_loss(unravel(theta), batch)

        loss, grad = jax.value_and_grad(loss_fn)(flat)
        hessian = jax.hessian(loss_fn)(flat) + self.damping * jnp.eye(flat.size, dtype=flat.dtype)
        new = flat - self.lr * jnp.linalg.solve(hessian, grad)
        return unravel(new), state, {"loss": loss}


def newton(*, lr: float = 1.0, damping: float = 0.0):
    """Newton's method with the dense Hessian of the batch loss: −η (H + λI)⁻¹ ∇L (small problems)."""
    return Newton(lr, damping)
