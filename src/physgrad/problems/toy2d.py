"""The PBDL book's 2D toy: y = (x₀, x₁²), L = |y|², started at x = (3, 3).

Source: PBDL book ``physgrad-comparison.ipynb``; SIP paper Fig. 1.

The problem optimises x itself (no network): the "network" is the free vector x, started
at (3, 3), and the single sample's target is y* = (0, 0). At the start y = (3, 9), L = 90,
∂L/∂y = (6, 18), ∂L/∂x = (6, 108): gradient descent is pulled along x₁. The book compares
10 iterations of

- gradient descent ``sgd`` (η 0.01):              x ← x − η ∂L/∂x
- Newton ``newton`` (η 1/3):                      x ← x − η H⁻¹ ∂L/∂x
- the inverse simulator ``sip`` (η 0.3):          x ← P⁻¹(y + η (y* − y); x), P⁻¹(y) = (y₀, ±√y₁)

(``sip`` with SGD at lr 1 on the proxy ½‖x − x̃‖² lands exactly on x̃.) Expected ordering
after 10 iterations: inverse simulator closest to the optimum, then Newton, then GD; the
inverse simulator's y trajectory is the straight diagonal to 0. Metrics log x and y
(``x0``, ``x1``, ``y0``, ``y1``) so trajectories can be drawn from ``metrics.csv``.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array

from ..precision import require_float64
from .base import AbstractProblem


class FreeVector(eqx.Module):
    """The optimised x itself; ignores its input."""

    x: Array


class Toy2d(AbstractProblem):
    """Minimise |y|² for y = (x₀, x₁²) from x = (3, 3), directly in x."""

    start: tuple[float, float] = eqx.field(static=True, default=(3.0, 3.0))

    name: ClassVar[str] = "toy2d"
    source: ClassVar[str] = "PBDL book physgrad-comparison.ipynb"
    default_batch_size: ClassVar[int] = 1

    needs_float64: ClassVar[bool] = True  # x and y are float64 (the book's NumPy toy): train under x64

    def make_data(self, key):
        require_float64(self.name)  # else JAX would silently make the float64 arrays float32
        split = {"y_target": jnp.zeros((1, 2), jnp.float64)}
        return {"train": split, "test": split}

    def make_network(self, key):
        require_float64(self.name)
        return FreeVector(jnp.asarray(self.start, jnp.float64))

    def initial_guess(self, sample):
        return jnp.asarray(self.start, jnp.float64)

    def network_output(self, network, sample):
        return network.x

    def simulate(self, x, sample):
        return jnp.stack([x[0], x[1] ** 2])

    def loss(self, y, sample):
        return jnp.sum((y - sample["y_target"]) ** 2)

    def target(self, sample):
        return sample["y_target"]

    def inverse(self, x, y, y_target, sample):
        """(y₀, ±√y₁) with the sign of the current x₁: the root closest to x."""
        root = jnp.sqrt(jnp.maximum(y_target[1], 0.0))
        return jnp.stack([y_target[0], jnp.where(x[1] < 0, -root, root)])

    def metrics(self, x, y, sample):
        return {"x0": x[0], "x1": x[1], "y0": y[0], "y1": y[1], "x_dist": jnp.linalg.norm(x)}
