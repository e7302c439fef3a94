"""Differentiable-physics (DP) gradients.

The direction is the gradient of the batch-mean loss back-propagated through network and
simulator,

    d = ∇_θ L,      L = (1/b) Σ_i L_i(P(f(x_i; θ))),

which any optax optimizer (Adam, SGD, …) turns into a step. This is the baseline every
physics-based deep learning paper compares against.
"""

from __future__ import annotations

import jax

from .base import AbstractRule, Estimator, Objective


class Gradient(AbstractRule):
    """``d = ∇_θ L`` with ``L`` the batch-mean loss (plain back-propagation)."""

    def __call__(self, objective, params, batch):
        loss, grads = jax.value_and_grad(objective.batch_loss)(params, batch)
        return grads, {"loss": loss}

    def check(self, objective):
        if objective.predict is None or objective.loss is None:
            raise ValueError("the DP gradient needs predict(params, sample) and loss(y, sample)")
        objective.require_differentiable()


def dp(predict, loss) -> Estimator:
    """The DP gradient of the batch-mean loss, ``(params, batch) -> (∇_θ L, {"loss": L})``.

    Arguments:
        predict: ``predict(params, sample) -> y``, network and simulator for one sample.
        loss: ``loss(y, sample) -> L_i``, the per-sample loss.
    """
    return Estimator(Gradient(), Objective(predict, loss))
