"""physgrad: improved update rules for training neural networks through physics simulators.

Importing physgrad enables JAX's float64 support, which the Gram route of the
half-inverse needs; every problem and network still runs in float32 unless a problem's
``dtype`` setting says otherwise.
"""

import jax

jax.config.update("jax_enable_x64", True)

from .config import Budget, ConfigError, RunConfig, make_config  # noqa: E402
from . import distributed, inverse  # noqa: E402
from .half_inverse import half_inverse  # noqa: E402
from .half_inverse_large import blockgram_half_inverse, lanczos_half_inverse  # noqa: E402
from .jacobian import stacked_jacobian  # noqa: E402
from .methods import METHODS, AbstractMethod, Objective  # noqa: E402
from .nets import MLP, UNet, parameter_count  # noqa: E402
from .problems import PROBLEMS, AbstractProblem  # noqa: E402
from .train import build, load_network, train  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "METHODS",
    "MLP",
    "PROBLEMS",
    "AbstractMethod",
    "AbstractProblem",
    "Budget",
    "ConfigError",
    "Objective",
    "RunConfig",
    "UNet",
    "blockgram_half_inverse",
    "build",
    "distributed",
    "half_inverse",
    "inverse",
    "lanczos_half_inverse",
    "load_network",
    "make_config",
    "parameter_count",
    "stacked_jacobian",
    "train",
]
