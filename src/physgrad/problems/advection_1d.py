"""1D periodic advection: learn a 2-tap stencil (trainax's quick-start).

    u_t + c u_x = 0 on [0, 1),  N = 30,  CFL = c Δt/Δx = −0.75,  Δt = 1,

reference frames from the exact Fourier-spectral solution (exponax ``Advection``) of random
truncated Fourier series (modes 1–5, amplitudes U(−1, 1), no offset): 20 training
trajectories of 100 steps. The network is a linear 2-tap convolution without bias
(u⁺_i = w₀u_i + w₁u_{i+1}, circular); Adam 1e-2, batch 32. trainax trains it for 1000 steps
with 1, 5 and 20 supervised rollout steps and reports the distance of w to the first-order
upwind stencil (FOU) [1 + CFL, −CFL]: 0.033, 0.025, 0.017 (:func:`fou_distance`).

Correction setup: the coarse solver is **implicit** first-order upwind,

    (1 + |C|) u⁺_i − |C| u⁺_{i+s} = u_i     (s = +1 for C < 0, −1 otherwise),

solved by ``iterations`` Jacobi sweeps from u⁺ = u (contraction |C|/(1+|C|) ≈ 0.43 per
sweep): an iterative solver whose inner iteration count a PRDP schedule can refine
(Bhatia et al., ICLR 2025). It is differentiable (the sweeps are unrolled).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..extras import import_extra
from ..precision import float64_scope
from .sim.steppers import AbstractComposition, Parallel, Repeated, Solver
from .time_stepper import AbstractTimeStepper, solver_rollout


class ImplicitUpwind(Solver):
    """Implicit first-order upwind for u_t + c u_x = 0 with ``iterations`` Jacobi sweeps."""

    cfl: float = eqx.field(static=True)
    iterations: int = eqx.field(static=True)

    def __call__(self, u, cond):
        a, shift = abs(self.cfl), (-1 if self.cfl < 0 else 1)  # roll by −1 brings u_{i+1} to i

        def sweep(_, v):
            return (u + a * jnp.roll(v, shift, axis=-1)) / (1.0 + a)

        return jax.lax.fori_loop(0, self.iterations, sweep, u)


def fou_distance(network, cfl: float = -0.75) -> float:
    """‖w − [1 + CFL, −CFL]‖ of a trained 2-tap stencil (trainax's quick-start metric)."""
    w = np.asarray(network.weight).reshape(-1)
    return float(np.linalg.norm(w - np.array([1 + cfl, -cfl])))


class Advection1d(AbstractTimeStepper):
    name: ClassVar[str] = "advection_1d"
    source: ClassVar[str] = "trainax README; List et al. 2025; Bhatia et al. ICLR 2025"
    extra: ClassVar[str | None] = "pde"  # exponax (the reference)
    default_eval_samples: ClassVar[int] = 0

    composition: AbstractComposition = eqx.field(static=True, default=Parallel(scale=1.0))
    m: int = eqx.field(static=True, default=5)
    eval_horizon: int = eqx.field(static=True, default=12)
    data_seed: int = eqx.field(static=True, default=0)
    differentiable_solver: bool = eqx.field(static=True, default=True)
    zero_init: bool = eqx.field(static=True, default=False)
    n: int = eqx.field(static=True, default=30)
    cfl: float = eqx.field(static=True, default=-0.75)
    highest_mode: int = eqx.field(static=True, default=5)
    n_train: int = eqx.field(static=True, default=20)
    n_test: int = eqx.field(static=True, default=20)
    horizon: int = eqx.field(static=True, default=100)
    iterations: int = eqx.field(static=True, default=20)

    training_only_settings: ClassVar[tuple[str, ...]] = ("iterations",)
    refinable_setting: ClassVar[str] = "iterations"  # what PRDP refines

    def reference(self):
        ex = import_extra("exponax", "pde", "the advection_1d problem")

        return Repeated(ex.stepper.Advection(1, 1.0, self.n, 1.0, velocity=self.cfl / self.n))

    def solvers(self):
        return ImplicitUpwind(self.cfl, self.iterations)

    def initial_conditions(self, key, count: int):
        x = jnp.arange(self.n) / self.n * 2 * jnp.pi
        k1, k2 = jax.random.split(key)
        a = jax.random.uniform(k1, (count, self.highest_mode, 1), jnp.float64, -1.0, 1.0)
        b = jax.random.uniform(k2, (count, self.highest_mode, 1), jnp.float64, -1.0, 1.0)
        modes = jnp.arange(1, self.highest_mode + 1)[:, None]
        u0 = jnp.sum(a * jnp.sin(modes * x) + b * jnp.cos(modes * x), axis=1)
        return u0[:, None, :]

    def generate(self, split):
        with float64_scope():  # the reference runs in float64 whatever the caller's x64 setting
            return self._generate(split)

    def _generate(self, split):
        count, seed, frames = {"train": (self.n_train, 0, self.horizon), "val": (4, 1, self.eval_horizon),
                               "test": (self.n_test, 2, max(self.horizon, self.eval_horizon))}[split]  # fmt: skip
        u0 = self.initial_conditions(jax.random.fold_in(jax.random.key(self.data_seed), seed), count)
        _, traj = solver_rollout(self.reference(), u0, frames)
        u = np.concatenate([np.asarray(u0)[:, None], np.asarray(traj).swapaxes(0, 1)], axis=1).astype(np.float32)
        return {"u": u, "cond": np.zeros(count, np.float32), "index": np.zeros(count, np.int32)}

    def make_network(self, key):
        return eqx.nn.Conv1d(
            1, 1, 2, padding="SAME", padding_mode="CIRCULAR", use_bias=False, dtype=jnp.float32, key=key
        )

    def apply(self, network, u, cond):
        return network(u)
