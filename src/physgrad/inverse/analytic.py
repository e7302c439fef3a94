"""``Analytic``: the problem's own (local) inverse.

Assumptions: ``fn(x, y, y_target, sample) -> x̃`` is the problem's closed-form inverse,
conditioned on the current prediction ``x`` where P is not injective (pick the solution
closest to x, as the SIP paper prescribes). Examples: Poisson ``x̃ = x + ∇²(y_t − y)``; exp ``x̃ = log y_t``;
the heat equation's damped Fourier deconvolution. Converged = all entries finite.

Internal module: the public names are those :mod:`physgrad.inverse` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx

from .base import AbstractInverseSolver, InverseResult, all_finite


class Analytic(AbstractInverseSolver):
    """x̃ = fn(x, y, y_target, sample), a closed-form local inverse.

    ``fn=None`` stands for the problem's own inverse: SIP binds it from the problem
    (``Objective.inverse``) before solving."""

    fn: Callable | None = eqx.field(static=True, default=None)

    def __call__(self, simulate, x, y, y_target, sample):
        if self.fn is None:
            raise ValueError(
                "Analytic() without fn needs the problem's inverse; pass Analytic(fn) or use it through sip"
            )
        x_new = self.fn(x, y, y_target, sample)
        return InverseResult(x_new, all_finite(x_new))
