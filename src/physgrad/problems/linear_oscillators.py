"""The PBDL book's linear oscillator chain: the HIG chapter's worked example.

Source: Thuerey et al., *Physics-based Deep Learning*, "Coupled Oscillators with
Half-Inverse Gradients" (``physgrad-hig-code.ipynb``).

The same controlled chain as :mod:`physgrad.problems.oscillators`, but linear:

    dq_i/dt = p_i
    dp_i/dt = −q_i + β (q_{i+1} − q_i) + β (q_{i−1} − q_i) + c · u(t) · δ_{i,n}

with spring coupling β = 0.2 (the book's free-end Laplacian), no cubic term, control gain
c = 1 on the last of n = 2 oscillators. RK4, dt = 0.5, 24 steps (T = 12). Return-to-start
task on x₀ ~ U[0,1)⁴; network 4 → 20 → 20 → 20 → 24 with tanh (1,444 parameters); loss
Σ‖y − y*‖² per sample. The book trains on 4,096 samples only; physgrad adds a 4,096-sample
test set drawn the same way. Book settings: Adam lr 1e-3 batch 256; HIG η 1, batch 32,
truncation 1e-10; SIP: Adam lr 1e-3 batch 256 on the Gauss–Newton local inverse
``pinv(J, rcond=1e-5)``; budget 100 s. The book's SIP takes the y-step from its
summed-over-batch loss (η ≈ 2/B); physgrad uses the paper's η = 1 (Adam normalises the
global scale away).

Because the dynamics are linear, y = e^{AT} x₀ + Σ_k B_k u_k exactly for RK4 too (RK4 of a
linear system is the degree-4 Taylor polynomial of e^{A dt} per step); the tests check the
solver against the matrix exponential.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax

from .oscillators import AbstractOscillators


class LinearOscillators(AbstractOscillators):
    """Return-to-start control of two linearly coupled oscillators (PBDL book).

    A final class beside :class:`~physgrad.problems.Oscillators`, not a subclass of it:
    every setting is stated here with the book's value.
    """

    n_oscillators: int = eqx.field(static=True, default=2)
    n_steps: int = eqx.field(static=True, default=24)
    dt: float = eqx.field(static=True, default=0.5)
    cubic_coupling: float = eqx.field(static=True, default=0.0)
    linear_coupling: float = eqx.field(static=True, default=0.2)
    control_gain: float = eqx.field(static=True, default=1.0)
    n_train: int = eqx.field(static=True, default=4096)
    n_test: int = eqx.field(static=True, default=4096)  # physgrad's test set (the book has none)
    hidden: int = eqx.field(static=True, default=20)
    activation: Callable = eqx.field(static=True, default=jax.nn.tanh)
    dtype: str = eqx.field(static=True, default="float32")

    name: ClassVar[str] = "linear_oscillators"
    source: ClassVar[str] = "PBDL book, physgrad-hig-code.ipynb"
    default_batch_size: ClassVar[int] = 32
