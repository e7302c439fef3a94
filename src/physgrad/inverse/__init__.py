"""Local inverse solvers for SIP, one small module each.

Each solver maps one sample's prediction x and a y-space target y_t to x̃ ≈ P⁻¹(y_t; x)
and reports convergence (:class:`InverseResult`). Pass one to :func:`physgrad.sip`
(``solver=GaussNewton(rcond=1e-5)``); ``Analytic()`` without a function uses the
problem's own inverse. The command line builds them by name (:mod:`physgrad.harness.registry`).
"""

from .analytic import Analytic
from .base import AbstractInverseSolver, InverseFailureWarning, InverseResult
from .gauss_newton import GaussNewton
from .lbfgs import LBFGS
from .linear_solve import LinearSolve, with_limits
from .saddle_free_newton import SaddleFreeNewton, saddle_free_newton_step

__all__ = [
    "LBFGS",
    "AbstractInverseSolver",
    "Analytic",
    "GaussNewton",
    "InverseFailureWarning",
    "InverseResult",
    "LinearSolve",
    "SaddleFreeNewton",
    "saddle_free_newton_step",
    "with_limits",
]


def __getattr__(name):
    # KRYLOV (the command line's Krylov names) moved to the harness: one release of warning.
    if name == "KRYLOV":
        import warnings

        from .linear_solve import _KRYLOV_NAMES

        warnings.warn(
            "physgrad.inverse.KRYLOV is deprecated: LinearSolve takes a lineax solver object "
            "(the command line's names are physgrad.harness.objects.KRYLOV)",
            DeprecationWarning,
            stacklevel=2,
        )
        return tuple(_KRYLOV_NAMES)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
