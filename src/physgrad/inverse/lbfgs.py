"""``LBFGS``: minimise the per-sample physics misfit, started at the prediction.

    x̃ = argmin_x ½‖P(x) − y_t‖²   by optimistix's L-BFGS from x₀ = x (the current prediction),

so the iterate stays in the basin of the solution closest to the prediction (the "numerical
local inverse" of the PBDL book's 2D toy and the SIP heat v1 variant).
Stops when optimistix's Cauchy criterion holds with ``rtol = atol = tol`` or after
``max_steps``; converged = optimistix reported success (not out of steps) and x̃ finite.
``accept_last=True`` uses the last iterate when the steps run out (converged = finite and
no worse than the start): the SIP authors' Navier–Stokes variant, 16 L-BFGS iterations with
PhiFlow's ``suppress=[NotConverged]``.
Needs a differentiable P (gradients in x only). Runs in float64 whatever the prediction's
dtype and whether or not the user enabled ``jax_enable_x64``: the solve is scoped with
:func:`physgrad.precision.float64_scope` (a tight ``tol`` needs float64, and optimistix's
line search mixes in float64 scalars wherever x64 is on). Its inputs are constants for
differentiation (a scoped region cannot be transposed outside it; SIP never
differentiates the solve); x̃ is returned in the prediction's dtype.

Internal module: the public names are those :mod:`physgrad.inverse` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ..precision import float64_scope
from .base import AbstractInverseSolver, InverseResult, all_finite, as_flat_real, flat_physics, half_squared_misfit


class LBFGS(AbstractInverseSolver):
    """x̃ = L-BFGS minimiser of ½‖P(x) − y_t‖² from the prediction (optimistix)."""

    max_steps: int = eqx.field(static=True, default=100)
    tol: float = eqx.field(static=True, default=1e-6)
    accept_last: bool = eqx.field(static=True, default=False)

    def __call__(self, simulate, x, y, y_target, sample):
        import optimistix as optx  # here, not at module level: ~0.5 s that `import physgrad` need not pay

        x_in, y_target, sample = jax.lax.stop_gradient((x, y_target, sample))
        with float64_scope():
            forward, x_flat = flat_physics(simulate, x_in, sample)
            objective = half_squared_misfit(forward, as_flat_real(y_target).astype(jnp.float64))
            solution = optx.minimise(
                objective, optx.LBFGS(rtol=self.tol, atol=self.tol), x_flat.astype(jnp.float64),
                max_steps=self.max_steps, throw=False,
            )  # fmt: skip
            x_new = solution.value.reshape(x.shape).astype(x.dtype)  # cast inside: no float64 escapes
            if self.accept_last:  # a budget, not a convergence test: keep any iterate that helped
                start = objective(x_flat.astype(jnp.float64))
                ok = all_finite(x_new) & (objective(solution.value) <= start)
            else:
                ok = (solution.result == optx.RESULTS.successful) & all_finite(x_new)
        return InverseResult(x_new, ok)
