"""Half-inverse gradients without the Jacobian: the routes for networks too large for J.

Source: the κ-power of :mod:`physgrad.half_inverse` (Schnell et al., ICLR 2022); Lanczos
for matrix functions: Saad, *Analysis of some Krylov subspace approximations to the
matrix exponential operator*, SIAM J. Numer. Anal. 29 (1992); Golub & Van Loan,
*Matrix Computations*, §10.1.

For the batch-output map ``F: θ ↦ y`` (m = batch × output size rows, P parameters) with
Jacobian ``J`` and Gram matrix ``G = J Jᵀ = U Λ Uᵀ``,

    J^κ g = Jᵀ f(G) g,      f(λ) = λ^{(κ−1)/2} for λ > τ² λ_max, else 0,

(κ = −½: f(λ) = λ^{−3/4}). The exact Gram route (:func:`physgrad.half_inverse.half_inverse`)
holds all of ``J`` (m × P). Two routes avoid it:

* **Block Gram** (:func:`blockgram_half_inverse`, exact): the batch is cut into ``blocks``
  groups of samples; ``G[A, B] = J_A J_Bᵀ`` is formed pair by pair (upper triangle) from
  the groups' Jacobians (``vmap(jacrev)`` of the group, recomputed, never stored
  together), then ``eigh(G)`` once and ``Jᵀ w = Σ_A J_Aᵀ w_A`` in a second pass, all in
  float64 as the Gram route. Memory: two groups' rows × P plus m × m; compute ≈
  (blocks + 5)/2 times the Jacobian. Why sample groups and not parameter blocks: a
  parameter block ``J[:, B]`` costs |B| Jacobian–vector products of the whole batch
  (P in total, each a batch forward pass), whereas a sample group's rows cost one
  backward pass per row; with m ≪ P recomputing rows is far cheaper.
* **Lanczos** (:func:`lanczos_half_inverse`, approximate): k steps of Lanczos on ``G``
  with the matrix-free product ``G v = J (Jᵀ v)`` (one VJP and one JVP of the batch,
  ``jax.linearize``), started from ``g``, with full re-orthogonalisation in float64:
  ``G Q_k = Q_k T_k + β_k q_{k+1} e_kᵀ`` and

      f(G) g ≈ x_k = ‖g‖ Q_k f(T_k) e₁,     J^κ g ≈ Jᵀ x_k,

  with the truncation applied to the Ritz values (θ > τ² θ_max). Memory k × m + the
  network's activations; compute 2k batch passes.

  **Error bound** (exact arithmetic; Saad 1992, Lemma 3.1 with the polynomial exactness
  of Lanczos): ``‖f(G) g − x_k‖₂ ≤ 2 ‖g‖₂ · min_{deg p < k} max_{λ ∈ Λ(G)} |f(λ) − p(λ)|``.
  Hence x_k is exact once k reaches the number of distinct eigenvalues of G that g
  touches (k = m always suffices), and for f(λ) = λ^{−3/4} on a spectrum in [a, b] the
  error falls like ((√(b/a) − 1)/(√(b/a) + 1))^k: the route needs about
  √(λ_max/λ_min) · log(1/ε) steps, i.e. σ_max/σ_min·log(1/ε) — it wins only for
  well-conditioned or fast-decaying spectra, or where an approximate direction is
  enough. Each step reports ``‖x_k − x_{k−1}‖ / ‖x_k‖`` (a posteriori estimate of the
  remaining error). The products ``J v``, ``Jᵀ v`` run in the network's dtype, so
  eigenvalues below ~ε_float32·λ_max are not resolved in float32 networks.

Both routes scope their float64 (:func:`physgrad.precision.float64_scope`) and work with
``jax_enable_x64`` off; the network and simulator are traced outside the scope (in the
caller's configuration), only the Gram/Lanczos arithmetic is float64. As the Gram route,
they treat their inputs as constants for differentiation (``stop_gradient``).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, PyTree

from .half_inverse import Spectrum, cast_spectrum, gram_power_and_spectrum
from .jacobian import flat_output, stacked_jacobian
from .precision import float64_scope


def _groups(batch: PyTree, blocks: int) -> PyTree:
    """The batch reshaped to (blocks, samples per group, ...)."""
    n = jax.tree.leaves(batch)[0].shape[0]
    if n % blocks:
        raise ValueError(f"blocks={blocks} must divide the batch size {n}")
    return jax.tree.map(lambda a: a.reshape(blocks, n // blocks, *a.shape[1:]), batch)


def blockgram_half_inverse(
    predict: Callable[[PyTree, PyTree], Array],
    params: PyTree,
    batch: PyTree,
    grad: Float[Array, " m"],
    *,
    blocks: int,
    exponent: float = -0.5,
    truncation: float = 1e-6,
) -> Float[Array, " p"]:
    """``J^κ g`` by the Gram route with ``G`` assembled from sample groups (exact).

    Arguments:
        predict: one sample's output ``(params, sample) -> y``.
        params: the network parameters (a pytree; the result is raveled in
            ``ravel_pytree`` order, as :func:`physgrad.jacobian.stacked_jacobian`).
        batch: b samples (leading axis); ``blocks`` must divide b.
        grad: ``g``, (m,), sample-major as the stacked Jacobian's rows.
        blocks: number of sample groups; memory holds two groups' Jacobians.

    Returns:
        The direction (P,) in the parameters' dtype; equal to
        ``half_inverse(stacked_jacobian(...), g, route="gram")`` up to rounding.
    """
    return blockgram_half_inverse_and_spectrum(
        predict, params, batch, grad, blocks=blocks, exponent=exponent, truncation=truncation
    )[0]


def blockgram_half_inverse_and_spectrum(
    predict: Callable[[PyTree, PyTree], Array],
    params: PyTree,
    batch: PyTree,
    grad: Float[Array, " m"],
    *,
    blocks: int,
    exponent: float = -0.5,
    truncation: float = 1e-6,
) -> tuple[Float[Array, " p"], Spectrum]:
    """:func:`blockgram_half_inverse` and the
    :func:`~physgrad.half_inverse.spectrum_stats` of J (σ's in the parameters' dtype)."""
    # Constants for differentiation: the float64 scope below cannot be transposed outside it.
    params, batch, grad = jax.lax.stop_gradient((params, batch, grad))
    flat, _ = ravel_pytree(params)
    groups = _groups(batch, blocks)
    rows = grad.shape[0] // blocks

    def group_rows(index):  # one group's rows (rows, P) in the network's dtype
        group = jax.tree.map(lambda a: a[index], groups)
        return stacked_jacobian(predict, params, group)[0]

    # Traced now, in the caller's configuration, and only evaluated inside the scope: the
    # network and simulator never run under x64 (no float64 promotion of their constants).
    traced_rows, consts = jax.closure_convert(group_rows, jnp.int32(0))

    with float64_scope():

        def jac(index):  # one group's rows in float64, recomputed when needed
            return traced_rows(jnp.asarray(index, jnp.int32), *consts).astype(jnp.float64)

        def row_block(a, gram):
            j_a = jac(a)

            def pair(b, gram):  # G[A, B] and its mirror G[B, A] for B ≥ A
                block = j_a @ jac(b).T
                gram = jax.lax.dynamic_update_slice(gram, block, (a * rows, b * rows))
                return jax.lax.dynamic_update_slice(gram, block.T, (b * rows, a * rows))

            return jax.lax.fori_loop(a, blocks, pair, gram)

        m = rows * blocks
        gram = jax.lax.fori_loop(0, blocks, row_block, jnp.zeros((m, m), jnp.float64))
        w, spectrum = gram_power_and_spectrum(gram, grad.astype(jnp.float64), exponent, truncation)
        w = w.reshape(blocks, rows)

        def apply(a, direction):  # Jᵀ w = Σ_A J_Aᵀ w_A, in float64 as the Gram route
            return direction + jac(a).T @ w[a]

        direction = jax.lax.fori_loop(0, blocks, apply, jnp.zeros(flat.size, jnp.float64))
        return direction.astype(flat.dtype), cast_spectrum(spectrum, flat.dtype)


def batch_output_map(predict: Callable[[PyTree, PyTree], Array], params: PyTree, batch: PyTree):
    """``(F, θ)``: the raveled parameters and ``F(θ)`` = every sample's flat output,
    concatenated sample-major (the rows of the stacked Jacobian)."""
    flat, unravel = ravel_pytree(params)

    def outputs(theta):
        return jax.vmap(lambda s: flat_output(predict(unravel(theta), s)))(batch).ravel()

    return outputs, flat


def lanczos_half_inverse(
    predict: Callable[[PyTree, PyTree], Array],
    params: PyTree,
    batch: PyTree,
    grad: Float[Array, " m"],
    *,
    steps: int,
    exponent: float = -0.5,
    truncation: float = 1e-6,
) -> tuple[Float[Array, " p"], Float[Array, ""]]:
    """``J^κ g ≈ Jᵀ x_k`` with ``x_k`` from k Lanczos steps on ``G = J Jᵀ`` (matrix-free).

    Arguments as :func:`blockgram_half_inverse`; ``steps`` = k (capped at m, where the
    result is exact up to rounding).

    Returns:
        ``(direction, estimate)``: the direction (P,) and ``‖x_k − x_{k−1}‖ / ‖x_k‖``.
    """
    direction, estimate, _ = lanczos_half_inverse_and_spectrum(
        predict, params, batch, grad, steps=steps, exponent=exponent, truncation=truncation
    )
    return direction, estimate


def lanczos_half_inverse_and_spectrum(
    predict: Callable[[PyTree, PyTree], Array],
    params: PyTree,
    batch: PyTree,
    grad: Float[Array, " m"],
    *,
    steps: int,
    exponent: float = -0.5,
    truncation: float = 1e-6,
) -> tuple[Float[Array, " p"], Float[Array, ""], Spectrum]:
    """:func:`lanczos_half_inverse` and the :func:`~physgrad.half_inverse.spectrum_stats`
    of the Ritz values (√ of the eigenvalues of the k × k Lanczos matrix T_k: σ_max is
    approximated from below first, the kept count and σ_min_kept only as far as k steps
    resolve the spectrum); σ's in the caller's default float, as the estimate."""
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
        direction, estimate, spectrum = _lanczos(jvp, vjp, y.dtype, grad, steps, exponent, truncation)
        return direction.astype(flat.dtype), estimate.astype(outer_float), cast_spectrum(spectrum, outer_float)


def _lanczos(jvp, vjp, dtype, grad, steps, exponent, truncation):
    """:func:`lanczos_half_inverse`'s iteration, run inside its float64 scope; ``dtype`` is
    the outputs' (a simulator may compute in another dtype than the network's parameters:
    the cotangents of ``Jᵀ v`` take the outputs' dtype, ``J v`` the parameters')."""

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
        w, spectrum = gram_power_and_spectrum(t, e1, exponent, truncation)
        return jnp.zeros(k, jnp.float64).at[:n].set(norm_g * w), spectrum

    c, spectrum = coefficients(k)
    change = jnp.linalg.norm(c - coefficients(k - 1)[0]) if k > 1 else jnp.array(jnp.inf, jnp.float64)
    estimate = change / jnp.maximum(jnp.linalg.norm(c), 1e-300)
    (direction,) = vjp((basis.T @ c).astype(dtype))
    return direction, estimate, spectrum
