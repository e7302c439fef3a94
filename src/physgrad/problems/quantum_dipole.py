"""Quantum dipole control: the HIG paper's Schrödinger benchmark.

Source: Schnell, Holl, Thuerey, ICLR 2022, quantum dipole; the authors' code
``Quantum_dipole/``.

A particle in a box, driven by a dipole field u(t) (ħ = 1, m = ½):

    i ∂ψ/∂t = H(u) ψ,      H(u) = −∂xx + u(t) · x,      x ∈ [0, 2],  ψ(0) = ψ(2) = 0.

Space: 16 grid points, dx = 2/15, the 14 interior values ψ_j = ψ(j·dx) are the unknowns
(homogeneous Dirichlet walls); −∂xx is the 3-point stencil, so H is tridiagonal with
diagonal 2/dx² + u·x_j and off-diagonals −1/dx². Time: Crank–Nicolson,

    (I + i dt/2 H(u_n)) ψ^{n+1} = (I − i dt/2 H(u_n)) ψ^n,    dt = 0.05, 384 steps (T = 19.2),

one control value per step (piecewise constant), solved as a complex tridiagonal system
(``lax.linalg.tridiagonal_solve``) inside ``lax.scan``. CN is unitary for real u, so the
norm is conserved exactly up to round-off.

Task: every sample starts in the discrete ground state ψ₁ (ψ_n ∝ sin(π n j / 15), the
exact eigenvectors of the discrete H(0)); the target is a random real superposition
ψ* = (c₁ψ₂ + c₂ψ₃)/‖c‖, c ~ N(0, 1)². The network sees ψ* as (Re, Im) pairs (28 values)
and outputs the 384 controls through tanh 20-20-20 (9,484 parameters). Loss: the
infidelity ``L = 1 − |⟨ψ*|ψ(T)⟩|²``. The simulator output y = ψ(T) enters HIG's
Jacobian as stacked (Re, Im) pairs: 14 × 2 = 28 rows per sample.

The authors draw two unused phases per sample; physgrad draws only c (its own RNG, so the
samples differ from theirs anyway).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from ..precision import require_float64
from .base import AbstractProblem


class QuantumDipole(AbstractProblem):
    """Steer a particle in a box from the ground state to a mix of the 2nd and 3rd eigenstates."""

    n_grid: int = eqx.field(static=True, default=16)
    length: float = eqx.field(static=True, default=2.0)
    dt: float = eqx.field(static=True, default=0.05)
    n_steps: int = eqx.field(static=True, default=384)
    n_train: int = eqx.field(static=True, default=1024)
    n_test: int = eqx.field(static=True, default=1024)
    hidden: int = eqx.field(static=True, default=20)
    dtype: str = eqx.field(static=True, default="float32")

    name: ClassVar[str] = "quantum_dipole"
    source: ClassVar[str] = "Schnell, Holl, Thuerey, ICLR 2022, quantum dipole"
    default_batch_size: ClassVar[int] = 16

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        """``dtype=float64`` runs the whole problem in double precision (engine scopes x64)."""
        return jnp.dtype(self.dtype) == jnp.float64

    def __check_init__(self):
        if self.n_grid < 4:
            raise ValueError(f"n_grid must be at least 4, got {self.n_grid}")

    @property
    def n_interior(self) -> int:
        return self.n_grid - 2

    @property
    def dx(self) -> float:
        return self.length / (self.n_grid - 1)

    @property
    def complex_dtype(self):
        return jnp.result_type(jnp.dtype(self.dtype), jnp.complex64)

    def positions(self) -> jax.Array:
        """Interior grid points x_j = j·dx, j = 1..n_grid−2."""
        return self.dx * jnp.arange(1, self.n_grid - 1, dtype=jnp.dtype(self.dtype))

    def eigenstate(self, n: int) -> jax.Array:
        """The n-th eigenvector of the discrete H(0), ``sin(π n j / (N+1))`` normalised (real)."""
        j = jnp.arange(1, self.n_grid - 1, dtype=jnp.dtype(self.dtype))
        psi = jnp.sin(math.pi * n * j / (self.n_grid - 1))
        return psi / jnp.linalg.norm(psi)

    def hamiltonian_bands(self, control):
        """Sub-, main and super-diagonal of H(u) (the tridiagonal_solve layout: dl[0] = du[-1] = 0)."""
        n, inv_dx2 = self.n_interior, 1.0 / self.dx**2
        off = jnp.full((n,), -inv_dx2, jnp.dtype(self.dtype))
        lower = off.at[0].set(0.0)
        upper = off.at[-1].set(0.0)
        diagonal = 2.0 * inv_dx2 + control * self.positions()
        return lower, diagonal, upper

    def cn_step(self, psi, control):
        """One Crank–Nicolson step ``(I + i dt/2 H) ψ' = (I − i dt/2 H) ψ`` (complex tridiagonal solve)."""
        lower, diagonal, upper = self.hamiltonian_bands(control)
        half = 0.5j * self.dt
        h_psi = diagonal * psi + upper * jnp.roll(psi, -1) + lower * jnp.roll(psi, 1)
        rhs = psi - half * h_psi
        ctype = self.complex_dtype
        solved = jax.lax.linalg.tridiagonal_solve(
            (half * lower).astype(ctype),
            (1.0 + half * diagonal).astype(ctype),
            (half * upper).astype(ctype),
            rhs.astype(ctype)[:, None],
        )
        return solved[:, 0]

    def make_data(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        psi2, psi3 = self.eigenstate(2), self.eigenstate(3)

        def draw(k, n):
            c = jax.random.normal(k, (n, 2), jnp.dtype(self.dtype))
            c = c / jnp.linalg.norm(c, axis=1, keepdims=True)
            target = c[:, :1] * psi2 + c[:, 1:] * psi3
            # (Re, Im) pairs, as the authors' (b, 14, 2) tensors; the targets are real.
            return {"target": jnp.stack([target, jnp.zeros_like(target)], axis=-1)}

        k_train, k_test = jax.random.split(key)
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        sizes = (2 * self.n_interior, self.hidden, self.hidden, self.hidden, self.n_steps)
        return MLP(sizes, jax.nn.tanh, key=key, dtype=jnp.dtype(self.dtype))

    def network_output(self, network, sample):
        return network(sample["target"].ravel())

    def simulate(self, controls, sample):
        """ψ(T) (complex, n_grid−2 values) from the ground state under ``controls`` (n_steps,)."""
        psi0 = self.eigenstate(1).astype(self.complex_dtype)

        def body(psi, u):
            return self.cn_step(psi, u), None

        psi, _ = jax.lax.scan(body, psi0, controls)
        return psi

    def loss(self, psi, sample):
        target = sample["target"][..., 0] + 1j * sample["target"][..., 1]
        overlap = jnp.sum(jnp.conj(target) * psi)
        return 1.0 - jnp.abs(overlap) ** 2
