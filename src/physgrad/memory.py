"""Deprecated alias of :mod:`physgrad.engine.memory`, where this module moved; the alias goes in the next
release. Import ``physgrad.engine.memory`` instead."""

import warnings

from .engine import memory as _moved

warnings.warn(
    "physgrad.memory moved to physgrad.engine.memory; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
