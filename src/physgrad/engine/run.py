"""One run: :func:`fit` settles the caller's arguments, :func:`_run` builds and resumes,
and :func:`loop` steps with one bundle of strategies (:class:`Strategies`).

From the caller's objects to the jitted step::

    fit(problem, method | [Phase], budget=, out=, seed=, settings=, split=, resume=, devices=, callbacks=)
      Request(...)                         the arguments checked, the phases settled
      with float64_scope(problem.needs_float64), the run directory's lock (out=None: none):
        preflight(problem, phases)         footprints from shapes alone   (setup.py)
        build_setup(problem, phases, seed, split)  data (split(make_data)), network, objective, stages
        TrainState(params, opt_state)      or the checkpoint's             (types.py)
        Steps(...).compile(state, setup)   the jitted chunk of steps, memory-guarded (step.py)
        loop(state, setup=, compiled=, strategies=Strategies(...))
        finish(ending, ...)                params.eqx, test_cases.json, summary.json (recording.py)
      FitResult(summary, history, network, state)                          (result.py)

Wall time counts training steps only: compilation (``compile_seconds``) and evaluation are
excluded, so equal budgets compare update rules, not tracing. The same chunks are also
timed in CPU seconds (``cpu_time_per_step``: a calibration's ``cpu`` clock,
:func:`~physgrad.engine.cpu_clock.run_cpu_time`: this thread's and XLA's, not those of the
host's other Python threads, such as a Dask worker's event loop).

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import numpy as np

from .. import checks, distributed
from ..errors import ConfigError
from ..methods import AbstractMethod
from ..precision import float64_scope
from ..problems import AbstractProblem
from . import record as records
from . import rundir
from .callbacks import Callback, Callbacks
from .cpu_clock import run_cpu_time
from .progress import AbstractProgressMeter, NoProgressMeter
from .recording import (
    Checkpointer,
    MetricsLog,
    Recorder,
    environment,
    finish,
    is_final,
    read_summary,
    write_json,
    writer_lock,
)
from .result import FitResult, history_from_metrics, history_of
from .resume import budget_met, done_already, missing_final_files, recorded, write_environment
from .setup import build_setup, preflight
from .splits import TEST_SPLIT, AbstractSplit
from .step import CHUNK, Steps
from .strategies import ChunkSize, EvalSchedule, Fidelity, Placement, StopRule
from .types import Budget, Ending, Phase, Setup, Stage, TrainSettings, TrainState

DEFAULT_SETTINGS = TrainSettings()  # frozen: one shared default


def fit(
    problem: AbstractProblem,
    method: AbstractMethod | Phase | Sequence[Phase],
    *,
    budget: Budget,
    out: str | Path | None = None,
    seed: int = 0,
    batch_size: int | None = None,
    settings: TrainSettings = DEFAULT_SETTINGS,
    split: AbstractSplit = TEST_SPLIT,
    resume: bool = False,
    progress: AbstractProgressMeter | None = None,
    devices: int | Sequence[jax.Device] | None = 1,  # pyright: ignore[reportInvalidTypeForm]
    record: dict[str, Any] | None = None,
    same_run: Callable[[dict[str, Any]], Any] | None = None,
    label: str = "",
    name: str = "",
    callbacks: Sequence[Callback | Callable[[int, dict[str, float]], Any]] | None = None,
) -> FitResult:
    """Train ``method`` (or a sequence of phases) on ``problem`` and return a
    :class:`~physgrad.engine.FitResult`: the summary, the history of every evaluation as
    arrays, the final network and state. With ``out`` the run writes the run directory
    ``out`` (``config.json``, ``metrics.csv``, checkpoints, ``params.eqx``,
    ``summary.json``, ...); with ``out=None`` (the default) it runs in memory and writes
    no file at all (no checkpoints, so no ``resume``).

    ``batch_size`` applies to a single method (phases carry their own; default: the
    problem's ``default_batch_size``). ``name`` is the method's name in the summary, in the
    record and, for a single method, in ``stage_steps`` (default: the phases' names joined
    by ``,``; a :class:`~physgrad.Method` without a name is called ``Method``).

    ``split`` says which data the run trains on and evaluates as its test split
    (:mod:`physgrad.engine.splits`): :class:`~physgrad.TestSplit`, the default, the
    problem's own; :class:`~physgrad.HoldOut` validation data (the problem's ``val``, else
    the last fraction of train, not trained on) in place of test, as a tuning trial needs.
    The problem stays the caller's own: the split applies to ``make_data``'s output.

    ``record`` is written as ``config.json`` (default: a description of problem, method,
    seed, budget and settings (and a :class:`~physgrad.HoldOut`'s note, key ``validation``), with ``method`` the name and ``optimizers`` each phase's
    optax hyperparameters where the optimizer was made with ``optax.inject_hyperparams``,
    else a note that they cannot be recorded: :func:`physgrad.engine.hyperparams.optimizer_record`).
    With ``resume=True`` an existing run whose record matches (``same_run(old_record)``:
    True, or an empty list of differences, each ``"key: old → new"``; default: equal
    apart from the budget, the name, the checkpoint interval and, without PRDP, the
    evaluation cadence, after :func:`physgrad.engine.record.normalised`) continues from its checkpoint up to
    ``budget``, and a finished run whose budget is met returns its summary (its history
    read from ``metrics.csv``; ``network`` and ``state`` None).

    ``callbacks`` is a list of :class:`~physgrad.engine.Callback` objects (``on_eval(step,
    metrics)`` after each evaluation, ``on_checkpoint(step, path)`` after each checkpoint)
    or functions ``f(step, metrics)`` (called after each evaluation), called between steps
    outside ``jax.jit`` (:mod:`physgrad.engine.callbacks`).

    A run whose loss turns NaN or infinite stops with status ``"diverged"``, the step and
    the last finite loss. ``devices`` (a number, a sequence of jax devices, or None for
    every device) splits every batch over a device mesh; in a multi-process run every process calls ``fit`` alike and only process
    0 writes.

    Keys: everything random derives from ``key = jax.random.key(seed)``:
    the data ``split(problem.make_data(fold_in(key, 0)))``, the initial network
    ``problem.initial_network(fold_in(key, 1), data)``, a shuffled epoch's order from
    ``fold_in(fold_in(fold_in(key, 2), stage), epoch)`` and, with ``fresh_samples``, a
    later epoch's training data ``split(make_data(fold_in(fold_in(fold_in(key, 3), stage),
    epoch)))["train"]`` (``fold_in`` is ``jax.random.fold_in``; stages and epochs count from
    0). A hand-written loop given these keys takes the same steps.

    Steps between evaluations run as chunks of one compiled program
    (:func:`~physgrad.engine.step.make_steps`) with one read-back each, so the loop adds
    almost nothing per step; ``summary["train_seconds"]`` counts training only
    (compilation, evaluation and callbacks excluded).

    A problem that declares ``needs_float64`` runs inside ``jax.enable_x64(True)``; the
    caller's JAX configuration is otherwise untouched.
    """
    _check_arguments(problem, budget=budget, seed=seed, batch_size=batch_size, settings=settings, out=out,
                     resume=resume)  # fmt: skip
    hooks = Callbacks(callbacks)
    phases = _phases(method, batch_size, name)
    label_all = name or ",".join(p.label for p in phases)
    # the record describes the phases as given (a name given to fit is the record's "method")
    record = record or records.describe(problem, phases=_phases(method, batch_size, ""), seed=seed, budget=budget,
                                        settings=settings, name=label_all, split=split)  # fmt: skip
    as_json = json.loads(json.dumps(record, default=str))
    same_run = same_run or (lambda old: records.differences(records.identity(old),
                                                            records.identity(records.like(as_json, old))))  # fmt: skip
    run_dir = None if out is None else Path(out)
    identity = {"problem": problem.name, "method": label_all, "seed": seed}
    request = Request(problem, phases, seed, budget, settings, run_dir, resume, record, same_run,
                      label or (run_dir.name if run_dir is not None else label_all), identity, hooks, split)  # fmt: skip
    with float64_scope(problem.needs_float64):
        placement = Placement(devices)
        if run_dir is None:  # in memory: no lock, no files, no signal handler to install
            return _run(request, placement=placement, progress=progress or NoProgressMeter())
        with writer_lock(run_dir, placement), rundir.terminate_as_interrupt():  # SIGTERM: a checkpoint, then stop
            return _run(request, placement=placement, progress=progress or NoProgressMeter())


@dataclasses.dataclass(frozen=True)
class Request:
    """:func:`fit`'s arguments, checked and settled: what one run is asked to do."""

    problem: AbstractProblem
    phases: list[Phase]
    seed: int
    budget: Budget
    settings: TrainSettings
    run_dir: Path | None  # None: in memory
    resume: bool
    record: dict[str, Any]  # written as config.json
    same_run: Callable[[dict[str, Any]], Any]  # whether a recorded run is this one (or what differs)
    label: str  # the progress meter's
    identity: dict[str, Any]  # problem, method and seed: the summary's first keys
    callbacks: Callbacks = dataclasses.field(default_factory=Callbacks)
    split: AbstractSplit = TEST_SPLIT  # which data it trains on and evaluates as test


class Strategies(NamedTuple):
    """Everything :func:`loop` consults besides its state, one decision each."""

    stop: StopRule
    schedule: EvalSchedule
    placement: Placement
    steps: Steps
    fidelity: Fidelity
    recorder: Recorder
    checkpointer: Checkpointer
    progress: AbstractProgressMeter


def loop(state: TrainState, *, setup: Setup, compiled: Any, strategies: Strategies) -> Ending:
    """Steps until the budget is met or the loss stops being finite (the training loop);
    ``compiled`` is the current stage's steps (:func:`~physgrad.engine.step.make_steps`).

    The steps are dispatched in chunks (:class:`ChunkSize`) that end where something
    happens between steps: an evaluation, an epoch's new batch order, a stage, the budget,
    a checkpoint. Each chunk's statistics are read back once, which is also what makes its
    training time honest (the device has finished)."""
    stop, schedule, placement, steps, fidelity, recorder, checkpointer, progress = strategies
    if state.step == 0:
        state, _ = recorder(state, final=False)
    schedule.start(state.train_time)
    chunks = ChunkSize()
    order_key, order = None, None
    try:
        while not stop.met(state.step, state.train_time):
            index = setup.stage_index(state.step)
            if index != state.stage:  # switch method: the parameters carry over, the new method starts fresh
                opt_state = placement.put(setup.stages[index].method.init(distributed.to_host(state.params)))
                compiled, state = steps.compile(state._replace(stage=index, opt_state=opt_state), setup)
                chunks.reset()
            stage = setup.stages[index]
            epoch, batch = divmod(state.step - stage.start, stage.steps_per_epoch)
            if (index, 0 if steps.same_every_epoch else epoch) != order_key:
                steps.draw(setup, index, epoch)
                order, order_key = steps.order(index, epoch), (index, 0 if steps.same_every_epoch else epoch)
            limit = min(compiled.chunk, _steps_left(state, stage, stop, schedule, epoch_end=not steps.same_every_epoch))
            count = placement.agree(chunks.size(limit, seconds_left=min(
                stop.seconds_left(state.train_time),
                schedule.seconds_left(state.train_time), checkpointer.seconds_left())))  # fmt: skip
            t_start, cpu_start = time.perf_counter(), run_cpu_time()
            params, opt_state, taken, diverged, stats = compiled(state.params, state.opt_state, steps.data, order,
                                                                 np.int32(batch), np.int32(count))  # fmt: skip
            taken, diverged, stats = jax.device_get(distributed.to_host((taken, diverged, stats)))  # waits: honest time
            cpu_seconds = run_cpu_time() - cpu_start  # the same chunk in CPU seconds (engine.cpu_clock)
            # From here to the checkpoint after an evaluation is one unit: a Ctrl-C or SIGTERM waits
            # for it, so a step is never taken without its evaluation logged (rundir.deferred_interrupts)
            with rundir.deferred_interrupts():
                train_time = placement.clock(state.train_time + time.perf_counter() - t_start)
                taken = int(taken)
                chunks.observe(taken + int(diverged), train_time - state.train_time)
                # A step its method's acceptance refused (physgrad.acceptance) left the parameters as they
                # were: its non-finite loss is not a divergence (make_steps stops at a divergent step only).
                losses = np.asarray(stats["loss"][:taken], np.float64)
                finite = losses[np.isfinite(losses)]
                last_finite = float(finite[-1]) if finite.size else state.last_finite_loss
                state = recorder.accumulate(state, stats, taken)._replace(
                    params=params, opt_state=opt_state, step=state.step + taken, train_time=train_time,
                    last_finite_loss=last_finite, cpu_seconds=state.cpu_seconds + cpu_seconds,
                    cpu_steps=state.cpu_steps + taken)  # fmt: skip
                if fidelity.name:
                    state = state._replace(
                        solver_iterations=state.solver_iterations + taken * fidelity.iterations(state)
                    )
                if diverged:
                    return Ending(state, setup, "diverged", state.step)
                boundary = stop.met(state.step, state.train_time) or (
                    stage.steps is not None and state.step == stage.start + stage.steps
                )
                if schedule.due(state.step, state.train_time, stage, boundary):
                    state, finite_eval = recorder(state, final=stop.met(state.step, state.train_time))
                    if not finite_eval:
                        return Ending(state, setup, "diverged", state.step)
                    refined = fidelity.problem_at(setup, state)
                    if refined is not setup:  # PRDP refined the solver: new problem, new step
                        setup = refined
                        recorder.use(setup)
                        compiled, state = steps.compile(state, setup)
                        chunks.reset()
                    checkpointer.save(state)  # an evaluation is work too: never lost to a kill
                else:
                    checkpointer.maybe(state)
            rundir.fault("step")
            progress.update(step=state.step, train_time=state.train_time, loss=float(losses[-1]))
    except KeyboardInterrupt as e:
        return Ending(state, setup, "terminated" if isinstance(e, rundir.Terminated) else "interrupted")
    except ConfigError:  # the memory guard refused a later stage's step: keep what was done for a resume
        checkpointer.save(state)
        raise
    return Ending(state, setup, "finished")


def _steps_left(state: TrainState, stage: Stage, stop: StopRule, schedule: EvalSchedule, *, epoch_end: bool) -> int:
    """The most steps the next chunk may take: to the end of the epoch (with ``epoch_end``:
    the next has a new batch order or new data), of the stage, of a steps or epochs
    budget, to a step-scheduled evaluation."""
    local = state.step - stage.start
    limit = min(CHUNK, stage.steps_per_epoch - local % stage.steps_per_epoch) if epoch_end else CHUNK
    if stage.steps is not None:
        limit = min(limit, stage.steps - local)
    evaluation = schedule.steps_left(state.step, stage)
    if evaluation is not None:
        limit = min(limit, evaluation)
    return stop.steps_left(state.step, max(limit, 1))


# --- the run around the loop -----------------------------------------------------------------
def _run(request: Request, *, placement: Placement, progress: AbstractProgressMeter) -> FitResult:
    """One run while its writer process holds the run directory's lock (a run in memory
    has neither): refuse or resume what the directory holds, build, loop, finish."""
    run_dir, settings, budget = request.run_dir, request.settings, request.budget
    old = recorded(request)
    checkpointer = Checkpointer(run_dir, settings.checkpoint_seconds, placement.writer, request.callbacks)
    has_ckpt = request.resume and checkpointer.exists()
    placement.barrier(f"physgrad.fit:{run_dir}")  # every process has looked before process 0 writes
    if not placement.writer:  # other processes compute alike and write nothing
        progress = NoProgressMeter()
    done = done_already(run_dir, budget, settings.wall_cap) if request.resume and run_dir is not None else None
    if done is not None and run_dir is not None:  # every file unchanged (checked before building data and network)
        return FitResult(done, history_from_metrics(run_dir / "metrics.csv"), run_dir=run_dir)

    fidelity = Fidelity.of(request.problem, settings)
    setup, state = _start(
        request, placement=placement, fidelity=fidelity, checkpoint=checkpointer if has_ckpt else None
    )
    met = state.step > 0 and run_dir is not None and budget_met(budget, recorded=(old or {}).get("budget"),
        step=state.step, seconds=state.train_time, epochs=setup.epochs, run_dir=run_dir)  # fmt: skip
    if met and run_dir is not None:  # a kill came after the final checkpoint: nothing to train, maybe the summary
        summary = read_summary(run_dir)
        if summary and is_final(summary) and summary.get("steps") == state.step and not missing_final_files(run_dir):
            return _result(summary, history_from_metrics(run_dir / "metrics.csv"), state, setup, run_dir)
    setup = fidelity.problem_at(setup, state)
    state = state._replace(params=placement.put(state.params), opt_state=placement.put(state.opt_state))
    steps, compiled = None, None
    if not met:
        steps = Steps(setup, placement, settings, request.seed)
        compiled, state = steps.compile(state, setup)  # a step the memory guard refuses leaves no files behind
    if checkpointer.writes and run_dir is not None:
        run_dir.mkdir(parents=True, exist_ok=True)  # made by the lock already, unless the caller holds none
        write_json(run_dir / "config.json", request.record)
        write_environment(run_dir, {**environment(), "mesh_devices": distributed.mesh_size(placement.mesh)})
    # a checkpoint at step 0 precedes the first evaluation, which the resumed loop makes again
    keep = state.step if has_ckpt and state.step > 0 else None
    log = MetricsLog(None if run_dir is None else run_dir / "metrics.csv", keep_until_step=keep,
                     enabled=checkpointer.writes)  # fmt: skip
    recorder = Recorder(setup, settings=settings, placement=placement, fidelity=fidelity, log=log,
                        callbacks=request.callbacks)  # fmt: skip
    evaluated = recorder.restore(log.kept)
    if steps is None:  # nothing to train (a finished run's deleted files): its earlier CPU counts stand
        before = (read_summary(run_dir) if run_dir is not None else None) or {}
        state = state._replace(cpu_seconds=before.get("cpu_seconds") or 0.0, cpu_steps=before.get("cpu_steps") or 0)
        ending = _evaluated(Ending(state, setup, "finished"), recorder=recorder, evaluated=evaluated)
    else:
        strategies = Strategies(StopRule(budget, setup, settings.wall_cap), EvalSchedule(settings), placement, steps, fidelity, recorder,
                                checkpointer, progress)  # fmt: skip
        progress.start(budget=budget, steps_per_epoch=setup.steps_per_epoch, step=state.step,
                       train_time=state.train_time, label=request.label)  # fmt: skip
        try:
            ending = loop(state, setup=setup, compiled=compiled, strategies=strategies)
        finally:
            progress.close()
    summary = _close(ending, request=request, recorder=recorder, checkpointer=checkpointer)
    return _result(summary, history_of(recorder.rows), ending.state, ending.setup, run_dir)


def _result(summary: dict[str, Any], history, state: TrainState, setup: Setup, run_dir: Path | None) -> FitResult:
    """The result with the final network and state on the host."""
    params, opt_state = distributed.to_host((state.params, state.opt_state))
    state = state._replace(params=params, opt_state=opt_state)
    return FitResult(summary, history, network=setup.network(params), state=state, run_dir=run_dir)


def _start(
    request: Request, *, placement: Placement, fidelity: Fidelity, checkpoint: Checkpointer | None
) -> tuple[Setup, TrainState]:
    """The setup and the first state: fresh, or ``checkpoint``'s (where resuming one)."""
    problem, phases, seed, split = request.problem, request.phases, request.seed, request.split
    if request.settings.memory_guard:
        preflight(problem, phases, seed=seed, mesh=placement.mesh, split=split)  # before minutes of data generation
    setup = build_setup(problem, phases, seed, split)
    for stage in setup.stages:
        distributed.check_batch(stage.batch_size, placement.mesh)
    fresh = TrainState(setup.params, setup.method.init(setup.params), prdp=fidelity.initial())
    like = lambda c: fresh._replace(opt_state=setup.stages[c["stage"]].method.init(setup.params))  # noqa: E731
    state = (checkpoint.load(like) if checkpoint is not None else None) or fresh
    if jax.process_count() > 1:  # every process must resume from the same checkpoint
        from jax.experimental import multihost_utils

        seen = multihost_utils.process_allgather(np.array([int(checkpoint is not None), state.step]))
        if len({tuple(row) for row in np.asarray(seen).reshape(-1, 2)}) > 1:
            raise ConfigError(f"the processes see different checkpoints in {request.run_dir}; a multi-process resume "
                              "needs the run directory on a file system every process shares")  # fmt: skip
    return setup, state


def _evaluated(ending: Ending, *, recorder: Recorder, evaluated: int | None) -> Ending:
    """A run that met its budget before a kill, with its final evaluation (made now if the
    kill came before it was logged)."""
    if evaluated == ending.state.step:
        return ending
    state, finite = recorder(ending.state, final=True)
    return ending._replace(state=state) if finite else Ending(state, ending.setup, "diverged", state.step)


def _close(ending: Ending, *, request: Request, recorder: Recorder, checkpointer: Checkpointer) -> dict[str, Any]:
    """The summary of a finished or diverged run (written last); an interrupted run is
    checkpointed and the interrupt raised again."""
    state, writer, run_dir = ending.state, checkpointer.writes, request.run_dir
    if ending.status in ("interrupted", "terminated"):  # Ctrl-C or SIGTERM: keep what was done, then stop
        checkpointer.save(state)
        if writer and run_dir is not None:
            write_json(run_dir / "summary.json",
                       {"status": "interrupted", "steps": state.step, "train_seconds": state.train_time})  # fmt: skip
        raise rundir.Terminated if ending.status == "terminated" else KeyboardInterrupt
    summary = {
        **request.identity,
        **finish(ending, recorder=recorder, checkpointer=checkpointer, budget=request.budget),
    }
    cap = request.settings.wall_cap
    if cap > 0:  # stopped by the wall-clock cap before its budget: recorded, and resumable with a larger cap
        rule = StopRule(request.budget, ending.setup, cap)
        summary["wall_capped"] = (ending.status == "finished" and rule.capped(state.train_time)
                                  and not rule.budget_met(state.step, state.train_time))  # fmt: skip
        summary["wall_cap"] = cap
    if writer and run_dir is not None:  # strict JSON: a diverged run's NaN loss as null
        rundir.atomic_write(run_dir / "summary.json", rundir.strict_json_text(summary))
    return summary


# --- fit's arguments --------------------------------------------------------------------------
def _check_arguments(problem, *, budget, seed, batch_size, settings, out, resume) -> None:
    """:func:`fit`'s arguments by type and range, each refused in one line in the library's
    words before any work (the method is checked by :func:`_phases`)."""
    if not isinstance(problem, AbstractProblem):
        raise ConfigError(f"problem must be a physgrad problem (an AbstractProblem instance), got {problem!r}")
    if not isinstance(budget, Budget):
        raise ConfigError(f"budget must be a physgrad.Budget, e.g. Budget(steps={budget!r}), got {budget!r}")
    if not checks.NON_NEGATIVE_INT.valid(seed) or seed > 2**63 - 1:  # jax.random.key's signed 64 bits
        raise ConfigError(f"seed must be {checks.NON_NEGATIVE_INT.text} below 2**63, got {seed!r}")
    if batch_size is not None and not checks.POSITIVE_INT.valid(batch_size):
        raise ConfigError(f"batch_size must be {checks.POSITIVE_INT.text} or None (the problem's default), "
                          f"got {batch_size!r}")  # fmt: skip
    if not isinstance(settings, TrainSettings):
        raise ConfigError(f"settings must be a physgrad.TrainSettings, got {settings!r}")
    if out is not None:
        checks.check_directory(out, "out")
    elif resume:
        raise ConfigError("resume=True needs the run directory to resume: pass out=DIR (out=None runs in memory)")


def _phases(method, batch_size, name: str = "") -> list[Phase]:
    """The phases of a single method (named ``name``) or of the phases given, checked."""
    if isinstance(method, AbstractMethod):
        return [Phase(method, None, batch_size, name=name)]
    phases = [method] if isinstance(method, Phase) else list(method)
    if not phases or not all(isinstance(p, Phase) for p in phases):
        raise ConfigError("method must be a physgrad method (e.g. physgrad.methods.Method) or a list of Phase")
    if any(p.steps is None for p in phases[:-1]) or phases[-1].steps is not None and len(phases) > 1:
        raise ConfigError("every phase but the last needs steps; the last runs until the budget is spent")
    return phases
