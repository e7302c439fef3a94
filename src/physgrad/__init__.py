"""physgrad: improved update rules for training neural networks through physics simulators.

The update rules are direction estimators that compose with any optax chain::

    estimate = physgrad.hig(predict, loss)                 # (params, batch) -> (direction, stats)
    updates, opt_state = optimizer.update(estimate(params, batch)[0], opt_state, params)

and :func:`fit` trains a problem object with a method object into a run directory.
Importing physgrad changes nothing in JAX's configuration: float64 is scoped to the
computations that need it (the Gram route's eigendecomposition, float64 problems), and
no thread pool: ``with physgrad.threads(1):`` limits the BLAS/LAPACK pools around a loop
(:mod:`physgrad.cpu`); :func:`fit` does it for its own duration (``threads=1``, as the
``physgrad`` command line does for its runs; ``threads=None`` leaves the pools alone).
"""

import importlib as _importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# The public names are imported on first use (PEP 562), so that ``physgrad --version`` and
# ``physgrad --help`` answer without importing JAX (the command line imports this package
# first). The imports below are the same names for static readers (type checkers, the API
# reference); _PUBLIC says where each lives at run time, and a test keeps the two in step.
if TYPE_CHECKING:
    from . import acceptance, cpu, distributed, inverse, routes, transforms
    from ._fit import fit  # the engine's fit with the BLAS/LAPACK pools limited (threads=1)
    from .cpu import threads
    from .engine import AbstractSplit, Budget, Callback, FitResult, HoldOut, Phase, TestSplit, TrainSettings, TrainState
    from .engine.types import Epochs, Seconds, Steps
    from .errors import ConfigError
    from .harness.train import load_network
    from .harness.tune import tune
    from .jacobian import stacked_jacobian
    from .methods import (
        AbstractMethod,
        AbstractRule,
        Estimator,
        Method,
        Objective,
        Stepper,
        bptt,
        dp,
        gauss_newton,
        hig,
        kronecker_hig,
        levenberg_marquardt,
        newton,
        sip,
        stabilised_bptt,
        unrolled,
    )
    from .nets import MLP, UNet, parameter_count
    from .problems import AbstractProblem
    from .rollout import System, closed_loop
    from .routes import blockgram_half_inverse, half_inverse, lanczos_half_inverse


# name -> the module it comes from ("" : a submodule of physgrad)
_PUBLIC: dict[str, str] = {
    **dict.fromkeys(("acceptance", "cpu", "distributed", "inverse", "routes", "transforms"), ""),
    "fit": "._fit",
    "threads": ".cpu",
    **dict.fromkeys(
        (
            "AbstractSplit",
            "Budget",
            "Callback",
            "FitResult",
            "HoldOut",
            "Phase",
            "TestSplit",
            "TrainSettings",
            "TrainState",
        ),
        ".engine",
    ),
    **dict.fromkeys(("Epochs", "Seconds", "Steps"), ".engine.types"),
    "ConfigError": ".errors",
    "load_network": ".harness.train",
    "tune": ".harness.tune",
    "stacked_jacobian": ".jacobian",
    **dict.fromkeys(
        (
            "AbstractMethod",
            "AbstractRule",
            "Estimator",
            "Method",
            "Objective",
            "Stepper",
            "bptt",
            "dp",
            "gauss_newton",
            "hig",
            "kronecker_hig",
            "levenberg_marquardt",
            "newton",
            "sip",
            "stabilised_bptt",
            "unrolled",
        ),
        ".methods",
    ),
    **dict.fromkeys(("MLP", "UNet", "parameter_count"), ".nets"),
    "AbstractProblem": ".problems",
    **dict.fromkeys(("System", "closed_loop"), ".rollout"),
    **dict.fromkeys(("blockgram_half_inverse", "half_inverse", "lanczos_half_inverse"), ".routes"),
}


def __getattr__(name: str) -> object:
    """A public name, imported on first use (then kept in the module's namespace); any other
    submodule (``physgrad.engine``) as ``import physgrad.engine`` gives it."""
    where = _PUBLIC.get(name)
    if where is None:
        if name.startswith("__"):
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
        try:
            return _importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:
            if e.name != f"{__name__}.{name}":  # the submodule exists but one of its imports does not
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
    value = (
        _importlib.import_module(f"{__name__}.{name}")
        if not where
        else getattr(_importlib.import_module(where, __name__), name)
    )
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


__all__ = [
    "MLP",
    "AbstractMethod",
    "AbstractProblem",
    "AbstractRule",
    "AbstractSplit",
    "Budget",
    "Callback",
    "ConfigError",
    "Epochs",
    "Estimator",
    "FitResult",
    "HoldOut",
    "Method",
    "Objective",
    "Phase",
    "Seconds",
    "Stepper",
    "Steps",
    "System",
    "TestSplit",
    "TrainSettings",
    "TrainState",
    "UNet",
    "acceptance",
    "blockgram_half_inverse",
    "bptt",
    "closed_loop",
    "cpu",
    "distributed",
    "dp",
    "fit",
    "gauss_newton",
    "half_inverse",
    "hig",
    "inverse",
    "kronecker_hig",
    "lanczos_half_inverse",
    "levenberg_marquardt",
    "load_network",
    "newton",
    "parameter_count",
    "routes",
    "sip",
    "stabilised_bptt",
    "stacked_jacobian",
    "threads",
    "transforms",
    "tune",
    "unrolled",
]
