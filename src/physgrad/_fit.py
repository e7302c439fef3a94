""":func:`physgrad.fit`: :func:`physgrad.engine.run.fit` with the BLAS/LAPACK thread pools
limited for its own duration (``threads=1`` by default, as the ``physgrad`` command line does).

A Jacobian method's float64 ``eigh`` runs in jaxlib's CPU LAPACK kernels on SciPy's
OpenBLAS, which starts one thread per core and spins them; beside a busy neighbour those
threads wait for each other and the step collapses (a user's script beside a busy
neighbour: a HIG step at 170 ms median with the default pools, 6.4 ms inside
``physgrad.threads(1)``; ``docs/performance.md``, "Threads under load", for more). The
command line runs the engine's ``fit`` inside :func:`physgrad.cpu.process_threads`; a user's
script calls this one, which limits the pools loaded in the process
(:func:`physgrad.cpu.threads`) and restores them on return. XLA's own Eigen pool is set
once, when JAX's backend starts, and is left alone (``physgrad.cpu``).

It also shows the command line's progress bar (:class:`~physgrad.engine.progress.RichProgressMeter`)
where a user's script runs in a terminal, and nothing where its output goes to a file, a
pipe or a test log, as the command line decides (Rich's console ``is_terminal``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import rich

from . import cpu as _cpu
from .engine import run as _run
from .engine.callbacks import Callback
from .engine.progress import AbstractProgressMeter, NoProgressMeter, RichProgressMeter
from .engine.result import FitResult
from .engine.splits import TEST_SPLIT, AbstractSplit
from .engine.types import Budget, Phase, TrainSettings
from .errors import ProgressInvalid
from .methods import AbstractMethod
from .problems import AbstractProblem

if TYPE_CHECKING:
    import jax


def fit(
    problem: AbstractProblem,
    method: AbstractMethod | Phase | Sequence[Phase],
    *,
    budget: Budget,
    out: str | Path | None = None,
    seed: int = 0,
    batch_size: int | None = None,
    settings: TrainSettings = _run.DEFAULT_SETTINGS,
    split: AbstractSplit = TEST_SPLIT,
    resume: bool = False,
    progress: AbstractProgressMeter | bool | None = None,
    devices: int | Sequence[jax.Device] | None = 1,  # pyright: ignore[reportInvalidTypeForm]
    record: dict[str, Any] | None = None,
    same_run: Callable[[dict[str, Any]], Any] | None = None,
    label: str = "",
    name: str = "",
    callbacks: Sequence[Callback | Callable[[int, dict[str, float]], Any]] | None = None,
    threads: int | None = 1,
) -> FitResult:
    """Train ``method`` (or a sequence of phases) on ``problem`` and return a
    :class:`~physgrad.engine.FitResult`: :func:`physgrad.engine.fit`, whose page documents
    every other argument, the run directory, ``resume``, the keys and the result, with the
    BLAS/LAPACK thread pools limited while it runs.

    ``threads`` (default 1) limits the BLAS/LAPACK and OpenMP thread pools of this process
    to that many threads while ``fit`` runs and restores them on return
    (:func:`physgrad.cpu.threads`), as the ``physgrad`` command line does for its runs
    (``--threads``): a Jacobian method's LAPACK calls (the float64 ``eigh`` of HIG and
    Gauss–Newton) collapse beside a busy neighbour with one spinning thread per core.
    ``threads=None`` leaves the pools as they are (a limit of the caller's own, such as
    ``with physgrad.threads(4):``, stays in force). XLA's own CPU thread pool is not
    affected (:mod:`physgrad.cpu`).

    ``progress``: None (the default) shows a progress bar (step, batch loss, training
    time, time left; :class:`~physgrad.engine.progress.RichProgressMeter`) when standard
    output is a terminal and nothing otherwise (a file, a pipe, a test log), as the
    command line does; ``False`` shows nothing; ``True`` shows the bar wherever Rich can
    draw one (a notebook, whose output is no terminal); an
    :class:`~physgrad.engine.progress.AbstractProgressMeter` is used as it is.
    """
    meter = _meter(progress)
    limit = contextlib.nullcontext() if threads is None else _cpu.threads(threads)
    with limit:
        return _run.fit(
            problem,
            method,
            budget=budget,
            out=out,
            seed=seed,
            batch_size=batch_size,
            settings=settings,
            split=split,
            resume=resume,
            progress=meter,
            devices=devices,
            record=record,
            same_run=same_run,
            label=label,
            name=name,
            callbacks=callbacks,
        )


def _console():
    """Rich's console of standard output (a function, so a test can give a forced terminal)."""
    return rich.get_console()


def _meter(progress: AbstractProgressMeter | bool | None) -> AbstractProgressMeter:
    """The meter ``fit``'s ``progress`` argument asks for (see :func:`fit`)."""
    if isinstance(progress, AbstractProgressMeter):
        return progress
    if progress is not None and not isinstance(progress, bool):
        raise ProgressInvalid(progress)
    if progress is False:
        return NoProgressMeter()
    console = _console()
    # the command line's rule: a bar only where it redraws in place; in a log it would be noise
    if progress is None and not console.is_terminal:
        return NoProgressMeter()
    return RichProgressMeter(console=console)


# help(physgrad.fit): the above, then the engine's own description of every argument
fit.__doc__ = (
    (fit.__doc__ or "").rstrip() + "\n\n    physgrad.engine.fit:\n\n    " + (_run.fit.__doc__ or "").strip() + "\n"
)
