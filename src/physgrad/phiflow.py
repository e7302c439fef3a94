"""Deprecated alias of :mod:`physgrad.problems.sim.phiflow`, where this module moved; the alias goes in the next
release. Import ``physgrad.problems.sim.phiflow`` instead."""

import warnings

from .problems.sim import phiflow as _moved

warnings.warn(
    "physgrad.phiflow moved to physgrad.problems.sim.phiflow; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
