"""2D Kolmogorov flow: a conv ResNet corrects a coarse spectral solver against a 4× finer one.

List et al., CMAME 2025, the Kolmogorov-flow experiment (their KOLM: PISO on 32², a
128² reference, Re ∈ {300, 400, 500, 700, 800, 900} for training, 600 and 1000 for testing,
Re/1000 as an input channel, sequential-with-bypass correction, Δt = 0.02 per network step).
Here in vorticity form with exponax ``KolmogorovFlowVorticity`` on [0, 2π)²:

    ω_t + (v·∇)ω = ν Δω + λ ω + f,   ν = 1/Re,  f = sin-forcing of wavenumber 6,  λ = −0.1 (drag),

reference on ``refinement``·n points with ``refinement``² substeps per network step of Δt
(0.0025 at 128², stable up to Re = 1000), downsampled spectrally to n (exponax
``map_between_resolutions``); coarse solver: one ETDRK2 step of Δt on n points. The coarse
error is spatial under-resolution (about 4 % per step, 20 % after 6 steps at n = 32,
Re = 1000). Initial vorticity: white noise of std 0.1, then ``warmup_frames`` dropped.

Sizes: n = 32 with a 128² reference is the paper's; ``--set n=32 frames=…`` fits a short
run on 2 CPU cores (the reference costs ≈ 0.4 ms per 128² step). The network is the 2D conv
ResNet (``width`` × ``blocks``, inputs ω and Re/1000); the paper's feature-list ResNets
(32k–1.08M parameters) are not reproduced layer by layer.
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
from .sim.steppers import AbstractComposition, Bypass, Repeated, single_precision, stack_solvers
from .time_stepper import AbstractTimeStepper, solver_rollout

TRAIN_RE = (300, 400, 500, 700, 800, 900)
TEST_RE = (600, 1000)


class Kolmogorov(AbstractTimeStepper):
    name: ClassVar[str] = "kolmogorov"
    source: ClassVar[str] = "List et al., CMAME 2025"
    extra: ClassVar[str | None] = "pde"  # exponax
    default_eval_samples: ClassVar[int] = 64

    composition: AbstractComposition = eqx.field(static=True, default=Bypass(scale=1.0))
    m: int = eqx.field(static=True, default=4)
    eval_horizon: int = eqx.field(static=True, default=12)
    data_seed: int = eqx.field(static=True, default=0)
    differentiable_solver: bool = eqx.field(static=True, default=True)
    zero_init: bool = eqx.field(static=True, default=False)
    n: int = eqx.field(static=True, default=32)
    refinement: int = eqx.field(static=True, default=4)
    dt: float = eqx.field(static=True, default=0.02)
    forcing_mode: int = eqx.field(static=True, default=6)
    drag: float = eqx.field(static=True, default=-0.1)
    warmup_frames: int = eqx.field(static=True, default=200)
    frames: int = eqx.field(static=True, default=600)
    n_test: int = eqx.field(static=True, default=3)
    long_horizon: int = eqx.field(static=True, default=100)
    width: int = eqx.field(static=True, default=24)
    blocks: int = eqx.field(static=True, default=4)

    training_only_settings: ClassVar[tuple[str, ...]] = ("width", "blocks")

    @property
    def reynolds(self) -> tuple[int, ...]:
        return TRAIN_RE + TEST_RE

    def _stepper(self, re: float, n: int, dt: float):
        ex = import_extra("exponax", "pde", "the kolmogorov problem")

        return ex.stepper.KolmogorovFlowVorticity(
            2, 2 * math.pi, n, dt, diffusivity=1.0 / re, injection_mode=self.forcing_mode, drag=self.drag
        )

    def solvers(self):
        # Built in float64 and rounded to float32 (as when x64 was global): the same
        # solver arrays whether or not the caller enabled x64.
        with float64_scope():
            steppers = [Repeated(self._stepper(re, self.n, self.dt)) for re in self.reynolds]
            return stack_solvers([single_precision(s) for s in steppers])

    def generate(self, split):
        with float64_scope():  # the reference runs in float64 whatever the caller's x64 setting
            return self._generate(split)

    def _generate(self, split):
        ex = import_extra("exponax", "pde", "the kolmogorov problem")

        fine, sub = self.n * self.refinement, self.refinement**2
        if split == "train":
            res, per, frames, seed = TRAIN_RE, 1, self.frames, 0
        elif split == "val":
            res, per, frames, seed = TRAIN_RE[::2], 1, self.eval_horizon, 1
        else:
            res, per, frames, seed = TEST_RE, self.n_test, max(self.long_horizon, self.eval_horizon), 2
        key = jax.random.fold_in(jax.random.key(self.data_seed), seed)
        out, cond, index = [], [], []
        for i, re in enumerate(res):
            ref = Repeated(self._stepper(re, fine, self.dt / sub), sub)
            w0 = 0.1 * jax.random.normal(jax.random.fold_in(key, i), (per, 1, fine, fine), jnp.float64)
            w, _ = solver_rollout(ref, w0, self.warmup_frames)
            _, traj = solver_rollout(ref, w, frames)
            traj = jnp.concatenate([w[None], traj])  # (T+1, per, 1, fine, fine)
            coarse = jax.vmap(jax.vmap(lambda v: ex.map_between_resolutions(v, self.n)))(traj)
            out.append(np.asarray(coarse).swapaxes(0, 1))
            cond += [re / 1000.0] * per
            index += [self.reynolds.index(re)] * per
        return {"u": np.concatenate(out).astype(np.float32), "cond": np.asarray(cond, np.float32),
                "index": np.asarray(index, np.int32)}  # fmt: skip

    def make_network(self, key):
        return ConvResNet(2, 2, 1, self.width, self.blocks, key=key, lift_activation=True)

    def apply(self, network, u, cond):
        return network(self.with_cond_channel(u, cond))
