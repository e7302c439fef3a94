"""Deprecated alias of :mod:`physgrad.engine.prdp`, where this module moved; the alias goes in the next
release. Import ``physgrad.engine.prdp`` instead."""

import warnings

from .engine import prdp as _moved

warnings.warn(
    "physgrad.prdp moved to physgrad.engine.prdp; the old name goes in the next release",
    DeprecationWarning,
    stacklevel=2,
)


def __getattr__(name):
    return getattr(_moved, name)
