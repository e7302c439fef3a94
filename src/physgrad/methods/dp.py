"""Differentiable-physics (DP) gradients.

The direction is the gradient of the batch-mean loss back-propagated through network and
simulator,

    d = ∇_θ L,      L = (1/b) Σ_i L_i(P(f(x_i; θ))),

which any optax optimizer (Adam, SGD, …) turns into a step. This is the baseline every
physics-based deep learning paper compares against.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import optax

from .base import OPEN_LOOP, AbstractRule, Estimator, Method, Objective, Part, trainable, with_extra_args


class Gradient(AbstractRule):
    """``d = ∇_θ L`` with ``L`` the batch-mean loss (plain back-propagation)."""

    def __call__(self, objective, params, batch):
        loss, grads = jax.value_and_grad(objective.batch_loss)(params, batch)
        return grads, {"loss": loss}

    part: ClassVar[Part] = OPEN_LOOP
    name: ClassVar[str] = "the DP gradient"


def dp(predict, loss) -> Estimator:
    """The DP gradient of the batch-mean loss, ``(params, batch) -> (∇_θ L, {"loss": L})``.

    Arguments:
        predict: ``predict(params, sample) -> y``, network and simulator for one sample.
        loss: ``loss(y, sample) -> L_i``, the per-sample loss.
    """
    return Estimator(Gradient(), Objective(predict, loss))


class LossAwareDP(Method):
    """DP gradients applied by an optax optimizer that may also need the loss function.

    The optimizer's update receives the keyword extras named in ``extras``, from:
    ``value`` (the batch loss), ``grad`` (the DP gradient), ``value_fn`` and ``obj_fn``
    (the batch loss as a function of the parameters on this batch) — what optax's
    line-search L-BFGS (``optax.lbfgs``: value, grad, value_fn) and Sophia's Hessian
    estimate (``optax.contrib.sophia``: obj_fn) ask for. Only the named ones are passed
    because some optax transformations refuse extras they do not consume.
    """

    extras: tuple[str, ...] = eqx.field(static=True, default=("value",))

    def __check_init__(self):
        unknown = set(self.extras) - {"value", "grad", "value_fn", "obj_fn"}
        if unknown:
            raise ValueError(
                f"unknown optimizer extras {sorted(unknown)}; valid choices: grad, obj_fn, value, value_fn"
            )

    def step(self, objective, params, state, batch):
        params, static = trainable(params)  # the array leaves (a whole module's others come back unchanged)
        objective = objective.bind_static(static)
        direction, stats = self.rule(objective, params, batch)

        def batch_loss(p):
            return objective.batch_loss(p, batch)

        available = {"value": stats["loss"], "grad": direction, "value_fn": batch_loss, "obj_fn": batch_loss}
        extras = {name: available[name] for name in self.extras}
        updates, state = with_extra_args(self.optimizer).update(direction, state, params, **extras)
        return eqx.combine(optax.apply_updates(params, updates), static), state, stats
