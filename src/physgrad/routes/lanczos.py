"""The Lanczos route: a Krylov approximation of the κ-power from Jacobian–vector products.

Source: Saad, *Analysis of some Krylov subspace approximations to the matrix exponential
operator*, SIAM J. Numer. Anal. 29 (1992); Golub & Van Loan, *Matrix Computations*, §10.1.

With ``G = J Jᵀ`` (m × m) and ``f(λ) = λ^{(κ−1)/2}`` (λ > τ² λ_max, else 0), ``J^κ g =
Jᵀ f(G) g``. k steps of Lanczos on ``G`` with the matrix-free product ``G v = J (Jᵀ v)``
(one VJP and one JVP of the batch, ``jax.linearize``), started from ``g``, with full
re-orthogonalisation in float64: ``G Q_k = Q_k T_k + β_k q_{k+1} e_kᵀ`` and

    f(G) g ≈ x_k = ‖g‖ Q_k f(T_k) e₁,     J^κ g ≈ Jᵀ x_k,

with the truncation applied to the Ritz values (θ > τ² θ_max). Memory k × m + the
network's activations; compute 2k batch passes.

**Error bound** (exact arithmetic; Saad 1992, Lemma 3.1 with the polynomial exactness of
Lanczos): ``‖f(G) g − x_k‖₂ ≤ 2 ‖g‖₂ · min_{deg p < k} max_{λ ∈ Λ(G)} |f(λ) − p(λ)|``.
Hence x_k is exact once k reaches the number of distinct eigenvalues of G that g touches
(k = m always suffices), and for f(λ) = λ^{−3/4} on a spectrum in [a, b] the error falls
like ((√(b/a) − 1)/(√(b/a) + 1))^k: the route needs about √(λ_max/λ_min) · log(1/ε) steps,
i.e. σ_max/σ_min·log(1/ε) — it wins only for well-conditioned or fast-decaying spectra, or
where an approximate direction is enough. Each step reports ``‖x_k − x_{k−1}‖ / ‖x_k‖``
(a posteriori estimate of the remaining error). The products ``J v``, ``Jᵀ v`` run in the
network's dtype, so eigenvalues below ~ε_float32·λ_max are not resolved in float32 networks.

The float64 is scoped as the Gram routes' (the network is linearised outside the scope);
the inputs are constants for differentiation.

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..precision import float64_scope
from .base import F64, AbstractMatrixFree, batch_output_map
from .spectrum import Damped, cast_spectrum, gram_power


class Lanczos(AbstractMatrixFree):
    """``steps`` Lanczos steps on J Jᵀ through JVP/VJP products (approximate; exact at
    steps = rows). Logs ``lanczos_change``, the relative change of the last step."""

    code = 4
    steps: int = eqx.field(static=True, default=64)

    def __check_init__(self):
        if self.steps < 1:
            raise ValueError(f"lanczos steps must be >= 1, got {self.steps}")

    def power(self, predict, params, batch, grad, exponent, truncation):
        """``Jᵀ x_k`` (P,) in the parameters' dtype (``steps`` capped at m, where it is
        exact up to rounding) and the :func:`~.spectrum.spectrum_stats` of the Ritz values
        (√ of the eigenvalues of T_k: σ_max is approximated from below first, the kept count
        and σ_min_kept only as far as k steps resolve the spectrum) with ``lanczos_change``
        = ``‖x_k − x_{k−1}‖ / ‖x_k‖``; the estimate and σ's in the caller's default float."""
        # Constants for differentiation: the float64 scope below cannot be transposed outside it.
        params, batch, grad = jax.lax.stop_gradient((params, batch, grad))
        outputs, flat = batch_output_map(predict, params, batch)
        # Linearised here, in the caller's configuration: inside the scope the products only
        # evaluate the traced linear map, in the network's dtype.
        y, jvp = jax.linearize(outputs, flat)
        vjp = jax.linear_transpose(jvp, flat)
        # The estimate leaves the scope as the caller's default float (float64 where x64 is on,
        # as before; float32 otherwise): no float64 array escapes into an x64-off trace.
        outer_float = jax.dtypes.canonicalize_dtype(jnp.float64)
        with float64_scope():
            direction, estimate, spectrum = _lanczos(jvp, vjp, y.dtype, grad, self.steps, exponent, truncation)
            spectrum = {**cast_spectrum(spectrum, outer_float), "lanczos_change": estimate.astype(outer_float)}
            return direction.astype(flat.dtype), spectrum

    def footprint_of(self, jacobian, devices=1):
        return 2 * self.steps * (jacobian.rows + jacobian.size) * F64


def lanczos_half_inverse(
    predict: Callable[[PyTree, PyTree], Array],
    params: PyTree,
    batch: PyTree,
    grad: Float[Array, " m"],
    *,
    steps: int,
    exponent: float | Damped = -0.5,
    truncation: float = 1e-6,
) -> tuple[Float[Array, " p"], Float[Array, ""]]:
    """``J^κ g ≈ Jᵀ x_k`` from ``steps`` Lanczos steps on ``G = J Jᵀ`` (matrix-free):
    ``(direction, estimate)``: :meth:`Lanczos.power`'s direction and ``lanczos_change``."""
    direction, spectrum = Lanczos(steps).power(predict, params, batch, grad, exponent, truncation)
    return direction, spectrum["lanczos_change"]


def _lanczos(jvp, vjp, dtype, grad, steps, exponent, truncation):
    """:meth:`Lanczos.power`'s iteration, run inside its float64 scope; ``dtype`` is the
    outputs' (a simulator may compute in another dtype than the network's parameters: the
    cotangents of ``Jᵀ v`` take the outputs' dtype, ``J v`` the parameters')."""

    def gram_times(v):  # G v = J (Jᵀ v), products in the network's and the simulator's dtypes
        (jtv,) = vjp(v.astype(dtype))
        return jvp(jtv).astype(jnp.float64)

    g = grad.astype(jnp.float64)
    m = g.shape[0]
    k = min(steps, m)
    norm_g = jnp.linalg.norm(g)
    q0 = g / jnp.where(norm_g > 0, norm_g, 1.0)

    def body(i, carry):
        basis, alpha, beta, q = carry
        basis = basis.at[i].set(q)
        z = gram_times(q)
        scale = jnp.linalg.norm(z)
        a = q @ z
        # Full re-orthogonalisation (twice is enough, Kahan–Parlett): Lanczos vectors
        # lose orthogonality as Ritz values converge.
        z = z - basis.T @ (basis @ z)
        z = z - basis.T @ (basis @ z)
        b = jnp.linalg.norm(z)
        # Breakdown (an invariant subspace: the result is already exact): continue with
        # zero vectors; the decoupled zero rows of T add nothing to x_k. With float32
        # products an invariant subspace leaves a residual ~1e-7‖Gq‖ and is not detected;
        # the iteration then goes on with re-orthogonalised rounding noise, which is harmless.
        live = b > 1e-12 * jnp.maximum(scale, 1e-300)
        q_next = jnp.where(live, z / jnp.where(live, b, 1.0), 0.0)
        return basis, alpha.at[i].set(a), beta.at[i].set(jnp.where(live, b, 0.0)), q_next

    init = (jnp.zeros((k, m), jnp.float64), jnp.zeros(k, jnp.float64), jnp.zeros(k, jnp.float64), q0)
    basis, alpha, beta, _ = jax.lax.fori_loop(0, k, body, init)

    def coefficients(n):  # ‖g‖ f(T_n) e₁ padded to k (f on the Ritz values θ = eig T_n)
        t = jnp.diag(alpha[:n]) + jnp.diag(beta[: n - 1], 1) + jnp.diag(beta[: n - 1], -1)
        e1 = jnp.zeros(n, jnp.float64).at[0].set(1.0)
        w, spectrum = gram_power(t, e1, exponent, truncation)
        return jnp.zeros(k, jnp.float64).at[:n].set(norm_g * w), spectrum

    c, spectrum = coefficients(k)
    change = jnp.linalg.norm(c - coefficients(k - 1)[0]) if k > 1 else jnp.array(jnp.inf, jnp.float64)
    estimate = change / jnp.maximum(jnp.linalg.norm(c), 1e-300)
    (direction,) = vjp((basis.T @ c).astype(dtype))
    return direction, estimate, spectrum
