"""The HIG paper's toy example: a two-output regression with one output scaled by λ.

Source: Schnell, Holl, Thuerey, ICLR 2022, toy example; PBDL book, "Half-inverse
gradients" (figures ``physgrad-hig-toy-example-{good,bad}``).

Network f: x ∈ [−1, 1] → (y₁, y₂), one hidden layer of 7 tanh units (glorot-uniform,
zero biases; 30 parameters). The "physics" scales the second output,
``P(y) = (y₁, λ y₂)``, and the target is ``ŷ(x) = (sin 6x, cos 9x)``:

    L = ½ (y₁ − ŷ₁)² + ½ (λ y₂ − ŷ₂)²

With λ = 0.01 the second output must grow 100×, which stalls Adam and GN (neurons
saturate) while HIG keeps progressing (book figure: ≈3e-3 vs ≈0.24 for Adam at 20 s).

The notes do not give the data size or the optimizers' settings for this figure; the
defaults below (1024 + 1024 points, batch 256, Adam lr 1e-3, GN/HIG η = 1, τ = 1e-6) are
physgrad's choice and are settings.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from ..precision import require_float64
from .base import AbstractProblem


class HigToy(AbstractProblem):
    """Fit (sin 6x, cos 9x) when the second output is scaled by λ."""

    lam: float = eqx.field(static=True, default=0.01)
    hidden: int = eqx.field(static=True, default=7)
    n_train: int = eqx.field(static=True, default=1024)
    n_test: int = eqx.field(static=True, default=1024)
    dtype: str = eqx.field(static=True, default="float32")

    name: ClassVar[str] = "hig_toy"
    source: ClassVar[str] = "Schnell, Holl, Thuerey, ICLR 2022, toy example"
    default_batch_size: ClassVar[int] = 256

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        """``dtype=float64`` runs the whole problem in double precision (engine scopes x64)."""
        return jnp.dtype(self.dtype) == jnp.float64

    def make_data(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        k_train, k_test = jax.random.split(key)
        draw = lambda k, n: {"x": jax.random.uniform(k, (n, 1), jnp.dtype(self.dtype), -1.0, 1.0)}  # noqa: E731
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        return MLP((1, self.hidden, 2), jax.nn.tanh, key=key, dtype=jnp.dtype(self.dtype))

    def network_output(self, network, sample):
        return network(sample["x"])

    def simulate(self, y, sample):
        return y * jnp.asarray([1.0, self.lam], y.dtype)

    def loss(self, y, sample):
        x = sample["x"][0]
        target = jnp.stack([jnp.sin(6.0 * x), jnp.cos(9.0 * x)])
        return 0.5 * jnp.sum((y - target) ** 2)
