"""Nonlinear coupled oscillators: the HIG paper's first benchmark (Fig. 2b).

Source: Schnell, Holl, Thuerey, ICLR 2022, §"Nonlinear oscillators"; the authors' code
``Nonlinear_oscillators/``.

State ``s = (q_1..q_n, p_1..p_n)`` (positions first), n oscillators with free ends:

    dq_i/dt = p_i
    dp_i/dt = −q_i + α (q_{i+1} − q_i)³ + α (q_{i−1} − q_i)³ + β (q_{i+1} + q_{i−1} − 2 q_i)
              + c · u(t) · δ_{i,n}

with cubic coupling α = 1, linear coupling β = 0 and control gain c = 3 on the last
oscillator only. Classic RK4, dt = 0.125, 96 steps (T = 12), control piecewise constant per
step. Task: return to the initial state, ``y* = x_0 ~ U[0,1)^{2n}``; the network sees
``x_0`` and outputs the 96 controls. Loss ``L_i = ‖y_i − y*_i‖²`` (no ½) on the final state.
Network 4 → 20 → 20 → 20 → 96, ReLU, glorot-uniform kernels, zero biases (2,956 params).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from ..precision import require_float64
from .base import AbstractProblem
from .sim.integrators import integrate, rk4_step


class AbstractOscillators(AbstractProblem):
    """Return-to-start control of a chain of coupled oscillators: the physics, data, network
    and loss shared by :class:`Oscillators` (the HIG paper's cubic chain) and
    :class:`~physgrad.problems.LinearOscillators` (the PBDL book's linear one).

    Equinox's abstract/final pattern: this class holds the methods, each final class
    declares every setting with its own source's value, and no concrete problem is
    subclassed (a preset would otherwise inherit the other paper's defaults silently).
    """

    n_oscillators: eqx.AbstractVar[int]
    n_steps: eqx.AbstractVar[int]
    dt: eqx.AbstractVar[float]
    cubic_coupling: eqx.AbstractVar[float]  # α
    linear_coupling: eqx.AbstractVar[float]  # β
    control_gain: eqx.AbstractVar[float]  # c
    n_train: eqx.AbstractVar[int]
    n_test: eqx.AbstractVar[int]
    hidden: eqx.AbstractVar[int]
    activation: eqx.AbstractVar[Callable]  # of the hidden layers (jax.nn.relu, jax.nn.tanh, ...)
    dtype: eqx.AbstractVar[str]

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        """``dtype=float64`` runs the whole problem in double precision (engine scopes x64)."""
        return jnp.dtype(self.dtype) == jnp.float64

    @property
    def state_size(self) -> int:
        return 2 * self.n_oscillators

    def rhs(self, state, control):
        """Right-hand side ``ds/dt`` of the controlled chain (free ends), one sample."""
        n = self.n_oscillators
        q, p = state[:n], state[n:]
        # Differences to the right neighbour; the last oscillator has none (free end).
        right = jnp.concatenate([q[1:] - q[:-1], jnp.zeros_like(q[:1])])
        left = jnp.concatenate([jnp.zeros_like(q[:1]), q[:-1] - q[1:]])
        force = -q + self.cubic_coupling * (right**3 + left**3) + self.linear_coupling * (right + left)
        force = force.at[n - 1].add(self.control_gain * control)
        return jnp.concatenate([p, force])

    def make_data(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        k_train, k_test = jax.random.split(key)
        draw = lambda k, n: {"x0": jax.random.uniform(k, (n, self.state_size), jnp.dtype(self.dtype))}  # noqa: E731
        return {"train": draw(k_train, self.n_train), "test": draw(k_test, self.n_test)}

    def make_network(self, key):
        if self.needs_float64:
            require_float64(f"{self.name} with dtype={self.dtype}")
        sizes = (self.state_size, self.hidden, self.hidden, self.hidden, self.n_steps)
        return MLP(sizes, self.activation, key=key, dtype=jnp.dtype(self.dtype))

    def network_output(self, network, sample):
        return network(sample["x0"])

    def simulate(self, controls, sample):
        return integrate(rk4_step, self.rhs, sample["x0"], controls, self.dt)

    def loss(self, y, sample):
        return jnp.sum((y - sample["x0"]) ** 2)

    def target(self, sample):
        """Return to the start: y* = x₀ (SIP's y-space target)."""
        return sample["x0"]


class Oscillators(AbstractOscillators):
    """Return-to-start control of a chain of cubically coupled oscillators (HIG paper)."""

    n_oscillators: int = eqx.field(static=True, default=2)
    n_steps: int = eqx.field(static=True, default=96)
    dt: float = eqx.field(static=True, default=0.125)
    cubic_coupling: float = eqx.field(static=True, default=1.0)
    linear_coupling: float = eqx.field(static=True, default=0.0)
    control_gain: float = eqx.field(static=True, default=3.0)
    n_train: int = eqx.field(static=True, default=4096)
    n_test: int = eqx.field(static=True, default=4096)
    hidden: int = eqx.field(static=True, default=20)
    activation: Callable = eqx.field(static=True, default=jax.nn.relu)
    dtype: str = eqx.field(static=True, default="float32")

    name: ClassVar[str] = "oscillators"
    source: ClassVar[str] = "Schnell, Holl, Thuerey, ICLR 2022, Fig. 2b"
    default_batch_size: ClassVar[int] = 128
