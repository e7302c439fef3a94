"""The run's own chunks, replayed for the calibration (issue 50, item 4).

A calibrated budget is only fair if the calibrated step costs what the run's step costs.
The run (:func:`physgrad.engine.run.loop`) takes its steps in chunks of one compiled
program (:func:`physgrad.engine.step.make_steps`) that end at each evaluation, each
epoch's new batch order, the stage's end (:class:`~physgrad.engine.strategies.ChunkSize`),
draws each epoch's order (and fresh data) between chunks, and counts each chunk from its
dispatch to the read-back of its statistics. Timing a chunk of a fixed size with the
same parameters, without the read-back or the epoch's new order, read a step of the
oscillators' Adam at 4.8 ms that cost 10.4 ms in its runs (issue 50).

So a calibration call is a stretch of the run itself: :func:`run_chunks` lists the chunks
the run's loop takes from step 0 (after its first one-step chunk) to the first step where
an evaluation and an epoch's end meet again (at most :data:`MAX_CHUNKS` chunks), and
:class:`Replay` takes them in turn, with the parameters and optimizer state carried from
chunk to chunk, each epoch's order and data drawn as the run draws them, and each chunk
timed from its dispatch to its read-back, as the run's ``train_seconds`` counts it.
Between chunks, untimed, it does the run's work there (:class:`Bookkeeping`: the
statistics, and where the run evaluates its evaluation, metrics row and checkpoint), so
each timed chunk starts as the run's does.
"""

from __future__ import annotations

import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

MAX_CHUNKS = 256  # the replayed cycle's length at most (then it starts again)
CALL_SECONDS = 0.01  # a timed call takes chunks until their seconds add up to this

Chunk = tuple[int, int, int]  # (epoch, batch within the epoch, steps)


def run_chunks(**options: Any) -> list[Chunk]:
    """The chunks of :func:`chunk_cycle` (its arguments), without their evaluations."""
    return [chunk for chunk, _ in chunk_cycle(**options)]


def chunk_cycle(
    *,
    steps_per_epoch: int,
    epoch_end: bool,
    stage_steps: int | None,
    program_chunk: int,
    eval_every: int,
    eval_seconds: float,
    per_step: float,
    max_chunks: int = MAX_CHUNKS,
) -> list[tuple[Chunk, bool]]:
    """The chunks ``(epoch, batch, count)`` the run's loop takes in one stage from its
    first step on, as :func:`physgrad.engine.run._steps_left` and
    :class:`~physgrad.engine.strategies.ChunkSize` size them at ``per_step`` seconds per
    step: to the end of an epoch (``epoch_end``: each epoch has a new order or new data),
    of the stage, to the next evaluation (every ``eval_every`` steps, else every epoch; for
    ``eval_seconds`` the chunks halve towards it), at most ``program_chunk``. Ends at the
    first step where the cycle starts again (an evaluation at an epoch's start), the
    stage's end, or after ``max_chunks`` chunks. Each with whether the run evaluates
    after it."""
    from ..engine.step import CHUNK
    from ..engine.strategies import ChunkSize

    sizer = ChunkSize()
    sizer.per_step = max(per_step, 1e-9)
    per_epoch = max(steps_per_epoch, 1)
    chunks: list[tuple[Chunk, bool]] = []
    step, t, next_eval = 0, 0.0, eval_seconds if eval_seconds > 0 else math.inf
    while len(chunks) < max_chunks and (stage_steps is None or step < stage_steps):
        limit = min(CHUNK, per_epoch - step % per_epoch) if epoch_end else CHUNK
        if stage_steps is not None:
            limit = min(limit, stage_steps - step)
        if eval_seconds <= 0:
            limit = min(limit, eval_every - step % eval_every if eval_every else per_epoch - step % per_epoch)
        count = sizer.size(min(program_chunk, max(limit, 1)), seconds_left=next_eval - t)
        chunk = (*divmod(step, per_epoch), count)
        step, t = step + count, t + count * sizer.per_step
        evaluated = eval_seconds <= 0 and (step % eval_every == 0 if eval_every else step % per_epoch == 0)
        if eval_seconds > 0 and t >= next_eval:
            next_eval, evaluated = eval_seconds * (1 + math.floor(t / eval_seconds)), True
        chunks.append((chunk, evaluated))
        if evaluated and step % per_epoch == 0:
            break
    return chunks


class Bookkeeping:
    """The run's untimed work between two chunks (:func:`physgrad.engine.run.loop`), done
    as the run does it, into a temporary run directory (removed with this object): after
    every chunk its step statistics are added up (``Recorder.accumulate``); where the run
    evaluates, its :class:`~physgrad.engine.recording.Recorder` evaluates every split and
    appends the rows to ``metrics.csv``, and the :class:`~physgrad.engine.recording.Checkpointer`
    saves a checkpoint (the run saves one at every evaluation: ``state.eqx``,
    ``counters.json`` and the manifest, each synced to disk, then the renames); elsewhere it
    saves one once ``checkpoint_seconds`` have passed (``Checkpointer.maybe``). The
    directory holds one checkpoint and one evaluation's rows at a time.

    Why (version 4 of the calibration): the chunk that follows this work costs more than
    the same chunk back to back, and the run counts it. Paired on ``hig_toy`` (one chunk
    of 4 steps after each kind of work, 150 each, in random order, load 15-16 on 2 cores),
    a chunk after a checkpoint took 1.44x the CPU seconds of a chunk back to back for Adam
    and 1.22x for HIG (about 0.4 ms a chunk: the thread waits on the disk's syncs and
    starts again on cold caches), after an evaluation 1.04x for both."""

    def __init__(self, setup: Any, settings: Any, placement: Any):
        from ..engine.recording import Checkpointer, MetricsLog, Recorder
        from ..engine.strategies import Fidelity

        self.directory = tempfile.TemporaryDirectory(prefix="physgrad-calibration-")
        path = Path(self.directory.name)
        self.metrics = path / "metrics.csv"
        self.fidelity = Fidelity.of(setup.problem, settings)  # PRDP's controller starts as the run's
        self.recorder = Recorder(setup, settings=settings, placement=placement, fidelity=self.fidelity,
                                 log=MetricsLog(self.metrics))  # fmt: skip
        self.checkpointer = Checkpointer(path, settings.checkpoint_seconds, True)
        self.state: Any = None

    def __call__(self, params: Any, opt_state: Any, stats: Any, taken: int, evaluated: bool) -> None:
        """After a chunk of ``taken`` steps that ended at ``params``, ``opt_state`` with
        the statistics ``stats`` (on the host); ``evaluated``: the run evaluates here."""
        from ..engine.types import TrainState

        state = self.state if self.state is not None else TrainState(params, opt_state, prdp=self.fidelity.initial())
        state = self.recorder.accumulate(state, stats, taken)
        state = state._replace(params=params, opt_state=opt_state, step=state.step + taken)
        if evaluated:
            state, _ = self.recorder(state, final=False)
            self.checkpointer.save(state)  # the run's "an evaluation is work too: never lost to a kill"
            # the rows were appended as the run appends them; emptied, the directory stays one checkpoint's size
            os.truncate(self.metrics, 0)
        else:
            self.checkpointer.maybe(state)
        self.state = state


def epoch_inputs(steps: Any, setup: Any, stage: int, epoch: int) -> tuple[Any, Any]:
    """A stage's epoch's training data and order (:class:`~physgrad.engine.step.Steps`),
    drawn as the run's loop draws them."""
    steps.draw(setup, stage, epoch)
    return steps.data, steps.order(stage, epoch)


class Replay:
    """A no-argument program for :func:`~physgrad.harness.calibration.time_programs`: each
    call takes the next chunks of ``chunks`` (cycling) until their timed seconds add up to
    ``call_seconds`` (at least one chunk) and returns ``(steps, seconds)``: the steps
    computed and the seconds from each chunk's dispatch to its read-back, summed.

    ``dispatch(params, opt_state, data, order, batch, count)`` is the run's compiled chunk
    (its result ``(params, opt_state, taken, diverged, stats)``); ``read(result)`` reads
    ``(taken, diverged, stats)`` back to the host (the run's ``jax.device_get``);
    ``epoch_inputs(epoch)`` gives the epoch's ``(data, order)``, drawn between chunks as the
    run draws them (``same_every_epoch``: once). The cycle starts again from the initial
    parameters, as does a chunk after a divergent step.

    ``between(params, opt_state, stats, taken, evaluated)``, where given, runs after each
    chunk, untimed, as the run's loop works between chunks (a :class:`Bookkeeping`;
    ``evaluated``: the chunk's entry of ``evaluated``, whether the run evaluates and
    checkpoints after it): the chunk that follows starts where the run's would, after the
    run's evaluation, its metrics row and its checkpoint, not back to back."""

    def __init__(
        self,
        dispatch: Callable[..., Any],
        read: Callable[[Any], tuple[Any, Any, Any]],
        epoch_inputs: Callable[[int], tuple[Any, Any]],
        initial: tuple[Any, Any],
        chunks: list[Chunk],
        *,
        same_every_epoch: bool = False,
        call_seconds: float = CALL_SECONDS,
        clock: Callable[[], float] = time.perf_counter,
        between: Callable[[Any, Any, Any, int, bool], Any] | None = None,
        evaluated: Sequence[bool] = (),
    ):
        self.dispatch, self.read, self.epoch_inputs = dispatch, read, epoch_inputs
        self.initial, self.chunks, self.same = initial, chunks or [(0, 0, 1)], same_every_epoch
        self.between, self.evaluated = between, list(evaluated)
        self.call_seconds, self.clock = call_seconds, clock
        self.position, self.state, self.epoch, self.inputs = 0, initial, None, None
        self.steps_per_call = int(statistics.median(c for _, _, c in self.chunks))

    def __call__(self) -> tuple[int, float]:
        steps, seconds, done = 0, 0.0, 0
        while done == 0 or seconds < self.call_seconds:
            if self.position == 0:
                self.state = self.initial
            position, (epoch, batch, count) = self.position, self.chunks[self.position]
            self.position = (self.position + 1) % len(self.chunks)
            key = 0 if self.same else epoch
            if key != self.epoch:  # the run draws a new epoch's order (and data) between chunks
                self.inputs, self.epoch = self.epoch_inputs(key), key
            data, order = self.inputs  # type: ignore[misc]
            t0 = self.clock()
            params, opt_state, *rest = self.dispatch(*self.state, data, order, batch, count)
            taken, diverged, stats = self.read(tuple(rest))
            seconds += self.clock() - t0
            steps, done = steps + int(taken) + int(bool(diverged)), done + 1
            self.state = self.initial if diverged else (params, opt_state)
            if self.between is not None and not diverged:  # untimed: the run's work before its next chunk
                evaluated = position < len(self.evaluated) and self.evaluated[position]
                self.between(params, opt_state, stats, int(taken), bool(evaluated))
        return steps, seconds
