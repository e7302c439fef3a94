"""``LBFGS``: minimise the per-sample physics misfit, started at the prediction.

    x̃ = argmin_x ½‖P(x) − y_t‖²   by optimistix's L-BFGS from x₀ = x (the current prediction),

so the iterate stays in the basin of the solution closest to the prediction (the "numerical
local inverse" of the PBDL book's 2D toy and the SIP heat v1 variant, sip.md §2.1, §4).
Stops when optimistix's Cauchy criterion holds with ``rtol = atol = tol`` or after
``max_steps``; converged = optimistix reported success (not out of steps) and x̃ finite.
Needs a differentiable P (gradients in x only). Runs in float64 whatever the prediction's
dtype (optimistix's line search mixes in float64 scalars when JAX's x64 mode is on, and a
tight ``tol`` needs it anyway); x̃ is returned in the prediction's dtype.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx

from .base import AbstractInverseSolver, InverseResult, all_finite, as_flat_real, flat_physics, half_squared_misfit


class LBFGS(AbstractInverseSolver):
    """x̃ = L-BFGS minimiser of ½‖P(x) − y_t‖² from the prediction (optimistix)."""

    max_steps: int = eqx.field(static=True, default=100)
    tol: float = eqx.field(static=True, default=1e-6)

    def __call__(self, simulate, x, y, y_target, sample):
        forward, x_flat = flat_physics(simulate, x, sample)
        objective = half_squared_misfit(forward, as_flat_real(y_target).astype(jnp.float64))
        solution = optx.minimise(
            objective, optx.LBFGS(rtol=self.tol, atol=self.tol), x_flat.astype(jnp.float64),
            max_steps=self.max_steps, throw=False,
        )  # fmt: skip
        x_new = solution.value.reshape(x.shape).astype(x.dtype)
        ok = (solution.result == optx.RESULTS.successful) & all_finite(x_new)
        return InverseResult(x_new, ok)
