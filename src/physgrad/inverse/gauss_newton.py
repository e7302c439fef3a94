"""``GaussNewton``: one pseudo-inverse step of the per-sample Jacobian.

    x̃ = x + J⁺ (y_t − y),     J = ∂P/∂x at x  (dim y × dim x),

with singular values below ``rcond · σ_max`` dropped (NumPy's ``pinv(rcond)``). Exact in one
step for affine P; the minimum-norm solution of an under-determined P is the one closest
to x. The PBDL book's SIP on the linear oscillators uses ``pinv(J, rcond=1e-5)``
(its linear-oscillators notebook). Assumes real x; complex outputs enter as (Re, Im) pairs.
Cost: one Jacobian and one SVD per sample. Converged = finite.

The Jacobian is built in forward mode (dim x JVPs) or reverse mode (dim y VJPs), a mode
object of :mod:`physgrad.jacobian`: ``jacobian=AutoMode()`` (default) takes reverse mode when the simulator has no forward mode
(a ``jax.custom_vjp`` such as PhiFlow's solves, :mod:`physgrad.problems.sim.phiflow`: detected at trace
time, :func:`physgrad.jacobian.supports_forward_mode`) or when dim y < dim x, else forward
mode; ``ForwardMode()`` and ``ReverseMode()`` force one. Both give the same J up to rounding.
The strings ``"auto"|"forward"|"reverse"`` still work for one release, with a
``DeprecationWarning``.

Internal module: the public names are those :mod:`physgrad.inverse` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..jacobian import AbstractJacobianMode, AutoMode, as_jacobian_mode, dense_jacobian
from .base import AbstractInverseSolver, InverseResult, all_finite, as_flat_real, flat_physics


class GaussNewton(AbstractInverseSolver):
    """x̃ = x + pinv(∂P/∂x, rcond) (y_t − y); ``jacobian``: a mode object (``AutoMode()``,
    ``ForwardMode()``, ``ReverseMode()``)."""

    rcond: float = eqx.field(static=True, default=1e-5)
    jacobian: AbstractJacobianMode = eqx.field(static=True, default=AutoMode(), converter=as_jacobian_mode)

    def __call__(self, simulate, x, y, y_target, sample):
        forward, x_flat = flat_physics(simulate, x, sample)
        residual = as_flat_real(y_target) - as_flat_real(y)
        jac = dense_jacobian(
            forward, x_flat, residual.size, self.jacobian, source=simulate, what="GaussNewton(jacobian='forward')"
        )
        step = jnp.linalg.pinv(jac, rtol=self.rcond) @ residual
        x_new = (x_flat + step).reshape(x.shape)
        return InverseResult(x_new, all_finite(x_new))
