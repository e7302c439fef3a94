"""Deprecated alias of :mod:`physgrad.engine.rundir`, where this module moved; the alias goes in the next
release. Import ``physgrad.engine.rundir`` instead."""

import warnings

from .engine import rundir as _moved

warnings.warn(
    "physgrad.rundir moved to physgrad.engine.rundir; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
