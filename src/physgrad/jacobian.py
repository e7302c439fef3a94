"""Per-sample Jacobians of the simulator output, stacked sample-major."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, PyTree


def flat_output(y: Array) -> Array:
    """One sample's output as a real vector; complex values become (Re, Im) pairs."""
    if jnp.iscomplexobj(y):
        y = jnp.stack([y.real, y.imag], axis=-1)
    return jnp.ravel(y)


def stacked_jacobian(
    predict: Callable[[PyTree, PyTree], Array], params: PyTree, batch: PyTree
) -> tuple[Array, Array]:
    """The joint Jacobian ∂y/∂θ of all samples, rows sample-major, and the outputs.

    ``J[i·d + k, j] = ∂ y_i[k] / ∂ θ_j`` where ``d`` is the (flattened) output size, ``i``
    the sample and ``θ`` all parameters raveled in ``jax.flatten_util.ravel_pytree``
    order (one matrix over every layer: no per-layer treatment, as the paper).

    Computed by ``vmap(jacrev)`` over the batch: reverse mode because d < P, one
    forward pass per sample (the outputs come back as auxiliary data).

    Returns:
        ``(J, y)`` with ``J`` of shape (b·d, P) and ``y`` of shape (b, d).
    """
    flat, unravel = ravel_pytree(params)

    def per_sample(theta, sample):
        y = flat_output(predict(unravel(theta), sample))
        return y, y

    jac, y = jax.vmap(jax.jacrev(per_sample, has_aux=True), in_axes=(None, 0))(flat, batch)
    return jac.reshape(-1, flat.size), y
