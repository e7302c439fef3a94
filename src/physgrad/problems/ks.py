"""Kuramoto–Sivashinsky: a neural time-stepper corrects (or replaces) a first-order solver.

List, Chen, Bali & Thuerey, CMAME 2025, the Kuramoto–Sivashinsky experiment:

    u_t + ½ ∂ₓ(u²) + u_xx + u_xxxx = 0,   periodic on [0, L),  L = 2π · 8 · f,

N = 48 points, frames Δt = 1 apart. The reference is ETRK2 (Cox–Matthews, exponax
``KuramotoSivashinskyConservative`` order 2) with two substeps of 0.5 per frame and no
dealiasing (as the authors'); the correction solver is ETD1 (order 1) at the same grid and
substeps, so the network learns the temporal discretisation error of a lower-order scheme.
The domain factor f is the conditioning input (the network's second channel, L/8 in the
authors' units of 2π): training f ∈ {0.9, 0.95, 1.0, 1.1, 1.2, 1.3}, test f ∈ {0.85, 0.93,
1.15, 1.40} (two interpolating, two extrapolating).

Data (seeded, cached): per training size ``n_ics`` trajectories from random low-mode
cosine perturbations, ``warmup_frames`` frames dropped, then ``frames × dataset_fraction``
frames (the authors: 6 ICs, 200, 5000 × 0.25); ``n_test`` test trajectories per test size of
``long_horizon`` frames after the warm-up (the authors score 12 steps of 5000-step
rollouts; we keep ``long_horizon`` frames for the decorrelation time). The network is the
1D conv ResNet (``width`` × ``blocks``: (16, 10) the code default, (26, 8) and (52, 12) the
blog re-run), Adam lr 1e-4, batch 16, m = 3.

Batches (shuffled by default, as the KS code): every batch holds windows of one domain size,
drawn at random from that size's windows, and the sizes' batches are interleaved at random,
a fresh order every epoch (``batch_group_key``; 7,488 windows per size at the defaults: 468
batches of 16 per size). The authors' loader draws the next size at random
per batch and ends the epoch when the first size runs out; here every window is seen once
per epoch. ``--set shuffle=false`` takes the windows in stored order (size by size).
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..extras import import_extra
from ..nets import ConvResNet
from ..precision import float64_scope
from .sim.steppers import AbstractComposition, Parallel, Repeated, single_precision, stack_solvers
from .time_stepper import AbstractTimeStepper, solver_rollout

TRAIN_FACTORS = (0.9, 0.95, 1.0, 1.1, 1.2, 1.3)
TEST_FACTORS = (0.85, 0.93, 1.15, 1.40)


def ks_stepper(factor: float, n: int, dt: float, order: int):
    """exponax's conservative KS stepper on L = 2π·8·factor, undealiased (as the authors)."""
    ex = import_extra("exponax", "pde", "the ks problem")

    return ex.stepper.KuramotoSivashinskyConservative(
        1, 2 * math.pi * 8 * factor, n, dt, order=order, dealiasing_fraction=1.0
    )


class KuramotoSivashinsky(AbstractTimeStepper):
    name: ClassVar[str] = "ks"
    source: ClassVar[str] = "List et al., CMAME 2025"
    extra: ClassVar[str | None] = "pde"  # exponax
    # The correction is ETD1(u) + Δt·f_θ(u) with Δt the ETD *substep* 0.5, as in the authors'
    # code (``diff_ks.dt * net(...)``); an earlier version scaled by the frame step 1, which
    # doubles the network's initial output and Adam's effective step in state space and left
    # the 12-step error several times higher (docs/reproductions/unrolling.md).
    network_scale: ClassVar[float] = 0.5

    composition: AbstractComposition = eqx.field(static=True, default=Parallel(scale=network_scale))
    m: int = eqx.field(static=True, default=3)
    eval_horizon: int = eqx.field(static=True, default=12)
    data_seed: int = eqx.field(static=True, default=0)
    differentiable_solver: bool = eqx.field(static=True, default=True)
    zero_init: bool = eqx.field(static=True, default=False)
    n: int = eqx.field(static=True, default=48)
    dt: float = eqx.field(static=True, default=0.5)
    substeps: int = eqx.field(static=True, default=2)
    width: int = eqx.field(static=True, default=26)
    blocks: int = eqx.field(static=True, default=8)
    n_ics: int = eqx.field(static=True, default=6)
    warmup_frames: int = eqx.field(static=True, default=200)
    frames: int = eqx.field(static=True, default=5000)
    dataset_fraction: float = eqx.field(static=True, default=0.25)
    n_test: int = eqx.field(static=True, default=10)
    long_horizon: int = eqx.field(static=True, default=200)

    training_only_settings: ClassVar[tuple[str, ...]] = ("width", "blocks")

    @property
    def factors(self) -> tuple[float, ...]:
        return TRAIN_FACTORS + TEST_FACTORS

    def reference(self, factor: float):
        return Repeated(ks_stepper(factor, self.n, self.dt, 2), self.substeps)

    def solvers(self):
        # Built in float64 and rounded to float32 (as when x64 was global): the same
        # solver arrays whether or not the caller enabled x64.
        with float64_scope():
            steppers = [Repeated(ks_stepper(f, self.n, self.dt, 1), self.substeps) for f in self.factors]
            return stack_solvers([single_precision(s) for s in steppers])

    def initial_condition(self, key, factor: float):
        """A random perturbation of the first four cosine modes (amplitude ≤ 1)."""
        x = jnp.arange(self.n) / self.n * 2 * jnp.pi
        amp = jax.random.uniform(key, (4,), jnp.float64, -1.0, 1.0)
        phase = jax.random.uniform(jax.random.fold_in(key, 1), (4,), jnp.float64, 0.0, 2 * jnp.pi)
        modes = jnp.arange(1, 5)
        return jnp.sum(amp[:, None] * jnp.cos(modes[:, None] * x[None] + phase[:, None]), axis=0)[None]

    def _simulate(self, factors, n_per, frames, split_seed):
        """(len(factors)·n_per, frames+1, 1, N) trajectories after the warm-up, float32."""
        keys = jax.random.split(jax.random.fold_in(jax.random.key(self.data_seed), split_seed), len(factors) * n_per)
        out = []
        for i, f in enumerate(factors):
            u0 = jnp.stack([self.initial_condition(keys[i * n_per + j], f) for j in range(n_per)])
            reference = self.reference(f)  # built once: an ETDRK stepper's coefficients cost a build each
            u, _ = solver_rollout(reference, u0, self.warmup_frames)
            _, traj = solver_rollout(reference, u, frames)
            out.append(np.concatenate([np.asarray(u)[:, None], np.asarray(traj).swapaxes(0, 1)], axis=1))
        return np.concatenate(out).astype(np.float32)

    def generate(self, split):
        with float64_scope():  # the reference runs in float64 whatever the caller's x64 setting
            return self._generate(split)

    def _generate(self, split):
        if split == "train":
            frames = max(int(self.frames * self.dataset_fraction), self.m + 1)
            factors, n_per, seed = TRAIN_FACTORS, self.n_ics, 0
        elif split == "val":
            frames, factors, n_per, seed = self.eval_horizon, TRAIN_FACTORS, 1, 1
        else:
            frames, factors, n_per, seed = max(self.long_horizon, self.eval_horizon), TEST_FACTORS, self.n_test, 2
        u = self._simulate(factors, n_per, frames, seed)
        offset = 0 if split != "test" else len(TRAIN_FACTORS)
        index = np.repeat(np.arange(len(factors)) + offset, n_per).astype(np.int32)
        cond = np.repeat(np.asarray(factors, np.float32), n_per)
        return {"u": u, "cond": cond, "index": index}

    def make_network(self, key):
        return ConvResNet(1, 2, 1, self.width, self.blocks, key=key)

    def apply(self, network, u, cond):
        return network(self.with_cond_channel(u, cond))

    # The domain size of every training window (its solver index): a shuffled batch holds one
    # size, as the KS code's per-size loaders.
    batch_group_key: ClassVar[str | None] = "index"
