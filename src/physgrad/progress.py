"""Deprecated alias of :mod:`physgrad.engine.progress`, where this module moved; the alias goes in the next
release. Import ``physgrad.engine.progress`` instead."""

import warnings

from .engine import progress as _moved

warnings.warn(
    "physgrad.progress moved to physgrad.engine.progress; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
