"""The block-Gram route: the exact Gram matrix from sample groups, never holding J.

Source: the κ-power of :mod:`.spectrum` (Schnell et al., ICLR 2022). For the batch-output
map ``F: θ ↦ y`` (m = batch × output size rows, P parameters) with Jacobian ``J`` and Gram
matrix ``G = J Jᵀ = U Λ Uᵀ``,

    J^κ g = Jᵀ f(G) g,      f(λ) = λ^{(κ−1)/2} for λ > τ² λ_max, else 0,

(κ = −½: f(λ) = λ^{−3/4}). The batch is cut into ``blocks`` groups of samples;
``G[A, B] = J_A J_Bᵀ`` is formed pair by pair (upper triangle) from the groups' Jacobians
(``vmap(jacrev)`` of the group, recomputed, never stored together), then ``eigh(G)`` once
and ``Jᵀ w = Σ_A J_Aᵀ w_A`` in a second pass, all in float64 as the Gram route. Memory:
two groups' rows × P plus m × m; compute ≈ (blocks + 5)/2 times the Jacobian. Why sample
groups and not parameter blocks: a parameter block ``J[:, B]`` costs |B| Jacobian–vector
products of the whole batch (P in total, each a batch forward pass), whereas a sample
group's rows cost one backward pass per row; with m ≪ P recomputing rows is far cheaper.

The float64 is scoped (:func:`physgrad.precision.float64_scope`) and works with
``jax_enable_x64`` off; the network and simulator are traced outside the scope (in the
caller's configuration), only the Gram arithmetic is float64. As the Gram route, the inputs
are constants for differentiation (``stop_gradient``).

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Float, PyTree

from ..jacobian import stacked_jacobian
from ..precision import float64_scope
from .base import F64, AbstractMatrixFree
from .gram import gram_bytes
from .spectrum import Damped, cast_spectrum, gram_power


class BlockGram(AbstractMatrixFree):
    """Exact Gram matrix from ``blocks`` sample groups, two groups' Jacobians at a time.

    Never forms J: memory two groups' rows × P plus m². Under a mesh XLA partitions what
    it can; the groups are indexed dynamically, so it may repeat work on every device.
    ``blocks`` has no default: it trades memory for compute at a given batch size (the
    command line's default is 8)."""

    code = 3
    blocks: int = eqx.field(static=True)

    def __check_init__(self):
        if self.blocks < 1:
            raise ValueError(f"blocks must be >= 1, got {self.blocks}")

    def check_batch_size(self, batch_size):
        if batch_size % self.blocks:
            raise ValueError(f"route blockgram needs blocks ({self.blocks}) to divide the batch size {batch_size}")

    def power(self, predict, params, batch, grad, exponent, truncation):
        """``J^κ g`` with ``G`` assembled from sample groups (exact; ``blocks`` must divide
        the batch size), and the :func:`~.spectrum.spectrum_stats` of J (σ's in the
        parameters' dtype)."""
        # Constants for differentiation: the float64 scope below cannot be transposed outside it.
        params, batch, grad = jax.lax.stop_gradient((params, batch, grad))
        flat, _ = ravel_pytree(params)
        blocks = self.blocks
        n = jax.tree.leaves(batch)[0].shape[0]
        if n % blocks:
            raise ValueError(f"blocks={blocks} must divide the batch size {n}")
        groups = jax.tree.map(lambda a: a.reshape(blocks, n // blocks, *a.shape[1:]), batch)
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
            w, spectrum = gram_power(gram, grad.astype(jnp.float64), exponent, truncation)
            w = w.reshape(blocks, rows)

            def apply(a, direction):  # Jᵀ w = Σ_A J_Aᵀ w_A, in float64 as the Gram route
                return direction + jac(a).T @ w[a]

            direction = jax.lax.fori_loop(0, blocks, apply, jnp.zeros(flat.size, jnp.float64))
            return direction.astype(flat.dtype), cast_spectrum(spectrum, flat.dtype)

    def compute(self, jacobian, exponent, truncation):
        self.check_batch_size(jacobian.batch_size)
        return super().compute(jacobian, exponent, truncation)

    def footprint_of(self, jacobian, devices=1):
        two_groups = 2 * -(-jacobian.rows // self.blocks) * jacobian.size * (jacobian.itemsize + F64)
        return two_groups + gram_bytes(jacobian.shape)


def blockgram_half_inverse(
    predict: Callable[[PyTree, PyTree], Array],
    params: PyTree,
    batch: PyTree,
    grad: Float[Array, " m"],
    *,
    blocks: int,
    exponent: float | Damped = -0.5,
    truncation: float = 1e-6,
) -> Float[Array, " p"]:
    """``J^κ g`` by the Gram route with ``G`` assembled from ``blocks`` sample groups
    (:meth:`BlockGram.power`, the direction alone): equal to :func:`~.auto.half_inverse`
    of the stacked Jacobian by the :class:`~.gram.Gram` route up to rounding; memory two
    groups' Jacobians."""
    return BlockGram(blocks).power(predict, params, batch, grad, exponent, truncation)[0]
