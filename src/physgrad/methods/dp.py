"""Differentiable-physics (DP) gradients applied by any optax optimizer.

The update direction is ∇_θ L with L = (1/b) Σ_i L_i(P(f(x_i; θ))) back-propagated through
network and simulator; the optimizer (Adam, SGD, …) turns it into a step. This is the
baseline every physics-based deep learning paper compares against.
"""

from __future__ import annotations

import equinox as eqx
import jax
import optax

from .base import AbstractMethod


class DifferentiablePhysics(AbstractMethod):
    """``θ ← θ + optimizer(∇_θ L)`` with ``L`` the batch-mean loss."""

    optimizer: optax.GradientTransformation = eqx.field(static=True)

    def init(self, params):
        return self.optimizer.init(params)

    def step(self, objective, params, state, batch):
        loss, grads = jax.value_and_grad(objective.batch_loss)(params, batch)
        updates, state = self.optimizer.update(grads, state, params)
        return optax.apply_updates(params, updates), state, {"loss": loss}


# ε = 1e-7 is the Keras default that the HIG and StableBPTT papers' baselines used.


def adam(*, lr: float = 1e-3, b1: float = 0.9, b2: float = 0.999, eps: float = 1e-7):
    """Adam on DP gradients (Kingma & Ba 2015; Keras ε = 1e-7)."""
    return DifferentiablePhysics(optax.adam(lr, b1=b1, b2=b2, eps=eps))


def sgd(*, lr: float = 1e-2, momentum: float = 0.0):
    """Plain (or momentum) SGD on DP gradients: θ ← θ − η ∇L."""
    return DifferentiablePhysics(optax.sgd(lr, momentum=momentum or None))


def rmsprop(*, lr: float = 1e-3, decay: float = 0.9, eps: float = 1e-7):
    """RMSprop on DP gradients (Tieleman & Hinton 2012; Keras defaults)."""
    return DifferentiablePhysics(optax.rmsprop(lr, decay=decay, eps=eps))


def adagrad(*, lr: float = 1e-2, initial_accumulator: float = 0.1, eps: float = 1e-7):
    """Adagrad on DP gradients (Duchi et al. 2011; Keras defaults)."""
    return DifferentiablePhysics(
        optax.adagrad(lr, initial_accumulator_value=initial_accumulator, eps=eps)
    )


def adadelta(*, lr: float = 1.0, rho: float = 0.95, eps: float = 1e-7):
    """Adadelta on DP gradients (Zeiler 2012: η = 1, ρ = 0.95)."""
    return DifferentiablePhysics(optax.adadelta(lr, rho=rho, eps=eps))


# The DP optimizers with their defaults above, by name, for methods that apply an optax
# optimizer to some other direction (SIP's proxy gradient): name -> (lr -> transformation).
OPTIMIZERS = {
    factory.__name__: (lambda lr, factory=factory: factory(lr=lr).optimizer)
    for factory in (adam, sgd, rmsprop, adagrad, adadelta)
}
