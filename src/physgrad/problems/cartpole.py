"""Cart-pole swing-up with several poles on one cart (stabilised BPTT's first task).

Source: Schnell & Thuerey, ICLR 2024, cart-pole; the authors' ``CartPole/`` code. One unbounded force F (the network output) drives a
cart carrying ``poles`` poles. With g = 9.8, pole mass m = 0.1, "total mass" M = 1.1 (kept
for any number of poles, as in the code) and half-length l = 0.5, per pole i:

    A_i  = (F + m l sin θ_i θ̇_i²) / M
    θ̈_i = (g sin θ_i − cos θ_i A_i) / (l (4/3 − m cos² θ_i / M))
    ẍ   = (F + m l Σ_i (sin θ_i θ̇_i² − θ̈_i cos θ_i)) / M

These are the classic single-pole (gym) equations applied per pole: the poles do not react
on each other through the cart (a quirk of the code, reproduced). Semi-implicit Euler:
velocities first (θ̇ += dt θ̈, ẋ += dt ẍ), then positions with the new velocities;
dt = 0.01, 100 steps (T = 1 s).

State (1 + poles, 2): the cart (x, ẋ), then each pole (θ_i, θ̇_i); θ = 0 is upright.
Initial states: x, ẋ, θ̇_i ~ U(−1, 1), θ_i = π + U(−1, 1)·π/6 (hanging down ±30°).
Loss (final): L = 1 − mean_i cos θ_i(T), in [0, 2]. Controller: flatten(2(1+poles)) → 100
tanh → 100 tanh → 1, glorot-uniform kernels, the last kernel zeroed (the authors' zero-init
pitfall, §2.6.1: the first control is exactly 0, where g_R = g_M).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import MLP
from .closed_loop import AbstractClosedLoop, zero_last_kernel


class CartPole(AbstractClosedLoop):
    """Swing up 1-4 poles on one cart with one force in 1 s (final loss 1 − cos θ)."""

    n_train: int = eqx.field(static=True, default=256)
    n_test: int = eqx.field(static=True, default=256)
    data_seed: int = eqx.field(static=True, default=42)
    poles: int = eqx.field(static=True, default=1)
    dt: float = eqx.field(static=True, default=0.01)
    n_steps: int = eqx.field(static=True, default=100)
    gravity: float = eqx.field(static=True, default=9.8)
    pole_mass: float = eqx.field(static=True, default=0.1)
    total_mass: float = eqx.field(static=True, default=1.1)
    half_length: float = eqx.field(static=True, default=0.5)
    width: int = eqx.field(static=True, default=100)
    zero_init: bool = eqx.field(static=True, default=True)

    name: ClassVar[str] = "cartpole"
    source: ClassVar[str] = "Schnell & Thuerey, ICLR 2024, cart-pole"

    def __check_init__(self):
        if self.poles < 1:
            raise ValueError(f"poles must be at least 1, got {self.poles}")

    def initial_states(self, key, n):
        kx, kv, kt, kw = jax.random.split(key, 4)
        f32 = jnp.float32
        cart = jnp.stack([jax.random.uniform(kx, (n,), f32, -1, 1), jax.random.uniform(kv, (n,), f32, -1, 1)], axis=-1)
        theta = math.pi + jax.random.uniform(kt, (n, self.poles), f32, -1, 1) * (math.pi / 6)
        omega = jax.random.uniform(kw, (n, self.poles), f32, -1, 1)
        poles = jnp.stack([theta, omega], axis=-1)
        return jnp.concatenate([cart[:, None, :], poles], axis=1)  # (n, 1 + poles, 2)

    def make_network(self, key):
        net = MLP((2 * (1 + self.poles), self.width, self.width, 1), jax.nn.tanh, key=key)
        return zero_last_kernel(net) if self.zero_init else net

    def control(self, network, s):
        return network(s.ravel())[0]

    def accelerations(self, s, force):
        """(ẍ, θ̈_i) of the cart and each pole under ``force``."""
        g, m, big_m, l = self.gravity, self.pole_mass, self.total_mass, self.half_length
        theta, omega = s[1:, 0], s[1:, 1]
        sin, cos = jnp.sin(theta), jnp.cos(theta)
        a = (force + m * l * sin * omega**2) / big_m
        theta_acc = (g * sin - cos * a) / (l * (4.0 / 3.0 - m * cos**2 / big_m))
        x_acc = (force + m * l * jnp.sum(sin * omega**2 - theta_acc * cos)) / big_m
        return x_acc, theta_acc

    def physics(self, s, c):
        x_acc, theta_acc = self.accelerations(s, c)
        velocities = s[:, 1] + self.dt * jnp.concatenate([x_acc[None], theta_acc])
        positions = s[:, 0] + self.dt * velocities  # semi-implicit: the new velocities
        return jnp.stack([positions, velocities], axis=-1)

    def step_loss(self, s_next, c, k):
        return 1.0 - jnp.mean(jnp.cos(s_next[1:, 0]))

    def loss_weights(self):
        return jnp.zeros(self.n_steps, jnp.float32).at[-1].set(1.0)
