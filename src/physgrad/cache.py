"""Deprecated alias of :mod:`physgrad.problems.sim.cache`, where this module moved; the alias goes in the next
release. Import ``physgrad.problems.sim.cache`` instead."""

import warnings

from .problems.sim import cache as _moved

warnings.warn(
    "physgrad.cache moved to physgrad.problems.sim.cache; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
