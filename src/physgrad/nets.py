"""Networks in Equinox with the papers' (Keras) initialisation.

The HIG paper's networks are Keras ``Dense`` stacks: glorot-uniform kernels,
``U(−a, a)`` with ``a = sqrt(6 / (fan_in + fan_out))``, and zero biases. Equinox's own
``Linear`` initialises differently, so the weights are re-drawn here.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

ACTIVATIONS = {
    "relu": jax.nn.relu,
    "tanh": jnp.tanh,
    "sigmoid": jax.nn.sigmoid,
    "gelu": jax.nn.gelu,
    "identity": lambda x: x,
}


def glorot_uniform(key: PRNGKeyArray, fan_out: int, fan_in: int, dtype) -> Array:
    """Glorot/Xavier uniform kernel of shape (fan_out, fan_in) (Glorot & Bengio 2010)."""
    limit = (6.0 / (fan_in + fan_out)) ** 0.5
    return jax.random.uniform(key, (fan_out, fan_in), dtype, -limit, limit)


class Dense(eqx.Module):
    """Affine layer ``y = W x + b`` with a glorot-uniform ``W`` (out, in) and zero ``b``."""

    weight: Float[Array, "out in"]
    bias: Float[Array, " out"]

    def __init__(self, in_size: int, out_size: int, *, key: PRNGKeyArray, dtype=jnp.float32):
        self.weight = glorot_uniform(key, out_size, in_size, dtype)
        self.bias = jnp.zeros((out_size,), dtype)

    def __call__(self, x: Float[Array, " in"]) -> Float[Array, " out"]:
        return self.weight @ x + self.bias


class MLP(eqx.Module):
    """Fully connected network ``sizes[0] → … → sizes[-1]``, activation on hidden layers only.

    Example: ``MLP((4, 20, 20, 20, 96), "relu", key=k)`` is the HIG oscillator network
    (2,956 parameters). Input and output are unbatched vectors; vmap over samples.
    """

    layers: tuple[Dense, ...]
    activation: str = eqx.field(static=True)

    def __init__(self, sizes: Sequence[int], activation: str, *, key: PRNGKeyArray, dtype=jnp.float32):
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; valid choices: {', '.join(ACTIVATIONS)}")
        keys = jax.random.split(key, len(sizes) - 1)
        self.layers = tuple(
            Dense(n_in, n_out, key=k, dtype=dtype) for n_in, n_out, k in zip(sizes[:-1], sizes[1:], keys)
        )
        self.activation = activation

    def __call__(self, x: Float[Array, " in"]) -> Float[Array, " out"]:
        act = ACTIVATIONS[self.activation]
        for layer in self.layers[:-1]:
            x = act(layer(x))
        return self.layers[-1](x)


def parameter_count(module) -> int:
    """Number of scalar parameters (inexact array leaves) in an Equinox module."""
    return sum(leaf.size for leaf in jax.tree.leaves(eqx.filter(module, eqx.is_inexact_array)))
