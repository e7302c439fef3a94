"""Benchmark problems, one file each (the command line's names for them: :mod:`physgrad.registry`)."""

from .base import AbstractProblem
from .cartpole import CartPole
from .closed_loop import ClosedLoopProblem
from .guidance import Guidance
from .quantum_control import QuantumControl
from .exp_inverse import ExpInverse
from .heat import Heat
from .poisson import Poisson
from .sine import Sine
from .toy2d import Toy2d
from .hig_toy import HigToy
from .linear_oscillators import LinearOscillators
from .navier_stokes import NavierStokes
from .oscillators import Oscillators
from .poisson_hig import PoissonHig
from .quantum_dipole import QuantumDipole
from .time_stepper import TimeStepperProblem
from .ks import KuramotoSivashinsky
from .kolmogorov import Kolmogorov
from .advection_1d import Advection1d

__all__ = ["TimeStepperProblem", "KuramotoSivashinsky", "Kolmogorov", "Advection1d", "AbstractProblem", "CartPole", "ClosedLoopProblem", "Guidance", "QuantumControl", "ExpInverse", "Heat", "Poisson", "Sine", "Toy2d", "HigToy", "LinearOscillators", "NavierStokes", "Oscillators", "PoissonHig", "QuantumDipole"]
