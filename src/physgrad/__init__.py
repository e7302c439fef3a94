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

from . import acceptance, cpu, distributed, inverse, routes, transforms
from ._fit import fit  # the engine's fit with the BLAS/LAPACK pools limited (threads=1)
from .cpu import threads
from .engine import Budget, Callback, FitResult, Phase, TrainSettings, TrainState
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

__version__ = "0.1.0"

__all__ = [
    "MLP",
    "AbstractMethod",
    "AbstractProblem",
    "AbstractRule",
    "Budget",
    "Callback",
    "ConfigError",
    "Epochs",
    "Estimator",
    "FitResult",
    "Method",
    "Objective",
    "Phase",
    "Seconds",
    "Stepper",
    "Steps",
    "System",
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
