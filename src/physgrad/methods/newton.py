"""Newton's method on the network (or free-variable) parameters, for small problems.

    d = (H + λ I)⁻¹ ∇_θ L,      H = ∇²_θ L  (dense, dim θ × dim θ),

with L the batch-mean loss; ``optax.sgd(η)`` then takes θ ← θ − η d. This is the "Newton"
baseline of the SIP paper's 2D toy (η = 1/3; Holl et al. 2022, Fig. 1) and is meant for
direct optimisation of a few variables (``--no-network``): the dense Hessian costs
O(dim θ²) memory. A singular H gives a non-finite direction, which the engine records as
divergence. The Hessian is forward over reverse, or reverse over reverse for a simulator
without forward mode (:func:`physgrad.jacobian.dense_hessian`; a one-line ``ValueError``
naming the alternatives if both fail).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from ..jacobian import dense_hessian
from .base import OPEN_LOOP, AbstractRule, Estimator, Objective, Part


class Newton(AbstractRule):
    """``d = (H + λI)⁻¹ ∇L`` with the exact dense Hessian of the batch loss."""

    damping: float = eqx.field(static=True, default=0.0)

    part: ClassVar[Part] = OPEN_LOOP
    name: ClassVar[str] = "Newton"

    def __call__(self, objective, params, batch):
        flat, unravel = ravel_pytree(params)

        def loss_fn(theta):
            return objective.batch_loss(unravel(theta), batch)

        loss, grad = jax.value_and_grad(loss_fn)(flat)
        hessian = dense_hessian(
            loss_fn, flat, what="newton", source=objective.predict,
            alternative="use gauss_newton or hig (reverse-mode Jacobians) or dp",
        )  # fmt: skip
        hessian = hessian + self.damping * jnp.eye(flat.size, dtype=flat.dtype)
        return unravel(jnp.linalg.solve(hessian, grad)), {"loss": loss}


def newton(predict, loss, *, damping: float = 0.0) -> Estimator:
    """Newton's direction ``(H + λI)⁻¹ ∇L`` of the batch-mean loss (small problems only).

    Arguments:
        predict, loss: as :func:`physgrad.dp`.
        damping: λ ≥ 0 added to the Hessian's diagonal.
    """
    return Estimator(Newton(damping), Objective(predict, loss))
