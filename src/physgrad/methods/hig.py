"""Half-inverse gradients (HIG) and Gauss–Newton: κ-powers of the joint Jacobian.

Source: Schnell, Holl, Thuerey, *Half-Inverse Gradients for Physical Deep Learning*,
ICLR 2022 (the update Δθ_HIG of §3 and the truncated pseudo-inverse of its code).

With ``J = ∂y/∂θ`` the per-sample Jacobians of the *simulator output* stacked
sample-major (rows = b · dim y, columns = all network parameters) and
``g = ∂L/∂y`` the gradient of the batch-mean loss w.r.t. the outputs,

    d = V Σ^κ Uᵀ g,      J = U Σ Vᵀ (thin SVD, σ ≤ τ σ_max dropped),

with κ = −½ (HIG) or κ = −1 (Gauss–Newton). The paper applies it with plain SGD
(θ ← θ − η d, Keras SGD without momentum); any optax chain composes. How ``V Σ^κ Uᵀ g``
is computed is a route object (:mod:`physgrad.routes`).
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
from jax.flatten_util import ravel_pytree

from ..routes import AbstractRoute, Auto, JointJacobian, alternatives
from .base import AbstractJacobianRule, Estimator, Objective


class JacobianPower(AbstractJacobianRule):
    """``d = J^κ g`` with the joint stacked Jacobian (HIG for κ = −½, GN for κ = −1)."""

    exponent: float = eqx.field(static=True)
    truncation: float = eqx.field(static=True, default=1e-6)
    route: AbstractRoute = eqx.field(static=True, default=Auto())

    def __check_init__(self):
        if not self.truncation >= 0:
            raise ValueError(f"truncation must be >= 0, got {self.truncation}")
        if not isinstance(self.route, AbstractRoute):
            raise ValueError(f"route must be a physgrad.routes object (Auto(), Gram(), SVD(), …), got {self.route!r}")

    name: ClassVar[str] = "the Jacobian methods"

    def check_batch_size(self, batch_size):
        self.route.check_batch_size(batch_size)

    def footprint(self, objective, params, batch, devices=1):
        return self.route.footprint(objective, params, batch, devices)

    def footprint_note(self, objective, params, batch):
        jacobian = JointJacobian.of(objective, params, batch)
        name = self.route.name()
        if isinstance(self.route, Auto):  # say which route auto takes for this batch
            name += f" ({self.route.resolve(jacobian).name()})"
        return f"route {name}: {jacobian.rows} × {jacobian.size} Jacobian"

    def describe(self, objective, params, batch):
        """``{"route": name, "jacobian": (rows, P)}``: the route that runs on this batch
        (``Auto()`` resolved; a tall J sends ``Structured()`` to ``gram``) and J's shape."""
        jacobian = JointJacobian.of(objective, params, batch)
        return {"route": self.route.resolve(jacobian).name(), "jacobian": jacobian.shape}

    def lighter(self, batch_size):
        """This rule with each other route (:func:`physgrad.routes.alternatives`): the exact
        ones by speed, then blockgram with ever more sample groups, then lanczos."""
        return [dataclasses.replace(self, route=route) for route in alternatives(self.route, batch_size)]

    def __call__(self, objective, params, batch):
        return self.filtered(objective, params, batch, self.exponent)

    def filtered(self, objective, params, batch, spectrum):
        """``V f(Σ) Uᵀ g`` by this rule's route and truncation for another spectral filter
        ``f`` (a number κ or :class:`physgrad.routes.Damped`): ``(direction, stats)``.

        ``stats``: ``loss``, ``route`` (the code of the route that ran,
        ``physgrad.routes.ROUTE_NAMES[code]``), ``rank`` (singular values kept),
        ``sigma_max`` and ``sigma_min_kept`` (:mod:`physgrad.routes`)."""
        # The joint Jacobian's shape facts, built once (one trace of predict) for the route.
        jacobian = JointJacobian.of(objective, params, batch)
        direction, loss, stats = self.route.resolve(jacobian).compute(jacobian, spectrum, self.truncation)
        _, unravel = ravel_pytree(params)
        return unravel(direction), {"loss": loss, **stats}


def hig(predict, loss, *, truncation: float = 1e-6, route: AbstractRoute = Auto()) -> Estimator:
    """Half-inverse gradients: ``(params, batch) -> (V Σ^{−½} Uᵀ g, stats)``.

    Apply with ``optax.sgd(η)`` for the paper's update θ ← θ − η V Σ^{−½} Uᵀ g (η = 1 on
    the oscillators, Schnell et al. 2022), or any other chain. The direction is linear in
    ``g``, so η depends on the loss's scale: a per-sample loss that is a mean over n output
    cells instead of a sum needs an n× larger η (docs/methods.md); sweep η over decades.

    Arguments:
        predict: ``predict(params, sample) -> y``, network and simulator for one sample.
        loss: ``loss(y, sample) -> L_i``; the rule uses the batch mean.
        truncation: τ; singular values σ ≤ τ·σ_max are dropped (not clamped).
        route: how the κ-power is computed (:mod:`physgrad.routes`); ``Auto()`` picks
            the exact float64 Gram route or the SVD by the shape of J.

    ``stats``: ``loss``; ``route``, the code of the route that ran
    (``physgrad.routes.ROUTE_NAMES[int(stats["route"])]``; ``estimate.describe(params,
    batch)`` names it from shapes alone, before a step); ``rank``, the number of singular
    values kept; ``sigma_max`` and ``sigma_min_kept``, the kept range of J's spectrum.
    """
    return Estimator(JacobianPower(-0.5, truncation, route), Objective(predict, loss))


def gauss_newton(predict, loss, *, truncation: float = 1e-6, route: AbstractRoute = Auto()) -> Estimator:
    """Gauss–Newton: ``(params, batch) -> (J⁺ g, stats)``, the truncated pseudo-inverse
    (κ = −1) of the same joint Jacobian; arguments as :func:`hig`."""
    return Estimator(JacobianPower(-1.0, truncation, route), Objective(predict, loss))
