"""What :func:`physgrad.fit` tells the caller while it runs: :class:`Callback` and the
checked list of them (:class:`Callbacks`).

A callback is a :class:`Callback` (override :meth:`~Callback.on_eval`,
:meth:`~Callback.on_checkpoint` or both) or a plain function ``f(step, metrics)``, which is
called as ``on_eval``. They are called in the training process between chunks of steps,
outside ``jax.jit``, with host numbers (Keras's ``on_epoch_end(epoch, logs)`` and
Lightning's hooks work the same way); their time is not training time.

Why not inside the step: a callback is for logging, plotting and stopping by hand, which
need Python values, and the steps between evaluations run as one compiled program.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ..errors import ConfigError


class Callback:
    """Hooks :func:`physgrad.fit` calls; each does nothing unless overridden.

    - ``on_eval(step, metrics)``: after every evaluation (the first at step 0, the last at
      the end of the budget); ``step`` is the number of steps taken, ``metrics`` a dict of
      floats: ``time`` (training seconds so far) and every metric of that evaluation, as
      named in :attr:`physgrad.engine.FitResult.history` (``train_loss``, ``test_loss``,
      ``train_step_<statistic>``, ...).
    - ``on_checkpoint(step, path)``: after every checkpoint, with the ``checkpoint/``
      directory just committed (only where :func:`physgrad.fit` writes a run directory: in
      memory, ``out=None``, there are none; in a multi-process run only process 0 writes).

    An exception raised by a callback stops the run and propagates out of ``fit`` (the run
    directory keeps its last checkpoint, for ``resume=True``).
    """

    def on_eval(self, step: int, metrics: dict[str, float]) -> None:
        """After an evaluation at ``step``."""

    def on_checkpoint(self, step: int, path: Path) -> None:
        """After a checkpoint of ``step`` was committed to ``path``."""


class _Function(Callback):
    """A plain function ``f(step, metrics)`` as a callback's ``on_eval``."""

    def __init__(self, function: Callable[[int, dict[str, float]], Any]):
        self.function = function

    def on_eval(self, step, metrics):
        self.function(step, metrics)

    def __repr__(self):
        return f"on_eval={self.function!r}"


class Callbacks:
    """The caller's callbacks, checked, called in the order given."""

    def __init__(self, callbacks: Sequence[Callback | Callable] | None = None):
        self.callbacks: list[Callback] = [_as_callback(c, i) for i, c in enumerate(_listed(callbacks))]

    def on_eval(self, step: int, metrics: dict[str, float]) -> None:
        for callback in self.callbacks:
            callback.on_eval(step, dict(metrics))  # a copy each: a callback may change its own

    def on_checkpoint(self, step: int, path: Path) -> None:
        for callback in self.callbacks:
            callback.on_checkpoint(step, path)


def _listed(callbacks) -> list:
    """``callbacks`` as a list; a single callback or anything else is refused in one line."""
    if callbacks is None:
        return []
    if isinstance(callbacks, (list, tuple)):
        return list(callbacks)
    hint = f"; wrap it in a list: callbacks=[{callbacks!r}]" if _usable(callbacks) else ""
    raise ConfigError(f"callbacks must be a list of physgrad.Callback objects or functions f(step, metrics), "
                      f"got {type(callbacks).__name__}{hint}")  # fmt: skip


def _usable(obj) -> bool:
    return isinstance(obj, Callback) or hasattr(obj, "on_eval") or hasattr(obj, "on_checkpoint") or callable(obj)


def _as_callback(obj, position: int) -> Callback:
    """A :class:`Callback`, an object with ``on_eval``/``on_checkpoint`` methods (used as
    it is, missing hooks doing nothing), or a function (its ``on_eval``)."""
    if isinstance(obj, Callback):
        return obj
    if hasattr(obj, "on_eval") or hasattr(obj, "on_checkpoint"):
        return _Duck(obj)
    if callable(obj):
        return _Function(obj)
    raise ConfigError(f"callbacks[{position}] must be a physgrad.Callback or a function f(step, metrics), "
                      f"got {obj!r} ({type(obj).__name__})")  # fmt: skip


class _Duck(Callback):
    """An object with some of a callback's methods (not a :class:`Callback` subclass)."""

    def __init__(self, obj):
        self.obj = obj

    def on_eval(self, step, metrics):
        if hasattr(self.obj, "on_eval"):
            self.obj.on_eval(step, metrics)

    def on_checkpoint(self, step, path):
        if hasattr(self.obj, "on_checkpoint"):
            self.obj.on_checkpoint(step, path)
