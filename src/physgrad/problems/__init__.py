"""Benchmark problems, one file each, and the ``PROBLEMS`` registry (name → class)."""

from .base import AbstractProblem
from .hig_toy import HigToy
from .linear_oscillators import LinearOscillators
from .oscillators import Oscillators
from .poisson_hig import PoissonHig
from .quantum_dipole import QuantumDipole

PROBLEMS: dict[str, type[AbstractProblem]] = {
    cls.name: cls for cls in (HigToy, Oscillators, QuantumDipole, PoissonHig, LinearOscillators)
}

__all__ = ["PROBLEMS", "AbstractProblem", "HigToy", "LinearOscillators", "Oscillators", "PoissonHig", "QuantumDipole"]
