"""Guidance by repulsion (herding): 2 drivers steer 4 evaders to the origin.

Source: Schnell & Thuerey, ICLR 2024, guidance by repulsion; the authors'
``GuidanceByRepulsion/`` code. The physics is reproduced
as coded, quirks included (§2.6.3), each marked below.

State (6, 2, 2) = (agent, position/velocity, xy): drivers 0–1, then evaders 2–5. With
ε = 0.1 and dist(r) = ε + |r|:

evaders (c_ev = 15, c_fric,ev = 4, c_flock = 0.2, d_f = 0.5)

    v̇_e = c_ev Σ_d (x_e − x_d)/dist(x_d − x_e)² − c_fric,ev v_e
          + c_flock Σ_{e'≠e} p(dist(x_e' − x_e)) (x_e' − x_e),     p(d) = (d_f/d − 1)/d

  (quirk: as coded the flock term attracts below d_f and repels above it);

drivers (c_fric,dr = 1, c_spread = 0.2), with the network's (a_d, b_d) per driver

    v̇_d = a_d (x_d − X) + b_d R₉₀(x_d − X) − c_fric,dr v_d + c_spread Σ_{d'≠d} (x_d − x_d')/dist²,

  R₉₀(x, y) = (−y, x) (quirk: X = Σ_e x_e is the *sum* of the evader positions, the code's
  ``center_diff``; the unused ``c_drive`` is left out).

Explicit Euler on (x, v) together, dt = 4/60, 60 steps. Loss (continuous):

    L = mean_{t=1..60, e, xy} x_e(t)² + rc · mean_{t, d, k} c_t²

(quirk: the target is the origin, hard-coded). Initial states: each driver at angle
U[0, 2π), radius U[3, 4]; the evaders' centre at radius U[1, 2], uniform angle, each evader
offset by U[−0.5, 0.5]²; all velocities 0. Controller: flatten(24) → 100 tanh → 100 tanh →
4 (2 coefficients per driver), last kernel zeroed (13,004 parameters). Self-pairs are left
out of the pairwise sums (|0| would give NaN gradients), as the authors delete them.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..nets import MLP
from .closed_loop import AbstractClosedLoop, zero_last_kernel


def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index arrays (i, j) of all ordered pairs i ≠ j."""
    i, j = np.nonzero(~np.eye(n, dtype=bool))
    return i, j


class Guidance(AbstractClosedLoop):
    """Two drivers herd four evaders to the origin by repulsion (continuous loss + rc·c²)."""

    n_train: int = eqx.field(static=True, default=256)
    n_test: int = eqx.field(static=True, default=256)
    data_seed: int = eqx.field(static=True, default=42)
    rc: float = eqx.field(static=True, default=0.1)
    drivers: int = eqx.field(static=True, default=2)
    evaders: int = eqx.field(static=True, default=4)
    horizon: float = eqx.field(static=True, default=4.0)
    n_steps: int = eqx.field(static=True, default=60)
    eps: float = eqx.field(static=True, default=0.1)
    c_evade: float = eqx.field(static=True, default=15.0)
    friction_evader: float = eqx.field(static=True, default=4.0)
    c_flock: float = eqx.field(static=True, default=0.2)
    flock_distance: float = eqx.field(static=True, default=0.5)
    friction_driver: float = eqx.field(static=True, default=1.0)
    c_spread: float = eqx.field(static=True, default=0.2)
    width: int = eqx.field(static=True, default=100)
    zero_init: bool = eqx.field(static=True, default=True)

    name: ClassVar[str] = "guidance"
    source: ClassVar[str] = "Schnell & Thuerey, ICLR 2024, guidance by repulsion"

    def __check_init__(self):
        if self.drivers < 1 or self.evaders < 1:
            raise ValueError("guidance needs at least one driver and one evader")
        if self.rc < 0:
            raise ValueError(f"rc must be >= 0, got {self.rc}")

    @property
    def dt(self) -> float:
        return self.horizon / self.n_steps

    def initial_states(self, key, n):
        f32 = jnp.float32
        k_da, k_dr, k_ca, k_cr, k_off = jax.random.split(key, 5)
        angle = jax.random.uniform(k_da, (n, self.drivers), f32, 0, 2 * math.pi)
        radius = jax.random.uniform(k_dr, (n, self.drivers), f32, 3, 4)
        drivers = radius[..., None] * jnp.stack([jnp.cos(angle), jnp.sin(angle)], -1)
        c_angle = jax.random.uniform(k_ca, (n, 1), f32, 0, 2 * math.pi)
        c_radius = jax.random.uniform(k_cr, (n, 1), f32, 1, 2)
        centre = c_radius[..., None] * jnp.stack([jnp.cos(c_angle), jnp.sin(c_angle)], -1)
        evaders = centre + jax.random.uniform(k_off, (n, self.evaders, 2), f32, -0.5, 0.5)
        positions = jnp.concatenate([drivers, evaders], axis=1)
        return jnp.stack([positions, jnp.zeros_like(positions)], axis=2)  # (n, agents, 2, 2)

    def make_network(self, key):
        agents = self.drivers + self.evaders
        net = MLP((agents * 4, self.width, self.width, 2 * self.drivers), jax.nn.tanh, key=key)
        return zero_last_kernel(net) if self.zero_init else net

    def control(self, network, s):
        return network(s.ravel()).reshape(self.drivers, 2)

    def _dist(self, r):
        return self.eps + jnp.linalg.norm(r, axis=-1, keepdims=True)

    def accelerations(self, s, c):
        """(v̇_drivers (D, 2), v̇_evaders (E, 2)) as coded by the authors."""
        xd, vd = s[: self.drivers, 0], s[: self.drivers, 1]
        xe, ve = s[self.drivers :, 0], s[self.drivers :, 1]
        # evaders: repulsion from every driver, friction, flocking with the other evaders
        away = xe[:, None, :] - xd[None, :, :]  # (E, D, 2)
        repulsion = jnp.sum(away / self._dist(-away) ** 2, axis=1)
        i, j = _pairs(self.evaders)
        towards = xe[j] - xe[i]  # (pairs, 2): x_e' − x_e
        d = self._dist(towards)
        flock = jax.ops.segment_sum((self.flock_distance / d - 1.0) / d * towards, i, self.evaders)
        acc_e = self.c_evade * repulsion - self.friction_evader * ve + self.c_flock * flock
        # drivers: radial and tangential forces about X = Σ_e x_e (the sum: a quirk)
        rel = xd - jnp.sum(xe, axis=0)
        rot = jnp.stack([-rel[:, 1], rel[:, 0]], axis=-1)
        acc_d = c[:, :1] * rel + c[:, 1:] * rot - self.friction_driver * vd
        if self.drivers > 1:
            i, j = _pairs(self.drivers)
            apart = xd[i] - xd[j]
            acc_d = acc_d + self.c_spread * jax.ops.segment_sum(apart / self._dist(apart) ** 2, i, self.drivers)
        return acc_d, acc_e

    def physics(self, s, c):
        acc = jnp.concatenate(self.accelerations(s, c), axis=0)
        x, v = s[:, 0], s[:, 1]
        return jnp.stack([x + self.dt * v, v + self.dt * acc], axis=1)  # explicit Euler

    def evader_loss(self, s):
        return jnp.mean(s[self.drivers :, 0] ** 2)

    def step_loss(self, s_next, c, k):
        return self.evader_loss(s_next) + self.rc * jnp.mean(c**2)

    def loss_weights(self):
        return jnp.full(self.n_steps, 1.0 / self.n_steps, jnp.float32)

    def metrics(self, x, y, sample):
        """``physics_loss``: the loss without the control term (the authors' l_phys)."""
        states, _ = y
        return {"physics_loss": jnp.mean(jax.vmap(self.evader_loss)(states))}
