"""The SIP paper's incompressible Navier–Stokes inverse problem: find the initial velocity.

Source: Holl, Koltun, Thuerey, *Scale-invariant Learning by Physics Inversion*, NeurIPS
2022, §5 and Fig. 7 (their ``fluid/train_fluid.py`` and ``fluid/fluid_base.py``).

Physics (:mod:`physgrad.problems.sim.fluid`): a passive marker m is carried by an inviscid,
incompressible, energy-conserving flow on a 64 × 64 periodic staggered grid over a
128 × 128 domain (Δx = 2), 8 steps of Δt = 0.25 (T = 2). Given the marker at the start and
at the end, (m₀, m_T*), the network predicts the initial velocity v₀ (cell centred, 2
channels); the simulator staggers and projects it and runs the 8 steps to m_T.

Data, per sample (the authors' ``generate_example``):

- m₀: PhiFlow noise (scale 10 in physical units, i.e. 5 cells) times a 56 × 56 box at a
  position U[32, 96]², thresholded so that the top fraction f ~ U[0.05, 0.15] of the grid's
  cells is 1, times the box;
- v₀* = (64 − COM(m₀)) / T  (the drift that brings the marker's centre of mass to the
  centre) + a Gaussian swirl s · exp(−|d|²/2σ²) · (−d_y, d_x) about (64, 64), σ = 20,
  s ~ U[−2, 2]  + 0.1 × vector noise;
- m_T* = the simulation of (m₀, v₀*) by the JAX fluid (also when ``simulator=PhiFlowFluid()``:
  pair it with ``limiter=CellLimiter()`` for data that PhiFlow's step reproduces).

Loss (DP / Adam): the authors' ``frequency_loss(m_T − m_T*, n=1, frequency_falloff=80,
ignore_mean=True)``: with d = m_T − m_T* − mean, D̂ = FFT(d) and k in cycles per cell,

    L = Σ_k max(|D̂_k| · exp(−½ |k|² · 80²), √1e-5)  −  N √1e-5,

an L1 norm of Gaussian-weighted Fourier amplitudes that sees only the lowest 1–2 modes
(physgrad subtracts PhiFlow's floor N√1e-5 = 12.95 on 64², so L = 0 at the target).
Metric: ``v0_l1`` = Σ_cells |v₀ − v₀*| (vector norm per cell, summed: the authors'
``gt_v0_l1``) and ``v0_mae`` its per-cell mean.

SIP's local inverse (``inverse``) is the authors' ``estimate_v0``, an approximate inverse
with a solution prior (uniform drift + Gaussian swirl):

1. the swirl strength of the prediction, s₀ = mean_cells cross(−v₀, x − c) / N_σ with
   N_σ = mean_cells exp(−|d|²/2σ²)|d|² (= 120.52 at the paper's sizes; the authors
   hard-coded 120.5), which is exactly s for a pure swirl;
2. forward simulation from (m₀, v₀), recording the centre of mass after each step;
3. the drift u = (64 − COM(m₀)) / T from the data;
4. time reversal: from m_T (the y-space target) with the negated final velocity, 8
   steps, recording centres of mass; per step a vorticity error
   cross(COM_fwd − COM_rev, COM_rev − p_swirl), with the swirl centre p_swirl moved by
   the drift; (as the authors: p_swirl = 64 + (64 − COM(m₀)) / T · (7 − i) in reverse
   step i, and 64 + (64 − COM(m₀)) at the end);
5. x̃ = u + swirl(s₀ + 10⁻³ · mean of the errors).

x̃ lies in the (uniform + swirl) family, so the 0.1 noise part of v₀* is never recovered.

Differences from the authors' code (all documented in docs/reproductions/sip.md):

- the projection is the exact FFT solve (``projection=CGProjection()`` for the authors' CG
  with absolute tolerance 1e-4, warm started);
- MacCormack's limiter clamps a staggered velocity component to its own faces' 2 × 2
  neighbourhood; ``limiter=CellLimiter()`` uses PhiFlow 3.4's (as if cell centred), and
  ``simulator=PhiFlowFluid()`` runs the same step written with PhiFlow itself
  (:mod:`physgrad.problems.sim.phiflow`; reverse-mode only, CG at 1e-4);
- the reference simulation runs on the same staggered grid as the predictions (the
  authors ran the ground truth on a centred grid without an initial projection), and the
  metric compares the centred v₀ directly;
- the fill fraction is drawn per sample (the authors: one per batch); the data are a
  fixed set of ``n_train`` samples made from the run's seed and cached on disk (the
  authors drew a fresh batch each step);
- the network. The authors' PhiFlow ``u_net`` (5 levels, 16 filters, ReLU) normalises
  over the batch after every conv (batch norm). physgrad's networks are per-sample
  functions (the methods vmap ``network_output`` over the batch without an axis name; HIG
  needs per-sample Jacobians, SIP per-sample targets, evaluation runs in chunks), so batch
  statistics are not available. The plain BN-less U-Net with PyTorch's initialisation
  (``activation=jax.nn.relu, weight_standardisation=False``) dies here: its ReLUs die within
  ~25 SIP or supervised steps at lr 5e-3 and the output collapses to a constant. The
  default is therefore per sample and does not die: leaky ReLU (slope 0.01) and
  weight-standardised 3×3 convs (He gain, He-normal kernels, zero biases; scale-invariant
  in the kernels as under batch norm; :class:`physgrad.nets.UNet`), the same 48,994
  parameters. In 60–100-step runs (batch 16, lr 5e-3) no channel died and supervised, DP
  and SIP training all moved v₀ towards the truth (docs/reproductions/sip.md).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..errors import warn_deprecated
from ..nets import UNet
from .base import AbstractProblem
from .poisson_hig import phiflow_noise
from .sim import fluid
from .sim.cache import cached_arrays
from .sim.phiflow import PhiFlowFluid

DATA_VERSION = 1  # bump when the generator changes, so cached data are regenerated

# The settings' objects with the words they were spelt with before they were objects: the
# deprecated string spellings (one release; the command line's own names are
# physgrad.harness.objects.STRATEGIES), and the data cache's keys, so that data cached
# then stay valid.
_SPELLINGS: dict[str, dict[str, Any]] = {
    "projection": {"fft": fluid.FFTProjection(), "cg": fluid.CGProjection()},
    "limiter": {"faces": fluid.FaceLimiter(), "cells": fluid.CellLimiter()},
    "simulator": {"jax": fluid.JaxFluid(), "phiflow": PhiFlowFluid()},
    "activation": {"relu": jax.nn.relu, "leaky_relu": jax.nn.leaky_relu},
}


def _spelling(setting: str, name: str) -> str:
    """How the library spells the object of a deprecated name (for the warning)."""
    return f"jax.nn.{name}" if setting == "activation" else repr(_SPELLINGS[setting][name])


def _spelt(setting: str, accepts: Callable[[Any], bool], expected: str) -> Callable[[Any], Any]:
    """The converter of ``setting``: a value it ``accepts`` passes, a deprecated name becomes
    its object with a ``DeprecationWarning``; anything else is refused in one line."""

    def convert(value):
        if not isinstance(value, str):
            if not accepts(value):
                raise ValueError(f"NavierStokes' {setting} must be {expected}, got {value!r}")
            return value
        if value not in _SPELLINGS[setting]:
            raise ValueError(f"unknown {setting} {value!r}; valid choices: {', '.join(_SPELLINGS[setting])}")
        warn_deprecated(
            f"NavierStokes({setting}={value!r}) is deprecated; pass the object, {setting}={_spelling(setting, value)}"
        )
        return _SPELLINGS[setting][value]

    return convert


def _strategy(setting: str, kind: type, default: Any, expected: str) -> Any:
    """A static strategy field of class ``kind`` (default ``default``), converted by
    :func:`_spelt` (a deprecated name becomes its object)."""
    return eqx.field(static=True, default=default, converter=_spelt(setting, lambda v: isinstance(v, kind), expected))


def _cache_word(setting: str, value: Any) -> Any:
    """``value``'s word in the data cache's key: its earlier spelling, else its repr."""
    for word, known in _SPELLINGS.get(setting, {}).items():
        if type(known) is type(value) and known == value:
            return word
    return value if isinstance(value, int | float | str | bool) else repr(value)


def box_fraction(n: int, dx: float, lower, upper, dtype=jnp.float32):
    """Fraction of each cell covered by the axis-aligned box [lower, upper] (physical units)."""
    edges = jnp.arange(n, dtype=dtype) * dx

    def overlap(lo, hi):
        return jnp.clip(jnp.minimum(edges + dx, hi) - jnp.maximum(edges, lo), 0.0, dx) / dx

    return overlap(lower[0], upper[0])[:, None] * overlap(lower[1], upper[1])[None, :]


def threshold_top(values, fraction):
    """1 on the ``round(N · fraction)`` largest values of a field, else 0 (PhiFlow's
    ``discretize``: the top ``N − round(N (1 − fraction))`` by rank)."""
    flat = values.reshape(-1)
    n = flat.size
    rank = jnp.argsort(jnp.argsort(flat))  # 0 = smallest
    first = jnp.round(n * (1 - fraction))
    return (rank >= first).astype(values.dtype).reshape(values.shape)


def frequency_loss(d, falloff: float = 80.0, threshold: float = 1e-5):
    """PhiFlow's ``frequency_loss(d, n=1, frequency_falloff, ignore_mean=True)`` of one field,
    minus its floor N·√threshold (so that it is 0 at the target; the gradient is PhiFlow's)."""
    n = d.shape[0]
    k = jnp.fft.fftfreq(n).astype(d.dtype)
    weight = jnp.exp(-0.5 * (k[:, None] ** 2 + k[None, :] ** 2) * falloff**2)
    amplitude = jnp.abs(jnp.fft.fft2(d - jnp.mean(d)) * weight)
    floor = jnp.sqrt(jnp.asarray(threshold, d.dtype))
    # The floor comes off each term, not the sum: in float32 the sum of N floors minus N·floor
    # leaves rounding of order N·ε·floor, so the loss at the target would not be exactly 0.
    return jnp.sum(jnp.sqrt(jnp.maximum(amplitude**2, threshold)) - floor)


class NavierStokes(AbstractProblem):
    """Predict the initial velocity of a 2-D incompressible flow from a marker's start and end."""

    resolution: int = eqx.field(static=True, default=64)
    size: float = eqx.field(static=True, default=128.0)
    steps: int = eqx.field(static=True, default=8)
    time: float = eqx.field(static=True, default=2.0)
    box: float = eqx.field(static=True, default=56.0)
    swirl_sigma: float = eqx.field(static=True, default=20.0)
    swirl_strength: float = eqx.field(static=True, default=2.0)
    fluctuations: float = eqx.field(static=True, default=0.1)
    noise_scale: float = eqx.field(static=True, default=10.0)
    falloff: float = eqx.field(static=True, default=80.0)
    # the pressure solve (FFTProjection(), exact; CGProjection(), the authors'), MacCormack's
    # limiter (FaceLimiter(); CellLimiter(), PhiFlow's), physgrad.problems.sim.fluid, and the
    # code that runs the training's steps (fluid.JaxFluid(); phiflow.PhiFlowFluid())
    projection: fluid.AbstractPressureSolver = _strategy(
        "projection", fluid.AbstractPressureSolver, fluid.FFTProjection(),
        "FFTProjection() or CGProjection() (physgrad.problems.sim.fluid)",
    )  # fmt: skip
    limiter: fluid.AbstractLimiter = _strategy(
        "limiter", fluid.AbstractLimiter, fluid.FaceLimiter(),
        "FaceLimiter() or CellLimiter() (physgrad.problems.sim.fluid)",
    )  # fmt: skip
    simulator: fluid.AbstractFluid = _strategy(
        "simulator", fluid.AbstractFluid, fluid.JaxFluid(),
        "JaxFluid() (physgrad.problems.sim.fluid) or PhiFlowFluid() (physgrad.problems.sim.phiflow)",
    )  # fmt: skip
    levels: int = eqx.field(static=True, default=5)
    filters: int = eqx.field(static=True, default=16)
    activation: Callable[[jax.Array], jax.Array] = eqx.field(
        static=True,
        default=jax.nn.leaky_relu,
        converter=_spelt("activation", callable, "a function (e.g. jax.nn.leaky_relu)"),
    )
    weight_standardisation: bool = eqx.field(static=True, default=True)
    n_train: int = eqx.field(static=True, default=4096)
    n_test: int = eqx.field(static=True, default=64)

    name: ClassVar[str] = "navier_stokes"
    # The authors simulate fresh examples every step; here each split is simulated once and
    # cached on disk (a 4,096-example training set takes minutes to simulate), so training
    # cycles over it: fresh_samples=true draws a new set every epoch at that cost.
    source: ClassVar[str] = "Holl et al., NeurIPS 2022, Fig. 7"
    default_batch_size: ClassVar[int] = 64

    def __check_init__(self):
        if self.resolution % 2 ** (self.levels - 1):
            raise ValueError(f"resolution must be divisible by 2^(levels - 1) = {2 ** (self.levels - 1)}")

    # --- the simulator ---------------------------------------------------------------------
    @property
    def dx(self) -> float:
        return self.size / self.resolution

    @property
    def dt(self) -> float:
        return self.time / self.steps

    @property
    def centre(self) -> float:
        return self.size / 2

    def pressure_solver(self) -> fluid.AbstractPressureSolver:
        return self.projection

    def initial_velocity(self, v0):
        """The centred prediction on the faces, made divergence free (the authors'
        ``make_incompressible(StaggeredGrid(v0))``)."""
        return fluid.project(fluid.stagger(v0), self.dx, self.pressure_solver())[0]

    def reference_rollout(self, marker, velocity):
        """The JAX fluid, which makes the data whatever ``simulator`` trains on."""
        return fluid.rollout(marker, velocity, self.steps, self.dt, self.dx, self.pressure_solver(), self.limiter)

    def rollout(self, marker, velocity):
        """``(m_T, v_T, markers)`` after ``steps`` steps from a staggered, divergence-free velocity."""
        return self.simulator.rollout(
            marker, velocity, self.steps, self.dt, self.dx, self.pressure_solver(), self.limiter
        )

    def swirl(self, strength):
        """The Gaussian swirl about the domain centre, cell centred (2, n, n)."""
        c = self.centre
        return fluid.gaussian_swirl(self.resolution, self.dx, (c, c), strength, self.swirl_sigma)

    def swirl_norm(self) -> jax.Array:
        """N_σ: ``mean_cells cross(−swirl, x − c)`` of a unit-strength swirl."""
        return self.vorticity(self.swirl(1.0), normalise=False)

    def vorticity(self, v0, normalise: bool = True):
        """The swirl strength seen in a centred velocity (step 1 of the inverse)."""
        d = fluid.sample_points(self.resolution, self.dx, fluid.CENTRED, v0.dtype) - self.centre
        value = jnp.mean(fluid.cross(-v0, d))
        return value / self.swirl_norm() if normalise else value

    # --- data ------------------------------------------------------------------------------
    def noise(self, key, count: int, channels: int = 1):
        """PhiFlow noise fields ``(count, channels, n, n)``; its scale is physical, i.e.
        ``noise_scale / Δx`` cells (drawn outside jit: the draw scopes float64 itself)."""
        n = self.resolution
        fields = phiflow_noise(key, (count * channels, n, n), scale=self.noise_scale / self.dx)
        return fields.reshape(count, channels, n, n)

    def example(self, key, noise, fluctuations):
        """One sample ``{"m0", "mT", "v0"}`` (module docstring) from its key and noise fields
        (n, n) and (2, n, n)."""
        n, dx = self.resolution, self.dx
        k_pos, k_fill, k_swirl = jax.random.split(key, 3)
        pos = jax.random.uniform(k_pos, (2,), jnp.float32) * (self.size / 2) + self.size / 4
        box = box_fraction(n, dx, pos - self.box / 2, pos + self.box / 2)
        fill = jax.random.uniform(k_fill, (), jnp.float32) * 0.1 + 0.05
        m0 = threshold_top(noise * box, fill) * box
        drift = (self.centre - fluid.centre_of_mass(m0, dx)) / self.time
        strength = (jax.random.uniform(k_swirl, (), jnp.float32) - 0.5) * 2 * self.swirl_strength
        v0 = drift[:, None, None] + self.swirl(strength) + self.fluctuations * fluctuations
        m_t, _, _ = self.reference_rollout(m0, self.initial_velocity(v0))
        return {"m0": m0, "mT": m_t, "v0": v0}

    def examples(self, key, count: int, chunk: int = 256) -> dict[str, np.ndarray]:
        """``count`` samples, made ``chunk`` at a time."""
        build = jax.jit(jax.vmap(self.example))
        parts = []
        for start in range(0, count, chunk):
            k = jax.random.fold_in(key, start)
            k_examples, k_noise, k_fluct = jax.random.split(k, 3)
            size = min(chunk, count - start)
            noise, fluct = self.noise(k_noise, size)[:, 0], self.noise(k_fluct, size, 2)
            parts.append(build(jax.random.split(k_examples, size), noise, fluct))
        return {name: np.concatenate([np.asarray(p[name]) for p in parts]) for name in parts[0]}

    def make_data(self, key):
        # settings that leave the data unchanged (the network's; the data always use the JAX fluid)
        skip = ("levels", "filters", "activation", "weight_standardisation", "simulator")

        def draw(split, k, count):
            settings = {f: _cache_word(f, getattr(self, f)) for f in self.settings() if f not in skip}
            cache_key = {"problem": self.name, "split": split, "count": count, "version": DATA_VERSION,
                         "key": np.asarray(jax.random.key_data(k)).tolist(), **settings}  # fmt: skip
            data = cached_arrays(f"{self.name}-{split}", cache_key, lambda: self.examples(k, count))
            return {name: jnp.asarray(v) for name, v in data.items()}

        k_train, k_test = jax.random.split(key)
        return {"train": draw("train", k_train, self.n_train), "test": draw("test", k_test, self.n_test)}

    # --- what the methods see --------------------------------------------------------------
    def make_network(self, key):
        return UNet(2, 2, levels=self.levels, filters=self.filters, key=key, activation=self.activation,
                    weight_standardisation=self.weight_standardisation)  # fmt: skip

    def network_output(self, network, sample):
        return network(jnp.stack([sample["m0"], sample["mT"]]))

    def simulate(self, x, sample):
        return self.rollout(sample["m0"], self.initial_velocity(x))[0]

    def loss(self, y, sample):
        return frequency_loss(y - sample["mT"], self.falloff)

    def target(self, sample):
        return sample["mT"]

    def inverse(self, x, y, y_target, sample):
        """The authors' ``estimate_v0`` (module docstring, steps 1–5); ``y_target`` is m_T."""
        dx, c, steps = self.dx, self.centre, self.steps
        com = lambda m: fluid.centre_of_mass(m, dx)  # noqa: E731
        s0 = self.vorticity(x)
        _, v_t, markers = self.rollout(sample["m0"], self.initial_velocity(x))
        com0 = com(sample["m0"])
        com_fwd = jnp.concatenate([com0[None], jax.vmap(com)(markers)])  # (steps + 1, 2)
        drift = (c - com0) / self.time
        com_rev_end = com(y_target)
        errors = [fluid.cross(com_fwd[-1] - com_rev_end, com_rev_end - (c + (c - com0)))]
        _, _, rev_markers = self.rollout(y_target, -v_t)
        com_rev = jax.vmap(com)(rev_markers)  # after reverse step i = 0 .. steps − 1
        i = jnp.arange(steps, dtype=x.dtype)
        swirl_pos = c + (c - com0)[None, :] / self.time * (steps - 1 - i)[:, None]  # the authors' expression
        matching = com_fwd[::-1][1:]  # forward COM after step steps − 1 − i
        errors = jnp.concatenate([jnp.stack(errors), fluid.cross((matching - com_rev).T, (com_rev - swirl_pos).T)])
        strength = s0 + 1e-3 * jnp.mean(errors)
        return (drift[:, None, None] + self.swirl(strength)).astype(x.dtype)

    def metrics(self, x, y, sample):
        err = jnp.sqrt(jnp.sum((x - sample["v0"]) ** 2, axis=0))
        return {"v0_l1": jnp.sum(err), "v0_mae": jnp.mean(err)}
