"""Benchmark problems, one file each (the command line's names for them: :mod:`physgrad.harness.registry`)."""

from .advection_1d import Advection1d
from .base import AbstractProblem
from .cartpole import CartPole
from .closed_loop import AbstractClosedLoop, ClosedLoopProblem
from .exp_inverse import ExpInverse
from .guidance import Guidance
from .heat import Heat
from .hig_toy import HigToy
from .kolmogorov import Kolmogorov
from .ks import KuramotoSivashinsky
from .linear_oscillators import LinearOscillators
from .navier_stokes import NavierStokes
from .oscillators import AbstractOscillators, Oscillators
from .poisson import Poisson
from .poisson_hig import PoissonHig
from .quantum_control import QuantumControl
from .quantum_dipole import QuantumDipole
from .sine import Sine
from .time_stepper import AbstractTimeStepper, TimeStepperProblem
from .toy2d import Toy2d

__all__ = [
    "AbstractTimeStepper",
    "TimeStepperProblem",
    "KuramotoSivashinsky",
    "Kolmogorov",
    "Advection1d",
    "AbstractProblem",
    "CartPole",
    "AbstractClosedLoop",
    "ClosedLoopProblem",
    "Guidance",
    "QuantumControl",
    "ExpInverse",
    "Heat",
    "Poisson",
    "Sine",
    "Toy2d",
    "HigToy",
    "AbstractOscillators",
    "LinearOscillators",
    "NavierStokes",
    "Oscillators",
    "PoissonHig",
    "QuantumDipole",
]
