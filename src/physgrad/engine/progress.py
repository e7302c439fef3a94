"""Progress meters for training runs, passed as one argument (diffrax's ``progress_meter=``)."""

from __future__ import annotations

import abc
import time

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn


class AbstractProgressMeter(abc.ABC):
    """Receives ``start`` once, ``update`` after each chunk of steps (:func:`physgrad.fit`
    runs the steps between evaluations in chunks of at most ~0.25 s of training, so ``step``
    may advance by more than one) and ``close`` at the end."""

    @abc.abstractmethod
    def start(self, *, budget, steps_per_epoch: int, step: int, train_time: float, label: str): ...

    @abc.abstractmethod
    def update(self, *, step: int, train_time: float, loss: float): ...

    @abc.abstractmethod
    def close(self): ...


class NoProgressMeter(AbstractProgressMeter):
    """Shows nothing."""

    def start(self, **kwargs):
        pass

    def update(self, **kwargs):
        pass

    def close(self):
        pass


class RichProgressMeter(AbstractProgressMeter):
    """A progress bar with step, batch loss, training time and time left (refreshed ≤ 10/s),
    drawn on ``console`` (default: Rich's console of standard output)."""

    def __init__(self, refresh_seconds: float = 0.1, console: Console | None = None):
        self.refresh_seconds = refresh_seconds
        self.console = console
        self._progress = None

    def start(self, *, budget, steps_per_epoch, step, train_time, label):
        self._budget, self._spe = budget, steps_per_epoch
        self._total = budget.meter_total(steps_per_epoch)
        self._progress = Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TextColumn(
                "step {task.fields[step]}  loss {task.fields[loss]}  train {task.fields[time]}  left {task.fields[left]}"
            ),
            transient=True,
            console=self.console,
        )
        self._progress.start()
        self._task = self._progress.add_task(label, total=self._total, step=step, loss="-", time="0s", left="?")
        self._last = 0.0

    def update(self, *, step, train_time, loss):
        if self._progress is None:  # not started, or closed
            return
        now = time.perf_counter()
        if now - self._last < self.refresh_seconds:
            return
        self._last = now
        done, left = self._budget.meter(step, train_time, self._total)
        self._progress.update(
            self._task, completed=done, step=step, loss=f"{loss:.3e}", time=f"{train_time:.1f}s", left=f"{left:.0f}s"
        )

    def close(self):
        if self._progress is not None:
            self._progress.stop()
            self._progress = None
