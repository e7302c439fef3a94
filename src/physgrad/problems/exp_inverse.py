"""Learn to invert the exponential: the SIP paper's Fig. 2.

Source: Holl, Koltun, Thuerey, NeurIPS 2022, Fig. 2; ``exp/train_exp.py``.

x* ~ U[−12, 0], y* = e^{x*}; the network f(y*; θ) → x (dense 1-16-64-16-1, sigmoid,
2,209 parameters) is trained through P(x) = e^x with L = ½ (e^x − y*)². Back-propagated
gradients carry the factor e^x, which vanishes for small y*, so GD/Adam learn only the
upper end of the range; the analytic local inverse x̃ = log((1 − η) y + η y*) rescales the
update to be uniform in x (computed in float64: y* reaches e⁻¹²). The metric ``x_l1`` =
|x − x*| measures that, split into ``x_l1_low`` and ``x_l1_high`` by the half of the range. Authors: SGD lr 1e-2 on the batch-*summed* loss (= lr 1.0 on
physgrad's batch mean; Adam lr 1e-3 as an option), batch 100, fresh data every step,
10,000 steps; physgrad pre-generates ``n_train`` samples (655 batches of 100 before one
repeats). SIP with the exact inverse and SGD at lr 1.0 overshoots (e^x overflows at step 2
from physgrad's glorot initialisation); its default is lr 0.1 (of 1.0, 0.3, 0.1 over 3,000
steps, 0.1 gave the lowest x error), while DP-SGD keeps the converted 1.0 (0.1 learns no
better: its gradient vanishes with e^x either way).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from .base import AbstractProblem


class ExpInverse(AbstractProblem):
    """Learn x = log y through the exponential; x* ~ U[−12, 0]."""

    low: float = eqx.field(static=True, default=-12.0)
    high: float = eqx.field(static=True, default=0.0)
    n_train: int = eqx.field(static=True, default=65536)
    n_test: int = eqx.field(static=True, default=1024)

    name: ClassVar[str] = "exp_inverse"
    # the authors generate every batch on the fly: every epoch a new training set
    default_fresh_samples: ClassVar[bool] = True
    source: ClassVar[str] = "Holl et al., NeurIPS 2022, Fig. 2"
    default_batch_size: ClassVar[int] = 100

    def make_data(self, key):
        def draw(k, n):
            x_gt = jax.random.uniform(k, (n, 1), jnp.float32, self.low, self.high)
            return {"x_gt": x_gt, "y": jnp.exp(x_gt)}

        k_train, k_test = jax.random.split(key)
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        return MLP((1, 16, 64, 16, 1), jax.nn.sigmoid, key=key)

    def network_output(self, network, sample):
        return network(sample["y"])

    def simulate(self, x, sample):
        return jnp.exp(x)

    def loss(self, y, sample):
        return 0.5 * jnp.sum((y - sample["y"]) ** 2)

    def target(self, sample):
        return sample["y"]

    def inverse(self, x, y, y_target, sample):
        return jnp.log(y_target)

    def metrics(self, x, y, sample):
        """|x − x*|, and its parts from the lower (x* < −6, y* < 2.5e-3) and upper halves of
        the range (their split means add up to ``x_l1``): where DP's gradient e^x vanishes."""
        err = jnp.sum(jnp.abs(x - sample["x_gt"]))
        low = jnp.sum(sample["x_gt"]) < 0.5 * (self.low + self.high)
        return {"x_l1": err, "x_l1_low": jnp.where(low, err, 0.0), "x_l1_high": jnp.where(low, 0.0, err)}
