"""The SVD route: thin SVD of the whole J in its own dtype (the paper's way).

``J = U Σ Vᵀ`` (thin, ``jnp.linalg.svd``), ``J^κ g = V f(Σ) Uᵀ g`` with f the κ-power or
damped filter of :mod:`.spectrum` on the kept singular values. Costs a bidiagonalisation,
O(m P min(m, P)); float32 for float32 networks (as the paper). Differentiable (no float64
scope). Memory: J, its copy in the factorisation and the thin factors U (m × k), V (P × k).

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from .base import AbstractRoute, JointJacobian
from .spectrum import Damped, Spectrum, cast_spectrum, kept_powers, spectrum_stats


class SVD(AbstractRoute):
    """Thin SVD of the whole J (float32 for float32 networks). Under a mesh XLA gathers J."""

    code = 0

    def power(
        self, jacobian: Float[Array, "m p"], grad: Float[Array, " m"], exponent: float | Damped, truncation: float
    ) -> tuple[Float[Array, " p"], Spectrum]:
        """``V f(Σ) Uᵀ g`` of an explicit J and its :func:`~.spectrum.spectrum_stats` (in J's dtype)."""
        u, s, vt = jnp.linalg.svd(jacobian, full_matrices=False)
        direction = vt.T @ (kept_powers(s, exponent, truncation) * (u.T @ grad))
        return direction.astype(jacobian.dtype), cast_spectrum(spectrum_stats(s, truncation), jacobian.dtype)

    def compute(self, jacobian: JointJacobian, exponent, truncation):
        jac, g, loss = jacobian.jacobian_and_gradient()
        direction, spectrum = self.power(jac, g, exponent, truncation)
        return direction, loss, self.stats(spectrum)

    def footprint_of(self, jacobian, devices=1):
        rows, size = jacobian.shape
        # J, its copy in the factorisation and the thin factors U (rows × k), V (P × k).
        return (2 * rows * size + min(rows, size) * (rows + size)) * jacobian.itemsize
