"""Optional dependencies: the extras of ``pip install physgrad[...]`` and the one-line error
of a method or problem whose extra is missing.

The core install trains every problem and method except these:

- ``kfac`` (kfac-jax, which brings distrax and TensorFlow Probability): the ``kfac`` method;
- ``pde`` (exponax): the time-stepper problems ``ks``, ``kolmogorov`` and ``advection_1d``
  (their reference and coarse solvers);
- ``phiflow`` (PhiFlow and PhiML): PhiFlow simulators (:mod:`physgrad.problems.sim.phiflow`);
- ``tensorboard`` (tensorboardX): :class:`physgrad.engine.tensorboard.TensorBoard`, a callback of
  :func:`physgrad.fit` that writes TensorBoard event files.

``all`` installs every one of them. Nothing here imports an optional package: whether one is
installed is asked of the import system (``importlib.util.find_spec``), and the packages are
imported where they are used, on first use.
"""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

from .errors import ConfigError

# extra -> the top-level modules it provides
EXTRAS: dict[str, tuple[str, ...]] = {
    "kfac": ("kfac_jax",),
    "pde": ("exponax",),
    "phiflow": ("phi", "phiml"),
    "tensorboard": ("tensorboardX",),
}

# registered methods that need an extra (problems declare theirs as the class variable ``extra``)
METHOD_EXTRAS: dict[str, str] = {"kfac": "kfac", "kfac_hig": "kfac"}


class MissingExtra(ConfigError, ImportError):
    """A method or problem used without its optional dependencies; the message is one line
    naming the extra. A :class:`~physgrad.errors.ConfigError` (the command line prints it and
    exits with status 2) and an :class:`ImportError`."""


def installed(extra: str) -> bool:
    """Whether every module of ``extra`` can be imported (without importing it)."""
    for module in EXTRAS[extra]:
        try:
            if importlib.util.find_spec(module) is None:
                return False
        except (ImportError, ValueError):
            return False
    return True


def message(what: str, extra: str) -> str:
    return f"{what} needs the {extra} extra: pip install 'physgrad[{extra}]'"


def require(extra: str | None, what: str) -> None:
    """Raise :class:`MissingExtra` if ``extra`` (None: nothing needed) is not installed."""
    if extra is not None and not installed(extra):
        raise MissingExtra(message(what, extra))


def import_extra(module: str, extra: str, what: str) -> ModuleType:
    """``import module``, or :class:`MissingExtra` naming ``extra`` when it is not installed
    (an installed package that fails to import raises its own error)."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        if installed(extra):
            raise
        raise MissingExtra(message(what, extra)) from error


def method_extra(name: str) -> str | None:
    """The extra a registered method needs (None: the core install has it)."""
    return METHOD_EXTRAS.get(name)


def missing_note(extra: str | None) -> str:
    """``""``, or a short note for listings when ``extra`` is not installed."""
    if extra is None or installed(extra):
        return ""
    return f"[needs the {extra} extra, not installed: pip install 'physgrad[{extra}]']"


__all__ = ["EXTRAS", "METHOD_EXTRAS", "MissingExtra", "import_extra", "installed", "message", "method_extra",
           "missing_note", "require"]  # fmt: skip
