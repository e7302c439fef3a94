"""``LinearSolve``: the exact local inverse of linear (affine) physics by a Krylov solve.

For P(x) = A x + b the inverse step solves, matrix-free through lineax,

    A Δ = y_t − y,      x̃ = x + Δ,

with A applied as the JVP of ``simulate`` at x (never materialised). ``krylov`` picks the
method and states the assumption on A:

- ``"cg"``: A symmetric positive (semi)definite;  ``"cg_negative"``: symmetric negative
  (semi)definite (e.g. a Laplacian or its inverse);
- ``"gmres"``, ``"bicgstab"``: any square non-singular A;
- ``"normal_cg"``: CG on the normal equations, any full-column-rank A.

Converged = lineax reported success within ``max_steps`` at ``rtol``/``atol`` and x̃ finite.
For nonlinear P this is one Newton–Krylov step, not the exact inverse. Krylov methods in
float32 stall on ill-conditioned operators (the 64×64 Poisson P = ∇⁻², condition ≈ 1,700,
never reaches rtol 1e-4 in float32 but converges in ≤ 300 steps in float64): run SIP with
``precision=float64`` there; failures are reported either way. A = ∂P/∂x is applied in
forward mode: a reverse-mode-only simulator (PhiFlow, :mod:`physgrad.phiflow`) gets a
one-line ``ValueError`` naming ``GaussNewton``/``LBFGS``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import lineax as lx

from ..jacobian import require_forward_mode
from .base import AbstractInverseSolver, InverseResult, all_finite

KRYLOV = ("cg", "cg_negative", "gmres", "bicgstab", "normal_cg")


def _krylov(name, rtol, atol, max_steps):
    if name in ("cg", "cg_negative"):
        return lx.CG(rtol=rtol, atol=atol, max_steps=max_steps)
    if name == "normal_cg":
        return lx.Normal(lx.CG(rtol=rtol, atol=atol, max_steps=max_steps))
    if name == "gmres":
        return lx.GMRES(rtol=rtol, atol=atol, max_steps=max_steps)
    return lx.BiCGStab(rtol=rtol, atol=atol, max_steps=max_steps)


class LinearSolve(AbstractInverseSolver):
    """x̃ = x + A⁻¹ (y_t − y) for affine P with A = ∂P/∂x, by a lineax Krylov solver."""

    krylov: str = eqx.field(static=True, default="gmres")
    rtol: float = eqx.field(static=True, default=1e-6)
    atol: float = eqx.field(static=True, default=1e-10)
    max_steps: int = eqx.field(static=True, default=1000)

    def __check_init__(self):
        if self.krylov not in KRYLOV:
            raise ValueError(f"unknown krylov {self.krylov!r}; valid choices: {', '.join(KRYLOV)}")

    def __call__(self, simulate, x, y, y_target, sample):
        require_forward_mode(
            lambda z: simulate(z, sample), x, what="LinearSolve", source=simulate,
            alternative="use GaussNewton() (reverse-mode Jacobian, dense) or LBFGS() for this simulator",
        )  # fmt: skip

        def apply(v):  # in x's dtype: a float64 simulator on float32 x stays a square operator
            return jax.jvp(lambda z: simulate(z, sample), (x,), (v,))[1].astype(x.dtype)

        tags = {
            "cg": (lx.symmetric_tag, lx.positive_semidefinite_tag),
            "cg_negative": (lx.symmetric_tag, lx.negative_semidefinite_tag),
        }.get(self.krylov, ())
        operator = lx.FunctionLinearOperator(apply, jax.eval_shape(lambda: x), tags=frozenset(tags))
        solver = _krylov(self.krylov, self.rtol, self.atol, self.max_steps)
        solution = lx.linear_solve(operator, (y_target - y).astype(x.dtype), solver, throw=False)
        x_new = x + solution.value
        ok = (solution.result == lx.RESULTS.successful) & all_finite(x_new)
        return InverseResult(x_new, ok)
