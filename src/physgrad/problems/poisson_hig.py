"""The HIG paper's inverse Poisson problem on an 8×8 grid.

Source: Schnell, Holl, Thuerey, ICLR 2022, Poisson problem; the authors'
``Poisson_problem/submit_Poisson.py`` (PhiFlow 2.1 + TensorFlow).

Given a right-hand side y* (8×8), find x with ∇²x = y*. The forward operator is PhiFlow's
``field.laplace`` on a cell-centred 8×8 grid with cell size 1 and zero extrapolation:

    (∇²x)_{ij} = x_{i−1,j} + x_{i+1,j} + x_{i,j−1} + x_{i,j+1} − 4 x_{ij},   x = 0 outside.

Data: x_gt is PhiFlow ``Noise`` (scale 10, smoothness 1): complex Gaussian Fourier
coefficients weighted by 1/|k|² with k = 10 · fftfreq(8) per axis (the zero mode removed),
the real part of the inverse FFT, normalised per sample to unit std and then zero mean;
y* = ∇²x_gt. The network maps y* (64) to x (64) through tanh 64-128-64 (24,896
parameters). Loss per sample ``L = ½ ‖∇²x − y*‖²`` (PhiFlow ``l2_loss``); the ground-truth
error ``x_l1 = mean |x − x_gt|`` is logged as an extra metric, as the authors did.

Deviations, documented: the authors draw a fresh batch every iteration (an infinite stream);
physgrad pre-generates ``n_train`` = 65,536 samples (1,024 batches of 64 before one repeats)
and a fixed test set, so runs are reproducible and evaluated on held-out data. The authors'
HIG step uses the *summed* loss (g = y − y*) with η = 0.01; physgrad's methods use the
batch-mean loss (g = (y − y*)/b), and the HIG step is homogeneous of degree 1 in g, so the
paper's step is η = 0.01 · 64 = 0.64 here (the default). Adam is scale-invariant: lr 3e-4.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from ..precision import float64_scope, require_float64
from .base import AbstractProblem


def laplace_zero_boundary(x: jax.Array) -> jax.Array:
    """5-point Laplacian of a 2-D field (cell size 1) with zero values outside the grid."""
    padded = jnp.pad(x, 1)
    return padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:] - 4.0 * x


def phiflow_noise(key, shape: tuple[int, int, int], *, scale: float = 10.0, smoothness: float = 1.0, dtype=jnp.float32):
    """Smooth random fields as PhiFlow's ``Noise`` on a grid with cell size 1, shape (b, nx, ny).

    Fourier coefficients ``(a + i b) · |k|^(−2·smoothness)`` with ``a, b ~ N(0, 1)`` and
    ``k = scale · fftfreq(n)`` per axis (only |k|² > 0.1 kept: the mean mode is removed);
    real part of the inverse FFT, divided by its std, then made zero-mean, per sample.
    Drawn and transformed in float64, scoped, then cast to ``dtype``: the fields do not
    depend on the caller's x64 setting.
    """
    with float64_scope():
        b, nx, ny = shape
        k_re, k_im = jax.random.split(key)
        coeffs = jax.random.normal(k_re, shape, jnp.float64) + 1j * jax.random.normal(k_im, shape, jnp.float64)
        kx = scale * jnp.fft.fftfreq(nx)[:, None]
        ky = scale * jnp.fft.fftfreq(ny)[None, :]
        k2 = kx**2 + ky**2
        weight = jnp.where(k2 > 0.1, 1.0 / jnp.where(k2 > 0.1, k2, 1.0), 0.0) ** smoothness
        field = jnp.real(jnp.fft.ifft2(coeffs * weight))
        field = field / jnp.std(field, axis=(1, 2), keepdims=True)
        field = field - jnp.mean(field, axis=(1, 2), keepdims=True)
        return field.astype(dtype)


class PoissonHig(AbstractProblem):
    """Learn to invert the 8×8 zero-boundary Laplacian from its right-hand side."""

    resolution: int = eqx.field(static=True, default=8)
    noise_scale: float = eqx.field(static=True, default=10.0)
    noise_smoothness: float = eqx.field(static=True, default=1.0)
    n_train: int = eqx.field(static=True, default=65536)
    n_test: int = eqx.field(static=True, default=1024)
    dtype: str = eqx.field(static=True, default="float32")

    name: ClassVar[str] = "poisson_hig"
    # the authors draw a fresh Noise batch every iteration: every epoch a new training set
    default_fresh_samples: ClassVar[bool] = True
    source: ClassVar[str] = "Schnell, Holl, Thuerey, ICLR 2022, Poisson problem"
    default_batch_size: ClassVar[int] = 64

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        """``dtype=float64`` runs the whole problem in double precision (engine scopes x64)."""
        return jnp.dtype(self.dtype) == jnp.float64

    @property
    def size(self) -> int:
        return self.resolution**2

    def make_data(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")

        def draw(k, n):
            x_gt = phiflow_noise(
                k, (n, self.resolution, self.resolution), scale=self.noise_scale,
                smoothness=self.noise_smoothness, dtype=jnp.dtype(self.dtype),
            )  # fmt: skip
            return {"x_gt": x_gt, "rhs": jax.vmap(laplace_zero_boundary)(x_gt)}

        k_train, k_test = jax.random.split(key)
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        return MLP((self.size, 64, 128, 64, self.size), jax.nn.tanh, key=key, dtype=jnp.dtype(self.dtype))

    def network_output(self, network, sample):
        return network(sample["rhs"].ravel()).reshape(self.resolution, self.resolution)

    def simulate(self, x, sample):
        return laplace_zero_boundary(x)

    def loss(self, y, sample):
        return 0.5 * jnp.sum((y - sample["rhs"]) ** 2)

    def metrics(self, x, y, sample):
        return {"x_l1": jnp.mean(jnp.abs(x - sample["x_gt"]))}
