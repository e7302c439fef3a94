"""The SIP paper's characterisation problem: a rotated, ill-conditioned sine.

Source: Holl, Koltun, Thuerey, NeurIPS 2022, Fig. 5; ``sin_characterization/train_sin.py``; the code's definition, which differs slightly from the book's formula.

    x̂ = (γ/ξ, γ ξ) ⊙ R_φ x,     P(x) = (sin x̂₁, x̂₂),     L = ½ ‖P(x) − y*‖²,

with γ = 10 ("best value for Adam"), ξ the ill-conditioning and φ the rotation (degrees,
counter-clockwise) coupling the two components; y* ~ U[−1, 1]². The network f(y*; θ) → x is
dense 2-32-64-32-2 with ReLU (4,386 parameters). The authors' defaults are ξ = 10,
φ = 45°; the figures sweep ξ ∈ [1, 64] at φ = 0 and φ ∈ [0°, 45°] at ξ = 32.

SIP uses the per-sample saddle-free Newton step with ``max_loss_change = 0.2`` and an L1
proxy (the code's choice), in float64 (2×2 per sample; at ξ = 32 float32 steps differ by up
to 4 %); Adam lr 1e-3, batch 100 (the code averages over the batch, as physgrad); the other optimizers' learning rates
are the code's (SGD 1e-2/ξ², here for ξ = 10: set ``sgd.lr`` when changing ξ). Metric:
``x_dist``, the distance to the *closest* exact solution (the arcsin branches
x̂₁ ∈ {asin y*₁, π − asin y*₁} + 2πn, x̂₂ = y*₂), and ``x_dist_rel`` = x_dist / ξ, the
quantity of the paper's ξ sweep. Data: the authors stream fresh batches; physgrad
pre-generates ``n_train`` samples.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from .base import AbstractProblem


class Sine(AbstractProblem):
    """Invert (sin x̂₁, x̂₂) with x̂ = (γ/ξ, γξ) ⊙ R_φ x; ill-conditioned for ξ ≫ 1."""

    xi: float = eqx.field(static=True, default=10.0)
    phi: float = eqx.field(static=True, default=45.0)
    gamma: float = eqx.field(static=True, default=10.0)
    n_train: int = eqx.field(static=True, default=65536)
    n_test: int = eqx.field(static=True, default=1024)

    name: ClassVar[str] = "sine"
    # the authors generate every batch on the fly: every epoch a new training set
    default_fresh_samples: ClassVar[bool] = True
    source: ClassVar[str] = "Holl et al., NeurIPS 2022, Fig. 5"
    default_batch_size: ClassVar[int] = 100

    def _scale(self):
        return jnp.array([self.gamma / self.xi, self.gamma * self.xi])

    def _rotation(self):
        a = jnp.deg2rad(self.phi)
        return jnp.array([[jnp.cos(a), -jnp.sin(a)], [jnp.sin(a), jnp.cos(a)]])

    def make_data(self, key):
        k_train, k_test = jax.random.split(key)
        draw = lambda k, n: {"y": jax.random.uniform(k, (n, 2), jnp.float32, -1.0, 1.0)}  # noqa: E731
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        return MLP((2, 32, 64, 32, 2), jax.nn.relu, key=key)

    def network_output(self, network, sample):
        return network(sample["y"])

    def simulate(self, x, sample):
        x_hat = self._scale().astype(x.dtype) * (self._rotation().astype(x.dtype) @ x)
        return jnp.stack([jnp.sin(x_hat[0]), x_hat[1]])

    def loss(self, y, sample):
        return 0.5 * jnp.sum((y - sample["y"]) ** 2)

    def target(self, sample):
        return sample["y"]

    def closest_solution(self, x, sample):
        """The exact solution of P(x) = y* nearest to x (nearest arcsin branch in x̂₁)."""
        scale, rot = self._scale().astype(x.dtype), self._rotation().astype(x.dtype)
        x_hat = scale * (rot @ x)
        y1, y2 = sample["y"][0].astype(x.dtype), sample["y"][1].astype(x.dtype)
        branches = jnp.stack([jnp.arcsin(y1), jnp.pi - jnp.arcsin(y1)])
        turns = jnp.round((x_hat[0] - branches) / (2 * jnp.pi))
        candidates = branches + 2 * jnp.pi * turns
        best = candidates[jnp.argmin(jnp.abs(x_hat[0] - candidates))]
        return rot.T @ (jnp.stack([best, y2]) / scale)

    def metrics(self, x, y, sample):
        dist = jnp.linalg.norm(x - self.closest_solution(x, sample))
        return {"x_dist": dist, "x_dist_rel": dist / self.xi}
