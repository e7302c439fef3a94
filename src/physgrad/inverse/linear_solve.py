"""``LinearSolve``: the exact local inverse of linear (affine) physics by a Krylov solve.

For P(x) = A x + b the inverse step solves, matrix-free through lineax,

    A Δ = r,   r = y_t − y,      x̃ = x + Δ,

with A applied as the JVP of ``simulate`` at x (never materialised). ``solver`` is a lineax
iterative solver object, which picks the method; ``tags`` state what it assumes of A
(lineax's operator tags):

- ``lx.CG(...)`` with ``tags=(lx.symmetric_tag, lx.positive_semidefinite_tag)``: A symmetric
  positive (semi)definite; with ``lx.negative_semidefinite_tag``: symmetric negative
  (semi)definite (e.g. a Laplacian or its inverse);
- ``lx.GMRES(...)`` (the default), ``lx.BiCGStab(...)``: any square non-singular A;
- ``lx.Normal(lx.CG(...))``: CG on the normal equations, any full-column-rank A.

The command line's ``krylov=cg|cg_negative|gmres|bicgstab|normal_cg`` names these five
(:mod:`physgrad.harness.objects`); ``LinearSolve("gmres")`` and ``LinearSolve(krylov="gmres")``
still work for one release, with a ``DeprecationWarning``.

Tolerances. The system is solved for ``r / ‖r‖_∞`` (then scaled back: A is linear), so
lineax's test, component by component in the max norm,

    |A u − r̂|_i ≤ atol + rtol · |r̂|_i     and     |u_k − u_{k−1}|_i ≤ atol + rtol · |u_k|_i,

holds ``atol`` relative to the largest residual component: the same setting works
whatever the physics' scale (SIP's point). The tolerances and the iteration limit are
``LinearSolve``'s own fields, which replace those the solver object was built with (one
rule for every solver, resolved for the operand's dtype). Left at None, both are ``ε^{3/4}`` of the
operand's dtype (6.4e-6 in float32, 1.8e-12 in float64): between ``√ε``, the usual
Krylov default, which on a float32 SPD operator of condition 170 left 2 % error in x̃,
and ε, which no solve can promise (64 samples of a 32 × 32 SPD operator in float32: CG
converged on all at conditions 170, 1700 and 1e4, with largest errors in x̃ of 5e-4,
3e-3 and 2e-2 of ‖x̃‖_∞). The previous
fixed ``rtol=1e-6, atol=1e-10`` on the unscaled system failed every sample at condition
170 in float32: components where r is small need |A u − r|_i ≤ 1e-10, below float32's
rounding. Converged = lineax reported success within ``max_steps`` and x̃ finite; SIP
counts the others (``stats["inverse_failures"]``) and warns when most of a batch fails
(:class:`physgrad.inverse.InverseFailureWarning`).

For nonlinear P this is one Newton–Krylov step, not the exact inverse. The error of x̃
grows like the condition number times the tolerance: on ill-conditioned operators run
SIP with ``precision=jnp.float64``. A = ∂P/∂x is applied in forward mode: a reverse-mode-only
simulator (PhiFlow, :mod:`physgrad.problems.sim.phiflow`) gets a one-line ``ValueError`` naming
``GaussNewton``/``LBFGS``.

Under ``precision=jnp.float64`` SIP runs the solve in :func:`physgrad.precision.float64_call`:
``lineax.linear_solve`` is a primitive whose body is traced again when an enclosing
``jax.jit`` is lowered, after a plain float64 scope has closed.

Internal module: the public names are those :mod:`physgrad.inverse` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx

from ..errors import warn_deprecated
from ..jacobian import require_forward_mode
from .base import AbstractInverseSolver, InverseResult, all_finite

# The deprecated string spellings (one release): name -> (solver, tags).
_PSD = (lx.symmetric_tag, lx.positive_semidefinite_tag)
_NSD = (lx.symmetric_tag, lx.negative_semidefinite_tag)
_KRYLOV_NAMES = {
    "cg": (lx.CG(rtol=0.0, atol=0.0, max_steps=1000), _PSD),
    "cg_negative": (lx.CG(rtol=0.0, atol=0.0, max_steps=1000), _NSD),
    "gmres": (lx.GMRES(rtol=0.0, atol=0.0, max_steps=1000), ()),
    "bicgstab": (lx.BiCGStab(rtol=0.0, atol=0.0, max_steps=1000), ()),
    "normal_cg": (lx.Normal(lx.CG(rtol=0.0, atol=0.0, max_steps=1000)), ()),
}


def with_limits(solver, rtol: float, atol: float, max_steps: int):
    """``solver`` (a lineax iterative solver, or ``lx.Normal`` around one) with its
    tolerances and iteration limit replaced."""
    if isinstance(solver, lx.Normal):
        return lx.Normal(with_limits(solver.inner_solver, rtol, atol, max_steps))
    return dataclasses.replace(solver, rtol=rtol, atol=atol, max_steps=max_steps)


def default_tolerance(dtype) -> float:
    """``ε^{3/4}`` of ``dtype`` (of its real part): 6.4e-6 for float32, 1.8e-12 for float64."""
    return float(jnp.finfo(dtype).eps) ** 0.75  # finfo of complex64 is float32's


class LinearSolve(AbstractInverseSolver):
    """x̃ = x + A⁻¹ (y_t − y) for affine P with A = ∂P/∂x, by a lineax Krylov solver.

    Fields:
        solver: the lineax iterative solver (module docstring); default ``lx.GMRES``.
        rtol, atol: lineax's tolerances on the system normalised by ‖y_t − y‖_∞; None:
            ``ε^{3/4}`` of x's dtype. They replace the solver object's own.
        max_steps: the iteration limit (a solve that reaches it is a failure); it replaces
            the solver object's own.
        tags: lineax operator tags, what the solver assumes of A (CG: symmetric and
            positive or negative semi-definite).
    """

    solver: lx.AbstractLinearSolver = eqx.field(static=True)
    rtol: float | None = eqx.field(static=True)
    atol: float | None = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    tags: frozenset = eqx.field(static=True)

    def __init__(
        self,
        solver: lx.AbstractLinearSolver | str | None = None,
        rtol: float | None = None,
        atol: float | None = None,
        max_steps: int = 1000,
        tags: Iterable = (),
        *,
        krylov: str | None = None,
    ):
        if isinstance(solver, str) or krylov is not None:
            name = str(krylov if krylov is not None else solver)
            warn_deprecated(
                f"LinearSolve({name!r}) is deprecated; pass a lineax solver object, e.g. "
                "LinearSolve(lx.GMRES(rtol=0.0, atol=0.0, max_steps=1000))"
            )
            if name not in _KRYLOV_NAMES:
                raise ValueError(f"unknown krylov {name!r}; valid choices: {', '.join(_KRYLOV_NAMES)}")
            solver, tags = _KRYLOV_NAMES[name]
        self.solver = _KRYLOV_NAMES["gmres"][0] if solver is None else solver  # pyright: ignore[reportAttributeAccessIssue]  (a name was mapped above)
        self.rtol, self.atol, self.max_steps = rtol, atol, max_steps
        self.tags = frozenset(tags)

    def __check_init__(self):
        if not isinstance(self.solver, lx.AbstractLinearSolver):
            raise TypeError(f"solver must be a lineax solver (e.g. lx.GMRES(...)), got {self.solver!r}")
        for name, value in (("rtol", self.rtol), ("atol", self.atol)):
            if value is not None and not value >= 0:
                raise ValueError(f"{name} must be >= 0 or None (ε^{3 / 4} of the dtype), got {value}")

    def tolerances(self, dtype) -> tuple[float, float]:
        """``(rtol, atol)`` for operands of ``dtype``: the fields, or ``ε^{3/4}`` where None."""
        default = default_tolerance(dtype)
        return (default if self.rtol is None else self.rtol, default if self.atol is None else self.atol)

    def __call__(self, simulate, x, y, y_target, sample):
        require_forward_mode(
            lambda z: simulate(z, sample), x, what="LinearSolve", source=simulate,
            alternative="use GaussNewton() (reverse-mode Jacobian, dense) or LBFGS() for this simulator",
        )  # fmt: skip

        def apply(v):  # in x's dtype: a float64 simulator on float32 x stays a square operator
            return jax.jvp(lambda z: simulate(z, sample), (x,), (v,))[1].astype(x.dtype)

        operator = lx.FunctionLinearOperator(apply, jax.eval_shape(lambda: x), tags=self.tags)
        solver = with_limits(self.solver, *self.tolerances(x.dtype), self.max_steps)
        residual = (y_target - y).astype(x.dtype)
        # A is linear: solve for the residual scaled to ‖·‖_∞ = 1, so atol is relative.
        scale = jnp.max(jnp.abs(residual))
        scale = jnp.where(scale > 0, scale, jnp.ones_like(scale))

        solution = lx.linear_solve(operator, residual / scale, solver, throw=False)
        unit, result = solution.value, solution.result
        x_new = x + scale * unit
        ok = (result == lx.RESULTS.successful) & all_finite(x_new)
        return InverseResult(x_new, ok)
