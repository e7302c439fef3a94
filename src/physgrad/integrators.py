"""Deprecated alias of :mod:`physgrad.problems.sim.integrators`, where this module moved; the alias goes in the next
release. Import ``physgrad.problems.sim.integrators`` instead."""

import warnings

from .problems.sim import integrators as _moved

warnings.warn(
    "physgrad.integrators moved to physgrad.problems.sim.integrators; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
