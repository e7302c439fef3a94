"""Local inverse solvers for SIP, one small module each, and the ``INVERSE_SOLVERS`` registry.

Each solver maps one sample's prediction x and a y-space target y_t to x̃ ≈ P⁻¹(y_t; x)
and reports convergence (:class:`InverseResult`). The SIP method builds a solver from its
flat settings (``rcond``, ``max_loss_change``, ``max_steps``, ``tol``, ``krylov``) with
:func:`make_solver`; ``analytic`` uses the problem's own ``inverse``.
"""

from .analytic import Analytic
from .base import AbstractInverseSolver, InverseResult
from .gauss_newton import GaussNewton
from .lbfgs import LBFGS
from .linear_solve import KRYLOV, LinearSolve
from .saddle_free_newton import SaddleFreeNewton, saddle_free_newton_step

INVERSE_SOLVERS = ("auto", "analytic", "gauss_newton", "saddle_free_newton", "lbfgs", "linear_solve")


def make_solver(name: str, *, analytic=None, rcond=1e-5, max_loss_change=0.2, max_steps=100, tol=1e-6, krylov="gmres"):
    """Build a registered solver; ``auto`` is ``analytic`` when the problem has one, else GN.

    ``analytic`` is the problem's inverse function (or None). ``max_loss_change <= 0``
    disables the saddle-free Newton limit.
    """
    if name not in INVERSE_SOLVERS:
        raise ValueError(f"unknown inverse solver {name!r}; valid choices: {', '.join(INVERSE_SOLVERS)}")
    if name == "auto":
        name = "analytic" if analytic is not None else "gauss_newton"
    if name == "analytic":
        if analytic is None:
            others = ", ".join(s for s in INVERSE_SOLVERS if s not in ("auto", "analytic"))
            raise ValueError(f"this problem has no analytic inverse; valid choices: {others}")
        return Analytic(analytic)
    if name == "gauss_newton":
        return GaussNewton(rcond)
    if name == "saddle_free_newton":
        return SaddleFreeNewton(max_loss_change if max_loss_change > 0 else None)
    if name == "lbfgs":
        return LBFGS(max_steps, tol)
    return LinearSolve(krylov, rtol=tol, max_steps=max_steps)


__all__ = [
    "INVERSE_SOLVERS",
    "KRYLOV",
    "LBFGS",
    "AbstractInverseSolver",
    "Analytic",
    "GaussNewton",
    "InverseResult",
    "LinearSolve",
    "SaddleFreeNewton",
    "make_solver",
    "saddle_free_newton_step",
]
