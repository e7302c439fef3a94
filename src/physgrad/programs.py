"""Deprecated alias of :mod:`physgrad.engine.programs`, where this module moved; the alias goes in the next
release. Import ``physgrad.engine.programs`` instead."""

import warnings

from .engine import programs as _moved

warnings.warn(
    "physgrad.programs moved to physgrad.engine.programs; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
