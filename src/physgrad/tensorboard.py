"""Deprecated alias of :mod:`physgrad.engine.tensorboard`, where this module moved; the alias goes in the next
release. Import ``physgrad.engine.tensorboard`` instead."""

import warnings

from .engine import tensorboard as _moved

warnings.warn(
    "physgrad.tensorboard moved to physgrad.engine.tensorboard; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
