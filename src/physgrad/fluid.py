"""Deprecated alias of :mod:`physgrad.problems.sim.fluid`, where this module moved; the alias goes in the next
release. Import ``physgrad.problems.sim.fluid`` instead."""

import warnings

from .problems.sim import fluid as _moved

warnings.warn(
    "physgrad.fluid moved to physgrad.problems.sim.fluid; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
