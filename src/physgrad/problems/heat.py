"""The SIP paper's heat equation: recover sharp initial heat from its diffused state.

Source: Holl, Koltun, Thuerey, NeurIPS 2022, Fig. 6c,d; ``heat/train_heat.py`` and
``heat/inv_diffuse.py``; PBDL book ``physgrad-code.ipynb``.

Forward physics (float64, as the authors' ``set_global_precision(64)``; the problem declares
``needs_float64``, so the engine trains it under ``jax.enable_x64(True)``): exact periodic
diffusion on a 64×64 grid with unit cells,

    ŷ_k = x̂_k · exp(−(2π)² |k|² · ν t),   k = fftfreq(64) per axis,  ν t = 8.

Data: x* = a sum of 4–10 boxes (count ⌊4 + 7u⌋), centres uniform over the central 80 %,
half-sizes U[0, 10) cells per axis (centre clipped so the box stays inside), strengths
U[0, 1); each box is sampled soft-edged as the fraction of each cell it covers. y* = P(x*).
Network: the U-Net, input y*, output x, followed by the authors' mean correction
x ← x + mean(x*) − mean(x); diffusion conserves the mean, so physgrad uses mean(y*), which
is the same number without reading the ground truth.

SIP's local inverse (``inverse``) is the authors' Bayesian-damped deconvolution of the
residual r = y_t − y: with the unnormalised FFT amplitudes a_k of r, the noise level
σ_n = 10⁻⁶ ‖r‖₂ and the expected signal amplitude e_k = 64 · exp(−κ_k), κ_k = (2π)²|k|²·8,

    p_k = N(a_k; e_k) / (N(a_k; e_k) + N(a_k; σ_n)),   N(a; s) = exp(−½ (|a|/s)²)  (NaN → 0),
    α_k = 2 (p_k − ½) if p_k ≤ ½ or p_k ≥ 0.68, else 0,
    x̃ = x + Re iFFT(a_k · exp(κ_k α_k)),

i.e. full inversion where the residual is signal (p = 1), damping (further diffusion)
where it is noise (p < ½), nothing in between. Metrics: ``x_l1`` = Σ|x − x*| per sample
(training logs); ``x_l1_clamped`` with the prediction clamped at ≥ 0, as the authors'
final numbers (SIP 50.4, Adam 125.0, SGD 118.9). Adam lr 1e-3, batch 128; SGD lr 2e-6 on
the batch-*summed* loss = 2.56e-4 on physgrad's batch mean.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import UNet
from ..precision import require_float64
from .base import AbstractProblem


def diffusion_exponent(n: int, amount: float) -> jax.Array:
    """κ_k = (2π)² |k|² · amount on an n×n periodic grid with unit cells (float64)."""
    k = jnp.fft.fftfreq(n).astype(jnp.float64)
    return (2 * jnp.pi) ** 2 * (k[:, None] ** 2 + k[None, :] ** 2) * amount


def diffuse(x: jax.Array, amount: float) -> jax.Array:
    """Exact periodic heat diffusion by Fourier multiplication, in float64."""
    x = x.astype(jnp.float64)
    return jnp.real(jnp.fft.ifft2(jnp.fft.fft2(x) * jnp.exp(-diffusion_exponent(x.shape[0], amount))))


def damped_deconvolution(residual: jax.Array, amount: float, uncertainty: float = 1e-6) -> jax.Array:
    """The SIP authors' Bayesian signal/noise damped inverse diffusion of a residual (float64)."""
    r = residual.astype(jnp.float64)
    n = r.shape[0]
    log_kernel = diffusion_exponent(n, amount)
    sigma_noise = uncertainty * jnp.sqrt(jnp.sum(r**2))
    amp = jnp.fft.fft2(r)
    expected = n * jnp.exp(-log_kernel)
    signal = 0.5 * jnp.exp(-0.5 * (jnp.abs(amp) / expected) ** 2)
    signal = jnp.where(jnp.isfinite(signal), signal, 0.0)
    noise = 0.5 * jnp.exp(-0.5 * (jnp.abs(amp) / sigma_noise) ** 2)
    total = signal + noise
    p = jnp.where(total > 0, signal / jnp.where(total > 0, total, 1.0), 0.0)
    action = jnp.where((p <= 0.5) | (p >= 0.68), 2.0 * (p - 0.5), 0.0)
    return jnp.real(jnp.fft.ifft2(amp * jnp.exp(log_kernel * action)))


def soft_box(n: int, centre: jax.Array, half_size: jax.Array) -> jax.Array:
    """Fraction of each unit cell [i, i+1]×[j, j+1] covered by the box centre ± half_size."""
    edges = jnp.arange(n, dtype=centre.dtype)

    def overlap(c, h):
        return jnp.clip(jnp.minimum(edges + 1, c + h) - jnp.maximum(edges, c - h), 0.0, 1.0)

    return overlap(centre[0], half_size[0])[:, None] * overlap(centre[1], half_size[1])[None, :]


def box_parameters(key, n: int, max_boxes: int = 10):
    """(centres (10, 2), half-sizes (10, 2), strengths (10,)) of one sample's boxes: ⌊4 + 7u⌋
    of them have a strength U[0, 1), the rest 0 (the authors' ``generate_heat_example``)."""
    k_count, k_pos, k_size, k_strength = jax.random.split(key, 4)
    count = jnp.floor(4 + 7 * jax.random.uniform(k_count, dtype=jnp.float64))
    size = jnp.float64(n)
    centres = (jax.random.uniform(k_pos, (max_boxes, 2), jnp.float64) - 0.5) * size * 0.8 + size * 0.5
    halves = jax.random.uniform(k_size, (max_boxes, 2), jnp.float64) * 10
    centres = jnp.clip(centres, halves, size - halves)  # the box stays inside the domain
    strengths = jax.random.uniform(k_strength, (max_boxes,), jnp.float64) * (jnp.arange(max_boxes) < count)
    return centres, halves, strengths


def random_boxes(key, n: int, max_boxes: int = 10) -> jax.Array:
    """One initial heat field (n, n): the sum of its soft boxes times their strengths."""
    centres, halves, strengths = box_parameters(key, n, max_boxes)
    boxes = jax.vmap(lambda c, h: soft_box(n, c, h))(centres, halves)
    return jnp.einsum("b,bij->ij", strengths, boxes)


class Heat(AbstractProblem):
    """Recover a box-shaped initial temperature from its state after periodic diffusion."""

    resolution: int = eqx.field(static=True, default=64)
    amount: float = eqx.field(static=True, default=8.0)
    uncertainty: float = eqx.field(static=True, default=1e-6)
    levels: int = eqx.field(static=True, default=4)
    filters: int = eqx.field(static=True, default=16)
    n_train: int = eqx.field(static=True, default=8192)
    n_test: int = eqx.field(static=True, default=128)

    name: ClassVar[str] = "heat"
    # the authors draw a fresh batch of boxes every step: every epoch a new training set
    default_fresh_samples: ClassVar[bool] = True
    source: ClassVar[str] = "Holl et al., NeurIPS 2022, Fig. 6c,d"
    default_batch_size: ClassVar[int] = 128

    needs_float64: ClassVar[bool] = True  # the physics and the data's y are float64, as the authors'

    def make_data(self, key):
        require_float64(self.name)  # else JAX would silently build float32 "float64" physics

        def draw(k, n):
            x_gt = jax.vmap(lambda kk: random_boxes(kk, self.resolution))(jax.random.split(k, n))
            y = jax.vmap(lambda x: diffuse(x, self.amount))(x_gt)
            return {"x_gt": x_gt.astype(jnp.float32), "y": y}

        k_train, k_test = jax.random.split(key)
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        return UNet(1, 1, levels=self.levels, filters=self.filters, key=key)

    def network_output(self, network, sample):
        x = network(sample["y"][None])[0]
        return x + (jnp.mean(sample["y"]) - jnp.mean(x)).astype(x.dtype)

    def simulate(self, x, sample):
        return diffuse(x, self.amount)

    def loss(self, y, sample):
        return 0.5 * jnp.sum((y - sample["y"]) ** 2)

    def target(self, sample):
        return sample["y"]

    def inverse(self, x, y, y_target, sample):
        return x + damped_deconvolution(y_target - y, self.amount, self.uncertainty).astype(x.dtype)

    def metrics(self, x, y, sample):
        return {
            "x_l1": jnp.sum(jnp.abs(x - sample["x_gt"])),
            "x_l1_clamped": jnp.sum(jnp.abs(jnp.maximum(x, 0.0) - sample["x_gt"])),
        }
