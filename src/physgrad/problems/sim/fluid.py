"""Inviscid incompressible 2-D flow on a periodic staggered grid, in pure JAX.

Source: the fluid of Holl, Koltun & Thuerey, *Scale-invariant Learning by Physics
Inversion*, NeurIPS 2022, §5 / Fig. 7 (their ``fluid/fluid_base.py``, written with
PhiFlow's ``advect.mac_cormack`` and ``fluid.make_incompressible``). One step
(:func:`step`) is, with time step Δt on an n × n grid of cell size Δx:

1. **MacCormack self-advection** of the staggered velocity v;
2. **pressure projection** ``v ← v − ∇p`` with ``∇²p = ∇·v`` (periodic, mean divergence
   removed), so that the discrete divergence vanishes;
3. **energy rescale** ``v ← v · √(E₀ / E)`` with E = Σ (u² + v²) over all faces, so the
   mean kinetic energy of the step's input is kept exactly (the flow is inviscid; the
   rescale removes the numerical dissipation of advection and projection);
4. **MacCormack advection** of a passive marker m (cell centred) by the new velocity.

Layout (PhiFlow's): axis 0 is x, axis 1 is y; a cell-centred field ``c[i, j]`` lives at
((i + ½)Δx, (j + ½)Δx); the staggered velocity is an array ``(2, n, n)`` whose x-component
``u[i, j]`` lives on the lower x-face of cell (i, j), at (iΔx, (j + ½)Δx), and whose
y-component ``v[i, j]`` on the lower y-face, at ((i + ½)Δx, jΔx).

MacCormack (PhiFlow's, Selle et al. 2008): with the field's own sample points p and the
velocity interpolated there, v_p,

    φ̂ = φ(p − Δt v_p),   φ̌ = φ̂(p + Δt v_p),   φ⁺ = φ̂ + ½ (φ − φ̌),

clamped to the range of the 2 × 2 values of φ that surround the back-traced point
p − Δt v_p (no new extrema). All sampling is bilinear with periodic wrap. The limiter is an
object: :class:`CellLimiter` reproduces PhiFlow 3.4, whose limiter picks a staggered
component's 2 × 2 values as if the component were cell centred (half a cell off along its
own axis); the default :class:`FaceLimiter` uses the component's own neighbours. The two
differ only where the limiter is active.

Projection: the discrete divergence ``(u[i+1,j] − u[i,j] + v[i,j+1] − v[i,j]) / Δx`` and
the face gradient ``(p[i,j] − p[i−1,j]) / Δx`` compose to the 5-point Laplacian, so
:class:`FFTProjection` — which divides by its exact eigenvalues
``λ_k = (2 cos(2πk_x/n) + 2 cos(2πk_y/n) − 4) / Δx²`` (mean mode 0) — leaves a divergence at
rounding level. The authors project with PhiFlow's CG (absolute tolerance 1e-4, warm
started with the previous step's pressure); :class:`CGProjection` does the same with
lineax's CG. The FFT solve is exact and cheaper on a periodic grid, so it is the default.
Everything is differentiable in reverse and forward mode (lineax differentiates its solve
by solving again).
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from ...errors import warn_deprecated

CENTRED = (0.5, 0.5)  # sample offset of a cell-centred field, in cells
FACE_X = (0.0, 0.5)  # the x-component of a staggered velocity
FACE_Y = (0.5, 0.0)  # the y-component
STAGGERED = (FACE_X, FACE_Y)


# --- grids and interpolation -------------------------------------------------------------
def sample_points(n: int, dx: float, offset: tuple[float, float], dtype=jnp.float32) -> Float[Array, "2 n n"]:
    """Physical positions ``((i + o_x)Δx, (j + o_y)Δx)`` of a field's samples."""
    i = jnp.arange(n, dtype=dtype)
    x = (i[:, None] + offset[0]) * dx
    y = (i[None, :] + offset[1]) * dx
    return jnp.stack(jnp.broadcast_arrays(x, y))


# The F821 noqa comments below: ruff reads jaxtyping's variadic shape "2 *p" as the expression `2 * p`
def bilinear(values: Float[Array, "n n"], offset, points: Float[Array, "2 *p"], dx: float):  # noqa: F821
    """(interpolated values ``*p``, the 2 × 2 surrounding values ``(4, *p)``) of a periodic
    field sampled at ``offset`` cells, at physical ``points``."""
    n = values.shape[0]
    q = [points[a] / dx - offset[a] for a in range(2)]
    base = [jnp.floor(qa) for qa in q]
    w = [qa - ba for qa, ba in zip(q, base)]
    i0, j0 = (b.astype(jnp.int32) % n for b in base)
    i1, j1 = (i0 + 1) % n, (j0 + 1) % n
    # one gather from the flat field (XLA's CPU gather is much faster on one flat index)
    index = jnp.stack([i0 * n + j0, i1 * n + j0, i0 * n + j1, i1 * n + j1])
    corners = jnp.take(values.reshape(-1), index, unique_indices=False, indices_are_sorted=False)
    wx, wy = w
    weights = jnp.stack([(1 - wx) * (1 - wy), wx * (1 - wy), (1 - wx) * wy, wx * wy])
    return jnp.sum(weights * corners, axis=0), corners


def sample_velocity(velocity: Float[Array, "2 n n"], points, dx: float) -> Float[Array, "2 *p"]:  # noqa: F821
    """The staggered velocity, each component interpolated from its own faces, at ``points``."""
    return jnp.stack([bilinear(velocity[a], STAGGERED[a], points, dx)[0] for a in range(2)])


def stagger(centred: Float[Array, "2 n n"]) -> Float[Array, "2 n n"]:
    """A cell-centred vector field sampled on the faces (mean of the two cells per face)."""
    return jnp.stack([0.5 * (centred[0] + jnp.roll(centred[0], 1, 0)), 0.5 * (centred[1] + jnp.roll(centred[1], 1, 1))])


def centre(velocity: Float[Array, "2 n n"]) -> Float[Array, "2 n n"]:
    """A staggered velocity at the cell centres (mean of each cell's two faces)."""
    return jnp.stack(
        [0.5 * (velocity[0] + jnp.roll(velocity[0], -1, 0)), 0.5 * (velocity[1] + jnp.roll(velocity[1], -1, 1))]
    )


# --- projection --------------------------------------------------------------------------
def divergence(velocity: Float[Array, "2 n n"], dx: float) -> Float[Array, "n n"]:
    """Cell-centred divergence of a staggered velocity."""
    u, v = velocity
    return (jnp.roll(u, -1, 0) - u + jnp.roll(v, -1, 1) - v) / dx


def face_gradient(p: Float[Array, "n n"], dx: float) -> Float[Array, "2 n n"]:
    """The gradient of a cell-centred field on the faces."""
    return jnp.stack([p - jnp.roll(p, 1, 0), p - jnp.roll(p, 1, 1)]) / dx


def laplace(p: Float[Array, "n n"], dx: float) -> Float[Array, "n n"]:
    """The periodic 5-point Laplacian, ``divergence ∘ face_gradient``."""
    return (jnp.roll(p, 1, 0) + jnp.roll(p, -1, 0) + jnp.roll(p, 1, 1) + jnp.roll(p, -1, 1) - 4 * p) / dx**2


class AbstractPressureSolver(eqx.Module):
    """``solver(rhs, dx, guess) -> p`` with ``∇²p = rhs`` (rhs of zero mean) on the periodic grid."""

    @abc.abstractmethod
    def __call__(self, rhs: Float[Array, "n n"], dx: float, guess: Float[Array, "n n"]) -> Float[Array, "n n"]: ...


class FFTProjection(AbstractPressureSolver):
    """Exact: ``p̂_k = r̂_k / λ_k`` with the 5-point Laplacian's eigenvalues, ``p̂_0 = 0``."""

    def __call__(self, rhs, dx, guess):
        n = rhs.shape[0]
        c = jnp.cos(2 * jnp.pi * jnp.fft.fftfreq(n)).astype(rhs.real.dtype)
        eig = (2 * c[:, None] + 2 * c[None, :] - 4) / dx**2
        eig = eig.at[0, 0].set(1.0)  # the mean mode: p̂_0 = 0 below
        p_hat = jnp.fft.fft2(rhs) / eig
        return jnp.real(jnp.fft.ifft2(p_hat.at[0, 0].set(0.0))).astype(rhs.dtype)


class CGProjection(AbstractPressureSolver):
    """Conjugate gradients (lineax) on −∇², warm-started from ``guess``; stops when the
    max-norm residual is below ``atol`` (the authors: PhiFlow ``Solve('CG', 0, 1e-4)``)."""

    atol: float = eqx.field(static=True, default=1e-4)
    max_steps: int = eqx.field(static=True, default=2000)

    def __call__(self, rhs, dx, guess):
        operator = lx.FunctionLinearOperator(
            lambda p: -laplace(p, dx), jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), lx.positive_semidefinite_tag
        )
        # the warm start only changes where CG starts, not the solution: no derivative through it
        options = {"y0": jax.lax.stop_gradient(guess)}
        solution = lx.linear_solve(
            operator, -rhs, lx.CG(rtol=0.0, atol=self.atol, max_steps=self.max_steps), options=options, throw=False
        )
        return solution.value


def project(velocity, dx: float, solver: AbstractPressureSolver = FFTProjection(), guess=None):
    """``(v − ∇p, p)`` with ``∇²p = ∇·v − mean(∇·v)``: the divergence-free part and the pressure."""
    div = divergence(velocity, dx)
    div = div - jnp.mean(div)  # PhiFlow's balance: a periodic Laplacian only reaches zero-mean data
    p = solver(div, dx, jnp.zeros_like(div) if guess is None else guess)
    return velocity - face_gradient(p, dx), p


# --- advection ---------------------------------------------------------------------------
def mac_cormack(values: Float[Array, "n n"], offset, velocity, dt: float, dx: float, clamp: bool = True,
                limiter_offset=None):  # fmt: skip
    """One MacCormack step of a periodic field sampled at ``offset`` (module docstring); the
    clamp's 2 × 2 neighbourhood is found as for a field at ``limiter_offset`` (default: ``offset``)."""
    points = sample_points(values.shape[0], dx, offset, values.dtype)
    v = sample_velocity(velocity, points, dx)
    semi, corners = bilinear(values, offset, points - dt * v, dx)
    back, _ = bilinear(semi, offset, points + dt * v, dx)
    new = semi + 0.5 * (values - back)
    if clamp:
        if limiter_offset is not None and tuple(limiter_offset) != tuple(offset):
            _, corners = bilinear(values, limiter_offset, points - dt * v, dx)
        new = jnp.clip(new, jnp.min(corners, axis=0), jnp.max(corners, axis=0))
    return new


class AbstractLimiter(eqx.Module):
    """Where MacCormack's clamp finds a staggered velocity component's 2 × 2 neighbourhood
    (module docstring): ``offset(axis)``, the sample offset (in cells) the component's
    values are taken at for the clamp."""

    @abc.abstractmethod
    def offset(self, axis: int) -> tuple[float, float]: ...


class FaceLimiter(AbstractLimiter):
    """The component's own faces (the default)."""

    def offset(self, axis):
        return STAGGERED[axis]


class CellLimiter(AbstractLimiter):
    """PhiFlow 3.4's: as if the component were cell centred, half a cell off along its own axis."""

    def offset(self, axis):
        return CENTRED


# The deprecated string spellings of a limiter (one release); the command line's own names are
# physgrad.harness.objects.STRATEGIES.
_LIMITER_NAMES = {"faces": FaceLimiter(), "cells": CellLimiter()}


def limiter_of(limiter: AbstractLimiter | str) -> AbstractLimiter:
    """``limiter`` itself, or the object of a deprecated name (``"faces"``, ``"cells"``) with a
    ``DeprecationWarning``; a one-line ``ValueError`` for anything else."""
    if isinstance(limiter, AbstractLimiter):
        return limiter
    if isinstance(limiter, str) and limiter in _LIMITER_NAMES:
        warn_deprecated(
            f"limiter={limiter!r} is deprecated; pass FaceLimiter() or CellLimiter() (physgrad.problems.sim.fluid)"
        )
        return _LIMITER_NAMES[limiter]
    raise ValueError(f"limiter must be FaceLimiter() or CellLimiter() (physgrad.problems.sim.fluid), got {limiter!r}")


def advect_velocity(velocity, dt: float, dx: float, clamp: bool = True, limiter: AbstractLimiter | str = FaceLimiter()):
    """MacCormack self-advection of a staggered velocity, component by component
    (``limiter``: the clamp's neighbourhood, module docstring)."""
    limiter = limiter_of(limiter)
    return jnp.stack(
        [mac_cormack(velocity[a], STAGGERED[a], velocity, dt, dx, clamp, limiter.offset(a)) for a in range(2)]
    )


def energy(velocity) -> Float[Array, ""]:
    """Mean squared face velocity ``(Σu² + Σv²) / (2n²)`` (PhiFlow's ``field.mean(v ** 2)``)."""
    return jnp.mean(velocity**2)


def rescale_energy(velocity, target_energy):
    """``v · √(E₀ / E)``, and 0 where E = 0 (as the authors, no NaN)."""
    e = energy(velocity)
    safe = jnp.where(e > 0, e, 1.0)
    return velocity * jnp.where(e > 0, jnp.sqrt(target_energy / safe), 0.0)


def step(marker, velocity, pressure, dt: float, dx: float, solver: AbstractPressureSolver = FFTProjection(),
         limiter: AbstractLimiter | str = FaceLimiter()):  # fmt: skip
    """One energy-conserving inviscid step: ``(marker, velocity, pressure) -> same``.

    ``marker`` (n, n) cell centred, ``velocity`` (2, n, n) staggered and divergence free,
    ``pressure`` (n, n) the previous step's (the CG solver's warm start)."""
    dtypes = marker.dtype, velocity.dtype, pressure.dtype
    e0 = energy(velocity)
    velocity = advect_velocity(velocity, dt, dx, limiter=limiter)  # first: the marker moves with the returned velocity
    velocity, pressure = project(velocity, dx, solver, pressure)
    velocity = rescale_energy(velocity, e0)
    marker = mac_cormack(marker, CENTRED, velocity, dt, dx)
    return tuple(a.astype(d) for a, d in zip((marker, velocity, pressure), dtypes))


def rollout(marker, velocity, steps: int, dt: float, dx: float, solver: AbstractPressureSolver = FFTProjection(),
            limiter: AbstractLimiter | str = FaceLimiter()):  # fmt: skip
    """``steps`` steps from a divergence-free staggered velocity, pressure guess 0.

    Returns the final ``(marker, velocity)`` and the markers after every step
    ``(steps, n, n)``."""
    limiter = limiter_of(limiter)  # once, not per step
    one_step = lambda m, v, p: step(m, v, p, dt, dx, solver, limiter)  # noqa: E731
    return unroll(one_step, marker, velocity, jnp.zeros_like(velocity[0]), steps)


class AbstractFluid(eqx.Module):
    """Which code runs the steps of a rollout: ``fluid.rollout(marker, velocity, steps, dt,
    dx, solver, limiter) -> (m_T, v_T, markers)``, as :func:`rollout`."""

    @abc.abstractmethod
    def rollout(self, marker, velocity, steps: int, dt: float, dx: float, solver: AbstractPressureSolver,
                limiter: AbstractLimiter) -> Any: ...  # fmt: skip


class JaxFluid(AbstractFluid):
    """This module's fluid (:func:`rollout`) with the given pressure solver and limiter."""

    def rollout(self, marker, velocity, steps, dt, dx, solver, limiter):
        return rollout(marker, velocity, steps, dt, dx, solver, limiter)


def unroll(one_step, marker, velocity, pressure, steps: int):
    """``steps`` applications of ``one_step(marker, velocity, pressure) -> same`` in one
    ``lax.scan``: the final ``(marker, velocity)`` and the markers after every step. Shared
    by :func:`rollout` and the PhiFlow step (:func:`physgrad.problems.sim.phiflow.rollout`)."""

    def body(carry, _):
        carry = one_step(*carry)
        return carry, carry[0]

    (marker, velocity, _), markers = jax.lax.scan(body, (marker, velocity, pressure), None, length=steps)
    return marker, velocity, markers


def centre_of_mass(marker: Float[Array, "n n"], dx: float) -> Float[Array, "2"]:
    """``Σ m x / Σ m`` over the cell centres (PhiFlow's ``field.center_of_mass``; not periodic)."""
    points = sample_points(marker.shape[0], dx, CENTRED, marker.dtype)
    return jnp.sum(points * marker, axis=(1, 2)) / jnp.sum(marker)


def cross(a: Float[Array, "2 *p"], b: Float[Array, "2 *p"]):  # noqa: F821
    """The 2-D cross product ``a_x b_y − a_y b_x``."""
    return a[0] * b[1] - a[1] * b[0]


def gaussian_swirl(n: int, dx: float, location, strength, sigma: float, dtype=jnp.float32) -> Float[Array, "2 n n"]:
    """PhiFlow's ``AngularVelocity`` with a Gaussian falloff, at the cell centres:
    ``v(x) = s · exp(−|d|² / 2σ²) · (−d_y, d_x)``, ``d = x − location``."""
    d = sample_points(n, dx, CENTRED, dtype) - jnp.asarray(location, dtype)[:, None, None]
    falloff = jnp.exp(-0.5 * jnp.sum(d**2, axis=0) / sigma**2)
    return strength * falloff * jnp.stack([-d[1], d[0]])
