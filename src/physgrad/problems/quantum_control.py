"""Closed-loop quantum control: steer a particle in a box to an excited eigenstate.

Source: Schnell & Thuerey, ICLR 2024, quantum control; the authors' ``QuantumControl/``
code. The 1-D Schrödinger equation (ħ = 1, m = ½)

    i ∂ψ/∂t = −∂²ψ/∂x² + u(t) x ψ,     x ∈ (0, 2),  ψ(0) = ψ(2) = 0,

on Nx = 32 interior points (dx = 2/33, x_j = j dx), Crank–Nicolson with dt = 0.0625 for
128 steps (T = 8): the same solver as the HIG quantum-dipole problem
(:meth:`physgrad.problems.QuantumDipole.cn_step`; the authors solve it as a dense 32×32
system, physgrad as the equivalent tridiagonal one). CN is unitary for real u, so ‖ψ‖
is conserved.

Initial states ψ₀ = (c₁ e^{iα₁} φ₁ + c₂ e^{iα₂} φ₂)/√(c₁² + c₂²), c_k ~ N(0, 1), α_k ~
U(0, 2π) (weighting 1-1), φ_n the discrete Dirichlet eigenvectors sin(π n j/33)
normalised. Target φ_TS, TS ∈ {3, 4, 5} (setting ``eigenstate``; the authors' plots count
from 0 and title these 2, 3, 4). Loss (continuous, summed over time):

    L = Σ_{t=1}^{128} (1 − |⟨ψ_t, φ_TS⟩|²)      ∈ [0, 128].

Controller (closed loop, a feedback on ψ_k at every step): (Re ψ, Im ψ) as a 32×2 image →
Conv2D(60, kernel (3, 2), stride 2, tanh, valid) → (15, 60) → Conv1D(60, 3, stride 2,
tanh, valid) → (7, 60) → flatten 420 → Dense 1 (linear) = u(t); 11,701 parameters,
glorot-uniform kernels and zero biases (Keras). Quirk (§2.6.1): the zero-init flag only
zeroes the last bias here, so the initial control is not zero.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import Dense
from .closed_loop import AbstractClosedLoop
from .quantum_dipole import QuantumDipole


def _glorot(key, shape, fan_in: int, fan_out: int):
    limit = (6.0 / (fan_in + fan_out)) ** 0.5
    return jax.random.uniform(key, shape, jnp.float32, -limit, limit)


def _patches(x, size: int, stride: int):
    """Valid 1-D windows along axis 0: (n, …) → (n_out, size, …)."""
    n_out = (x.shape[0] - size) // stride + 1
    span = stride * (n_out - 1) + 1
    return jnp.stack([x[j : j + span : stride] for j in range(size)], axis=1)


class QuantumController(eqx.Module):
    """The authors' CNN controller: ψ (n,) complex → u (scalar).

    Conv2D(width, (3, 2), stride 2) on the (n, 2) image of (Re ψ, Im ψ) and Conv1D(width, 3,
    stride 2), both "valid" with tanh, then Dense 1. The convolutions are written as
    window extraction + ``einsum`` (identical to ``lax.conv``, tested against
    ``eqx.nn.Conv2d``/``Conv1d``): at these tiny sizes XLA's CPU convolution costs ~8× more.
    Keras initialisation: glorot-uniform kernels (fans = kernel size × channels), zero biases.
    """

    kernel1: jax.Array  # (width, 3, 2): Conv2D over (row, Re/Im), one input channel
    bias1: jax.Array
    kernel2: jax.Array  # (width, 3, width): Conv1D over (tap, channel)
    bias2: jax.Array
    out: Dense

    def __init__(self, n: int, width: int, *, key):
        k1, k2, k3 = jax.random.split(key, 3)
        self.kernel1 = _glorot(k1, (width, 3, 2), 6, 6 * width)
        self.bias1 = jnp.zeros((width,), jnp.float32)
        self.kernel2 = _glorot(k2, (width, 3, width), 3 * width, 3 * width)
        self.bias2 = jnp.zeros((width,), jnp.float32)
        n2 = ((n - 3) // 2 + 1 - 3) // 2 + 1
        self.out = Dense(width * n2, 1, key=k3)

    def __call__(self, psi):
        image = jnp.stack([psi.real, psi.imag], axis=-1)  # (n, 2)
        h = jnp.tanh(jnp.einsum("ikl,okl->io", _patches(image, 3, 2), self.kernel1) + self.bias1)  # (n1, width)
        h = jnp.tanh(jnp.einsum("ikc,okc->io", _patches(h, 3, 2), self.kernel2) + self.bias2)  # (n2, width)
        return self.out(h.ravel())[0]


class QuantumControl(AbstractClosedLoop):
    """Feedback control of the 1-D Schrödinger equation to eigenstate 3, 4 or 5 (summed infidelity)."""

    n_train: int = eqx.field(static=True, default=256)
    n_test: int = eqx.field(static=True, default=256)
    data_seed: int = eqx.field(static=True, default=42)
    eigenstate: int = eqx.field(static=True, default=3)
    nx: int = eqx.field(static=True, default=32)
    dt: float = eqx.field(static=True, default=0.0625)
    n_steps: int = eqx.field(static=True, default=128)
    width: int = eqx.field(static=True, default=60)

    name: ClassVar[str] = "quantum_control"
    source: ClassVar[str] = "Schnell & Thuerey, ICLR 2024, quantum control"

    def __check_init__(self):
        if not 1 <= self.eigenstate <= self.nx:
            raise ValueError(f"eigenstate must be an eigenstate 1..{self.nx}, got {self.eigenstate}")

    @property
    def box(self) -> QuantumDipole:
        """The HIG problem's Crank–Nicolson solver on this grid (n_grid counts both walls)."""
        return QuantumDipole(n_grid=self.nx + 2, length=2.0, dt=self.dt, n_steps=self.n_steps)

    def initial_states(self, key, n):
        kc, ka = jax.random.split(key)
        c = jax.random.normal(kc, (n, 2), jnp.float32)
        alpha = jax.random.uniform(ka, (n, 2), jnp.float32, 0, 2 * math.pi)
        phi = jnp.stack([self.box.eigenstate(1), self.box.eigenstate(2)])  # (2, nx)
        coeff = (c * jnp.exp(1j * alpha)).astype(jnp.complex64)
        psi = coeff @ phi.astype(jnp.complex64)
        return psi / jnp.linalg.norm(c, axis=1, keepdims=True)

    def make_network(self, key):
        return QuantumController(self.nx, self.width, key=key)

    def control(self, network, s):
        return network(s)

    def physics(self, s, c):
        return self.box.cn_step(s, c)

    def fidelity(self, psi):
        """|⟨ψ, φ_TS⟩|²."""
        return jnp.abs(jnp.vdot(self.box.eigenstate(self.eigenstate).astype(psi.dtype), psi)) ** 2

    def step_loss(self, s_next, c, k):
        return 1.0 - self.fidelity(s_next)

    def loss_weights(self):
        return jnp.ones(self.n_steps, jnp.float32)

    def metrics(self, x, y, sample):
        """``final_infidelity``: 1 − |⟨ψ_T, φ_TS⟩|² at the end of the rollout."""
        states, _ = y
        return {"final_infidelity": 1.0 - self.fidelity(states[-1])}
