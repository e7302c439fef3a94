"""Explicit time integrators shared by the ODE problems."""

from __future__ import annotations

from collections.abc import Callable

import jax
from jaxtyping import Array, PyTree

RHS = Callable[[Array, Array], Array]  # (state, control) -> d state / dt


def rk4_step(rhs: RHS, state: Array, control: Array, dt: float) -> Array:
    """One classic fourth-order Runge–Kutta step with a piecewise-constant control.

        k1 = f(s, u), k2 = f(s + dt/2 k1, u), k3 = f(s + dt/2 k2, u), k4 = f(s + dt k3, u)
        s' = s + dt/6 (k1 + 2 k2 + 2 k3 + k4)

    The same control ``u`` enters all four stages, as in the HIG oscillator code.
    """
    k1 = rhs(state, control)
    k2 = rhs(state + 0.5 * dt * k1, control)
    k3 = rhs(state + 0.5 * dt * k2, control)
    k4 = rhs(state + dt * k3, control)
    return state + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def integrate(
    step: Callable[[RHS, Array, Array, float], Array], rhs: RHS, state: Array, controls: PyTree, dt: float
) -> Array:
    """Apply ``step`` once per leading entry of ``controls`` (lax.scan); return the final state."""

    def body(s, u):
        return step(rhs, s, u, dt), None

    final, _ = jax.lax.scan(body, state, controls)
    return final
