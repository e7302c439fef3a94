"""Benchmark problems, one file each, and the ``PROBLEMS`` registry (name → class)."""

from .base import AbstractProblem
from .hig_toy import HigToy
from .oscillators import Oscillators

PROBLEMS: dict[str, type[AbstractProblem]] = {cls.name: cls for cls in (Oscillators, HigToy)}

__all__ = ["PROBLEMS", "AbstractProblem", "HigToy", "Oscillators"]
