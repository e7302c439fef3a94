"""``SaddleFreeNewton``: per-sample Newton on |Hessian| with the SIP authors' step limit.

For ℓ(x) = ½‖P(x) − y_t‖² with gradient g and Hessian H = V diag(s) Vᵀ (``eigh``):

    ĝ = Vᵀ g,   n_i = |ĝ_i / s_i|                       (|eigenvalue| steps, Dauphin et al.)
    if max_loss_change:  n_i ← min(n_i, |max_loss_change / ĝ_i|)  where s_i ≤ s̄,
                         s̄ = |Π s_i|^{1/d} (geometric mean)
    x̃ = x − V (sign(ĝ) ⊙ n)                             (always a descent direction)

Directions of small or negative curvature would otherwise get huge steps; the limit caps
the first-order loss change there at ``max_loss_change`` (0.2: the SIP authors' setting
for the rotated sine of their Fig. 5); a zero eigenvalue gets the capped step. Without a
limit, zero divisions give zero steps (``divide_no_nan``, as the authors'). Assumes a small x (dense
d × d Hessian per sample). Converged = finite. The Hessian is forward over reverse
(``jax.hessian``), or reverse over reverse for a simulator without forward mode
(:func:`physgrad.jacobian.dense_hessian`); a one-line ``ValueError`` if both fail.

Internal module: the public names are those :mod:`physgrad.inverse` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..jacobian import dense_hessian
from .base import AbstractInverseSolver, InverseResult, all_finite, as_flat_real, flat_physics, half_squared_misfit


def _divide_no_nan(a, b):
    safe = jnp.where(b == 0, 1.0, b)
    return jnp.where(b == 0, 0.0, a / safe)


def saddle_free_newton_step(grad, hessian, max_loss_change=None):
    """The limited |H|-Newton step (d,) from a gradient (d,) and a symmetric Hessian (d, d)."""
    s, v = jnp.linalg.eigh(hessian)
    g_eig = v.T @ grad
    newton = jnp.abs(_divide_no_nan(g_eig, s))
    if max_loss_change is not None:
        # geometric mean of |s| through logs (a product of d eigenvalues over/underflows)
        s_mean = jnp.exp(jnp.mean(jnp.log(jnp.abs(s))))
        cap = jnp.abs(_divide_no_nan(jnp.asarray(max_loss_change, grad.dtype), g_eig))
        # zero curvature: the cap alone sets the step (continuous as s → 0)
        newton = jnp.where(s == 0, jnp.inf, newton)
        newton = jnp.where(s > s_mean, newton, jnp.minimum(newton, cap))
    return v @ (-jnp.sign(g_eig) * newton)


class SaddleFreeNewton(AbstractInverseSolver):
    """x̃ = x + saddle-free Newton step on ½‖P(x) − y_t‖², limited as in the SIP code."""

    max_loss_change: float | None = eqx.field(static=True, default=0.2)

    def __call__(self, simulate, x, y, y_target, sample):
        forward, x_flat = flat_physics(simulate, x, sample)
        objective = half_squared_misfit(forward, as_flat_real(y_target))
        grad = jax.grad(objective)(x_flat)
        hessian = dense_hessian(
            objective, x_flat, what="SaddleFreeNewton", source=simulate,
            alternative="use GaussNewton() (reverse-mode Jacobian) or LBFGS() for this simulator",
        )  # fmt: skip
        x_new = (x_flat + saddle_free_newton_step(grad, hessian, self.max_loss_change)).reshape(x.shape)
        return InverseResult(x_new, all_finite(x_new))
