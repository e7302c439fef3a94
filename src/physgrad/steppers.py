"""Deprecated alias of :mod:`physgrad.problems.sim.steppers`, where this module moved; the alias goes in the next
release. Import ``physgrad.problems.sim.steppers`` instead."""

import warnings

from .problems.sim import steppers as _moved

warnings.warn(
    "physgrad.steppers moved to physgrad.problems.sim.steppers; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
