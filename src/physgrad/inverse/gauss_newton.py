"""``GaussNewton``: one pseudo-inverse step of the per-sample Jacobian.

    x̃ = x + J⁺ (y_t − y),     J = ∂P/∂x at x  (dim y × dim x),

with singular values below ``rcond · σ_max`` dropped (NumPy's ``pinv(rcond)``). Exact in one
step for affine P; the minimum-norm solution of an under-determined P is the one closest
to x. The PBDL book's SIP on the linear oscillators uses ``pinv(J, rcond=1e-5)``
(its linear-oscillators notebook). Assumes real x; complex outputs enter as (Re, Im) pairs. Cost: one
Jacobian (forward mode, dim x JVPs) and one SVD per sample. Converged = finite.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .base import AbstractInverseSolver, InverseResult, all_finite, as_flat_real, flat_physics


class GaussNewton(AbstractInverseSolver):
    """x̃ = x + pinv(∂P/∂x, rcond) (y_t − y)."""

    rcond: float = eqx.field(static=True, default=1e-5)

    def __call__(self, simulate, x, y, y_target, sample):
        forward, x_flat = flat_physics(simulate, x, sample)
        jac = jax.jacfwd(forward)(x_flat)
        step = jnp.linalg.pinv(jac, rtol=self.rcond) @ (as_flat_real(y_target) - as_flat_real(y))
        x_new = (x_flat + step).reshape(x.shape)
        return InverseResult(x_new, all_finite(x_new))
