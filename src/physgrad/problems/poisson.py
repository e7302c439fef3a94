"""The SIP paper's Poisson problem: recover x from the solution y of ∇²y = x on 64×64.

Source: Holl, Koltun, Thuerey, NeurIPS 2022, Fig. 6a,b; ``poisson/train_poisson.py``.

Forward physics: y = P(x) solves ∇²y = x with PhiFlow's cell-centred 5-point Laplacian
(cell size 1, zero values outside the grid). physgrad solves it *exactly* in the sine
basis that diagonalises this Laplacian,

    ∇² = S Λ S (per axis),  S_ij = √(2/(n+1)) sin(π i j/(n+1)),
    λ_j = −4 sin²(π j / (2(n+1))),   y = S [(S x S) ⊘ (λ_i + λ_j)] S,

instead of the authors' CG (rel. tol. 1e-5): the same operator to float precision, and
its adjoint (what DP baselines back-propagate) is the same solve. Data: x* = PhiFlow
``Noise`` (scale 10, smoothness 1), y* = P(x*). Network: the U-Net (4 levels × 16
filters), input y*, output x. Loss ½‖P(x) − y*‖².

SIP's local inverse is exact (``inverse``): x̃ = x + ∇²(y_t − y) — with η = 1 this is x*,
so SIP is supervised training with labels made by the inverse. Through the
solve, DP's gradient P^T(Px − y*) damps an error mode by λ⁻², the "square of the scaling".
Metrics: ``x_l1`` = Σ|x − x*| per sample (the paper's "MAE"), ``x_mae`` its per-cell mean.

Hyperparameters (code): Adam lr 1e-3, batch 128 for Adam and SIP; SGD lr 3e-12 with
momentum 0.9 on the batch-*summed* loss, i.e. 3e-12 × 128 = 3.84e-10 on physgrad's batch
mean. The authors stream fresh noise every step; physgrad pre-generates ``n_train``
samples (64 batches of 128 per epoch).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..nets import UNet
from ..precision import require_float64
from .base import AbstractProblem
from .poisson_hig import laplace_zero_boundary, phiflow_noise


def sine_basis(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, λ): the orthonormal DST-I matrix and the eigenvalues of the 1-D zero-padded
    3-point Laplacian, so that ``tridiag(1, −2, 1) = S diag(λ) S`` (float64 NumPy)."""
    j = np.arange(1, n + 1)
    s = np.sqrt(2.0 / (n + 1)) * np.sin(np.pi * np.outer(j, j) / (n + 1))
    lam = -4.0 * np.sin(np.pi * j / (2 * (n + 1))) ** 2
    return s, lam


def solve_poisson(x: jax.Array) -> jax.Array:
    """y with ∇²y = x (5-point Laplacian, zero outside), by the sine transform; (n, n)."""
    n = x.shape[0]
    s, lam = sine_basis(n)
    s = jnp.asarray(s, x.dtype)
    eig = jnp.asarray(lam[:, None] + lam[None, :], x.dtype)
    # HIGHEST: on GPUs XLA's default float32 matmul is TF32, whose 1e-3 error the SIP
    # target x + ∇²(y_t − y) would amplify.
    mm = lambda a, b: jnp.matmul(a, b, precision=jax.lax.Precision.HIGHEST)  # noqa: E731
    return mm(mm(s, mm(mm(s, x), s) / eig), s)


class Poisson(AbstractProblem):
    """Learn the source x of a 64×64 zero-boundary Poisson problem from its solution y."""

    resolution: int = eqx.field(static=True, default=64)
    noise_scale: float = eqx.field(static=True, default=10.0)
    noise_smoothness: float = eqx.field(static=True, default=1.0)
    levels: int = eqx.field(static=True, default=4)
    filters: int = eqx.field(static=True, default=16)
    n_train: int = eqx.field(static=True, default=8192)
    n_test: int = eqx.field(static=True, default=128)
    dtype: str = eqx.field(static=True, default="float32")

    name: ClassVar[str] = "poisson"
    # the authors draw fresh noise every step: every epoch a new training set
    default_fresh_samples: ClassVar[bool] = True
    source: ClassVar[str] = "Holl et al., NeurIPS 2022, Fig. 6a,b"
    default_batch_size: ClassVar[int] = 128

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        """``dtype=float64`` runs the whole problem in double precision (engine scopes x64)."""
        return jnp.dtype(self.dtype) == jnp.float64

    def make_data(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")

        def draw(k, n):
            x_gt = phiflow_noise(k, (n, self.resolution, self.resolution), scale=self.noise_scale,
                                 smoothness=self.noise_smoothness, dtype=jnp.dtype(self.dtype))  # fmt: skip
            return {"x_gt": x_gt, "y": jax.vmap(solve_poisson)(x_gt)}

        k_train, k_test = jax.random.split(key)
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        return UNet(1, 1, levels=self.levels, filters=self.filters, key=key, dtype=jnp.dtype(self.dtype))

    def network_output(self, network, sample):
        return network(sample["y"][None])[0]

    def simulate(self, x, sample):
        return solve_poisson(x)

    def loss(self, y, sample):
        return 0.5 * jnp.sum((y - sample["y"]) ** 2)

    def target(self, sample):
        return sample["y"]

    def inverse(self, x, y, y_target, sample):
        """Exact: x̃ = x + ∇²(y_t − y) (robust to solver error in y, as the authors' form)."""
        return x + laplace_zero_boundary(y_target - y)

    def metrics(self, x, y, sample):
        err = jnp.abs(x - sample["x_gt"])
        return {"x_l1": jnp.sum(err), "x_mae": jnp.mean(err)}
