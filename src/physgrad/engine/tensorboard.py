"""A :class:`~physgrad.Callback` that writes every evaluation's metrics to a TensorBoard
event file (the ``tensorboard`` extra: ``pip install 'physgrad[tensorboard]'``, which
installs tensorboardX).

    from physgrad.engine.tensorboard import TensorBoard

    with TensorBoard("runs/tb/adam") as board:
        physgrad.fit(problem, method, budget=physgrad.Budget(steps=2000), callbacks=[board])
    # tensorboard --logdir runs/tb

Each metric of :attr:`physgrad.FitResult.history` (``train_loss``, ``test_loss``,
``train_step_<statistic>``, ...) becomes a scalar tag at the evaluation's step, and
``time`` (training seconds) the tag ``time``; a NaN is not written. Nothing is imported or
created before the first evaluation: constructing one without the extra is a one-line
error, and the directory appears with the first scalars.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from .. import extras
from .callbacks import Callback


class TensorBoard(Callback):
    """Writes each evaluation's metrics as TensorBoard scalars into ``logdir`` (one event
    file per writer; flushed after each evaluation, so a running TensorBoard shows them).
    ``prefix`` goes before every tag (e.g. ``"adam/"``). Use it as a context manager, or
    call :meth:`close`, to close the file."""

    def __init__(self, logdir: str | Path, prefix: str = ""):
        extras.require("tensorboard", "physgrad.engine.tensorboard.TensorBoard")
        self.logdir = Path(logdir)
        self.prefix = prefix
        self._writer: Any = None

    def on_eval(self, step: int, metrics: dict[str, float]) -> None:
        if self._writer is None:
            from tensorboardX import SummaryWriter

            self._writer = SummaryWriter(logdir=str(self.logdir))
        for name, value in metrics.items():
            if math.isfinite(value):
                self._writer.add_scalar(self.prefix + name, value, global_step=step)
        self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None

    def __enter__(self) -> TensorBoard:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
