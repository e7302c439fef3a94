"""Differentiable-physics (DP) gradients.

The direction is the gradient of the batch-mean loss back-propagated through network and
simulator,

    d = ∇_θ L,      L = (1/b) Σ_i L_i(P(f(x_i; θ))),

which any optax optimizer (Adam, SGD, …) turns into a step. This is the baseline every
physics-based deep learning paper compares against.
"""

from __future__ import annotations

from typing import ClassVar

import jax
import optax

from .base import OPEN_LOOP, AbstractRule, Estimator, Objective, Part
from .method import Method


class Gradient(AbstractRule):
    """``d = ∇_θ L`` with ``L`` the batch-mean loss (plain back-propagation)."""

    part: ClassVar[Part] = OPEN_LOOP
    name: ClassVar[str] = "the DP gradient"

    def __call__(self, objective, params, batch):
        loss, grads = jax.value_and_grad(objective.batch_loss)(params, batch)
        return grads, {"loss": loss}


def dp(predict, loss) -> Estimator:
    """The DP gradient of the batch-mean loss, ``(params, batch) -> (∇_θ L, {"loss": L})``.

    Arguments:
        predict: ``predict(params, sample) -> y``, network and simulator for one sample.
        loss: ``loss(y, sample) -> L_i``, the per-sample loss.
    """
    return Estimator(Gradient(), Objective(predict, loss))


def LossAwareDP(  # a preset is a constructor; it keeps the name of the class it was
    rule: AbstractRule, optimizer: optax.GradientTransformation, extras: tuple[str, ...] = ("value",)
) -> Method:
    """DP gradients (or another ``rule``'s direction) applied by an optax optimizer that may
    also need the loss function: ``Method(rule, optimizer, extras=extras)``.

    The optimizer's update receives the keyword extras named in ``extras``, from:
    ``value`` (the batch loss), ``grad`` (the DP gradient), ``value_fn`` and ``obj_fn``
    (the batch loss as a function of the parameters on this batch) — what optax's
    line-search L-BFGS (``optax.lbfgs``: value, grad, value_fn) and Sophia's Hessian
    estimate (``optax.contrib.sophia``: obj_fn) ask for. Only the named ones are passed
    because some optax transformations refuse extras they do not consume.
    """
    return Method(rule, optimizer, extras=tuple(extras))
