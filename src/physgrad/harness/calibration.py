"""Calibrated cost: each method's compiled training step timed on the problem, and the step
budgets and time axis that follow from it (issue 31, item 2).

A wall-clock race on a shared machine measures the machine's load as much as the update
rule (one busy neighbour made a HIG step 55× slower, an Adam step 3×). So a study with a
seconds budget first **calibrates**: it builds each method's run (seed 0, the study's
settings), compiles its step with the engine's own :class:`~physgrad.engine.step.Steps`
(the compiled program is kept in :data:`physgrad.engine.programs.STEPS`, so the runs that follow
do not compile it again), calls it once more to warm it up, and then times it in
**interleaved rounds** (one call of every method per round, so that a change of load
touches every method alike) under the thread setting the study runs with. A call replays
the run's own chunks between evaluations, read-back and each epoch's order included, with
the run's work between chunks done untimed as the run does it (its evaluations, metrics
rows and checkpoints; :mod:`physgrad.harness.run_chunks`), until they take about 10 ms.
The median over the rounds of the seconds per step is the method's cost (the quartiles and the extremes are kept as its
spread). Each run then trains for

    steps = floor(seconds / calibrated seconds per step)           (at least 1)

(a sequence ``adam:2000,hig`` spends its stages' calibrated costs in order), and its curves
are drawn against the **calibrated time** ``t = step × calibrated seconds per step`` (summed
over the stages of a sequence), with the raw training wall-clock recorded beside it. The
record, ``calibration.json`` in the study directory (and ``calibration.csv``: one row per
stage in the columns of ``docs/reproductions/long/calibration.csv``), holds the machine,
its load before and after, the thread setting, and per method the median, spread, number
of rounds and compile time. A resumed study reads it back and does not time again (a
method whose configuration changed, or a new method, is timed then and added).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import math
import os
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from ..engine import rundir
from ..engine.cpu_clock import run_cpu_time
from ..engine.types import Steps
from ..errors import ConfigError
from .calibration_table import CSV_COLUMNS, EXTRA_COLUMNS, csv_rows, load, machine, machine_line, write_csv  # noqa: F401
from .config import RunConfig

CALIBRATION_FILE = "calibration.json"
CALIBRATION_CSV = "calibration.csv"
REPEATS = 15  # rounds of interleaved timing, at most
CALL_SECONDS = 0.01  # a timed call takes at least this many steps' worth (chunk_steps)
# 2: a timed call is a chunk of the run's loop (1: one step per call, which charged a cheap
# step a whole dispatch). A resumed study keeps its record (its runs were budgeted by it).
# 3: a timed call replays the run's own chunks between evaluations, read-back and epoch orders
# included, and the run's evaluations between them, untimed (harness.run_chunks).
# 4: and the run's other work between chunks, untimed: its metrics rows and the checkpoint it
# saves at every evaluation (harness.run_chunks.Bookkeeping; a chunk after a checkpoint costs more).
VERSION = 4
MIN_REPEATS = 3  # every method gets at least this many rounds
MAX_SECONDS = 10.0  # a method leaves the rounds once its timed steps add up to this (after MIN_REPEATS)
# The timer of a calibration (``$PHYSGRAD_CALIBRATION_CLOCK``, recorded as the record's "clock").
# "wall" (default): the step's wall-clock, what a user on an idle machine waits. "cpu": the
# CPU seconds of the calibrating thread and XLA's threads (engine.cpu_clock.run_cpu_time: the
# process's, less its other Python threads', such as the loop of a Dask cluster this process
# started; a run's cpu_time_per_step is read on the same clock), which
# a busy neighbour on the same cores barely changes: it takes turns with the step instead of
# stretching its work, so a study calibrated on a loaded machine gets the step budgets it would
# get idle (a run's steps are one thread's work: --threads 1, the default of a study).
CLOCKS: dict[str, Callable[[], float]] = {"wall": time.perf_counter, "cpu": run_cpu_time}
CLOCK_VARIABLE = "PHYSGRAD_CALIBRATION_CLOCK"


def clock_name() -> str:
    """The calibration's timer by name (:data:`CLOCKS`), from ``$PHYSGRAD_CALIBRATION_CLOCK``
    (default "wall"); a one-line error naming the valid ones otherwise."""
    name = os.environ.get(CLOCK_VARIABLE, "wall").strip().lower() or "wall"
    if name not in CLOCKS:
        raise ConfigError(f"${CLOCK_VARIABLE}={name!r} is not a calibration clock; choose one of {', '.join(CLOCKS)}")
    return name


RULE = ("median over interleaved rounds (one call of every method per round) of the compiled step's time per step, "
        "each call the run's own chunks between evaluations (dispatch to read-back; each epoch's order and, untimed, "
        "the run's work between chunks: its evaluations, metrics rows and checkpoints) adding up to about 10 ms; "
        "compilation, first call excluded; seed 0")  # fmt: skip

Program = Callable[[], Any]  # one training step, blocking until its results are ready


@dataclasses.dataclass(frozen=True)
class StageCost:
    """One stage's calibrated step: its method and batch size, its length (None: the last
    stage, until the budget is spent), its route (the Jacobian methods' ``route`` setting,
    else empty) and the timing: median seconds per step, quartiles, extremes, rounds, and
    the seconds spent compiling and warming it up."""

    method: str
    batch_size: int
    steps: int | None
    route: str
    seconds: float
    q25: float
    q75: float
    low: float
    high: float
    rounds: int
    compile_seconds: float = 0.0
    steps_per_call: int = 1  # steps in each timed call (a chunk of the run's loop; 1 before version 2)


def steps_for(seconds: float, stages: Sequence[StageCost]) -> int:
    """The step budget of ``seconds`` of calibrated time: each fixed-length stage spends its
    steps × cost in order, the last stage runs on until ``seconds`` is spent; at least 1
    step (a budget below one step still trains one)."""
    spent, steps = 0.0, 0
    for stage in stages:
        if stage.steps is not None and spent + stage.steps * stage.seconds < seconds:
            spent += stage.steps * stage.seconds
            steps += stage.steps
            continue
        steps += math.floor((seconds - spent) / stage.seconds + 1e-9)
        break
    return max(1, steps)


def time_at(step: float, stages: Sequence[StageCost]) -> float:
    """The calibrated time after ``step`` steps: each step costs its stage's calibrated
    seconds (``t = step × seconds per step`` for a single method)."""
    t, left = 0.0, float(step)
    for stage in stages:
        n = left if stage.steps is None else min(left, stage.steps)
        t += n * stage.seconds
        left -= n
        if left <= 0:
            break
    return t


def time_programs(
    programs: Mapping[str, Sequence[Program]],
    *,
    repeats: int = REPEATS,
    max_seconds: float = MAX_SECONDS,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, list[list[float]]]:
    """Seconds per step of each program, in interleaved rounds: every round calls each
    key's programs (a sequence's stages) once, in order; a key leaves the rounds once it
    has ``MIN_REPEATS`` rounds and its timed calls add up to ``max_seconds``. A program
    that returns a Python ``int`` n took n steps in that call, ``(n, seconds)`` n steps in
    seconds it timed itself (a :class:`~.run_chunks.Replay`); anything else one step. Returns
    ``{key: [per-program list of seconds per step]}``. ``clock`` is the timer (a fake one
    makes the tests deterministic)."""
    times: dict[str, list[list[float]]] = {k: [[] for _ in progs] for k, progs in programs.items()}
    spent = dict.fromkeys(programs, 0.0)
    active = list(programs)
    for r in range(max(repeats, 1)):
        for key in list(active):
            for i, program in enumerate(programs[key]):
                t0 = clock()
                steps = program()
                seconds = clock() - t0
                if isinstance(steps, tuple):  # (steps, seconds): a replay of the run's chunks timed itself
                    steps, seconds = steps
                spent[key] += seconds
                n = steps if isinstance(steps, int) and not isinstance(steps, bool) and steps > 0 else 1
                times[key][i].append(seconds / n)
            if r + 1 >= min(MIN_REPEATS, repeats) and spent[key] >= max_seconds:
                active.remove(key)
        if not active:
            break
    return times


def summarize_times(values: Sequence[float]) -> dict[str, Any]:
    """Median, quartiles and extremes of one program's timings (seconds), and their count."""
    q = statistics.quantiles(values, n=4, method="inclusive") if len(values) > 1 else [values[0]] * 3
    return {"seconds": statistics.median(values), "q25": q[0], "q75": q[2], "low": min(values), "high": max(values),
            "rounds": len(values)}  # fmt: skip


def fingerprint(config: RunConfig) -> str:
    """What a calibration is valid for: the run's configuration with seed 0 and no budget
    (the problem, its settings, every stage's method, hyperparameters and batch size)."""
    untimed = dataclasses.replace(config.settings, eval_every=0, eval_seconds=0.0)
    return dataclasses.replace(config, seed=0, budget=Steps(1), settings=untimed).digest()


def step_programs(
    config: RunConfig, devices: int | str | None = 1, clock: Callable[[], float] = time.perf_counter
) -> tuple[list[Program], list[float], list[Any]]:
    """Each stage's compiled training step of ``config`` as a no-argument program, the
    seconds spent compiling and warming up each, and the stages (the engine's
    :class:`~physgrad.engine.types.Stage`). Built with the engine's
    :class:`~physgrad.engine.step.Steps`, so the program is the one the run uses (and finds
    in :data:`physgrad.engine.programs.STEPS` instead of compiling it again); the memory guard
    checks it as in a run. Call inside :func:`physgrad.precision.float64_scope` where the
    problem needs float64 (:func:`calibrate` does)."""
    import jax
    import numpy as np

    from .. import distributed
    from ..engine.step import Steps
    from ..engine.strategies import Placement
    from ..engine.types import TrainState
    from .objects import devices as edge_devices
    from .run_chunks import Bookkeeping, Replay, chunk_cycle, epoch_inputs
    from .train import build, settings_of

    setup = build(config)
    placement = Placement(edge_devices(devices))
    params = placement.put(setup.params)
    steps = Steps(setup, placement, settings_of(config), config.seed)
    programs, warmups = [], []
    for i, stage in enumerate(setup.stages):
        opt_state = placement.put(stage.method.init(setup.params))
        state = TrainState(params, opt_state, stage=i)
        t0 = time.perf_counter()
        with placement.scope():
            compiled, _ = steps.compile(state, setup)
            order = steps.order(i, 0)
            # the run's chunked program (engine.step.make_steps), first asked for one step
            chunk = functools.partial(compiled, params, opt_state, steps.data, order, np.int32(0))
            jax.block_until_ready(chunk(np.int32(1)))  # the first call: warm-up, not timed
        warmups.append(time.perf_counter() - t0)
        # the run's own chunks between evaluations, replayed (harness.run_chunks), sized at this step's cost
        count = sized_chunk(lambda n, chunk=chunk: _chunk_call(chunk, np.int32(n)), compiled.chunk)
        t0 = time.perf_counter()
        done = _chunk_call(chunk, np.int32(count))
        per_step = (time.perf_counter() - t0) / max(done, 1)
        # a calibrated run evaluates eval_seconds as eval_every steps (study.calibrated_config)
        every = (max(1, round(config.settings.eval_seconds / per_step)) if config.settings.eval_seconds > 0
                 else config.settings.eval_every)  # fmt: skip
        cycle = chunk_cycle(steps_per_epoch=stage.steps_per_epoch, epoch_end=not steps.same_every_epoch, per_step=per_step,
                            stage_steps=stage.steps, program_chunk=compiled.chunk, eval_every=every, eval_seconds=0.0)  # fmt: skip
        programs.append(Replay(
            lambda p, s, d, o, b, c, compiled=compiled: compiled(p, s, d, o, np.int32(b), np.int32(c)),
            lambda result: jax.device_get(distributed.to_host(result)),
            lambda epoch, i=i: epoch_inputs(steps, setup, i, epoch), (params, opt_state), [c for c, _ in cycle],
            same_every_epoch=steps.same_every_epoch, call_seconds=CALL_SECONDS, clock=clock,
            between=Bookkeeping(setup, settings_of(config), placement), evaluated=[e for _, e in cycle]))  # fmt: skip
    return programs, warmups, list(setup.stages)


def sized_chunk(
    call: Callable[[int], int],
    longest: int | None = None,
    tries: int = 4,
    clock: Callable[[], float] = time.perf_counter,
) -> int:
    """The steps per timed call: grown from one step until a call takes about
    :data:`CALL_SECONDS` (:func:`chunk_steps` from each call's seconds per step; a call of
    one step is mostly dispatch, so the first estimate is short and is measured again), at
    most ``longest`` (the run's longest chunk in the stage) and CHUNK."""
    count = 1
    for _ in range(tries):
        t0 = clock()
        done = max(call(count), 1)
        seconds = clock() - t0
        grown = chunk_steps(seconds / done)
        grown = min(grown, longest) if longest else grown
        if grown <= count or seconds >= CALL_SECONDS / 2:
            break
        count = grown
    return count


def chunk_steps(seconds_per_step: float) -> int:
    """How many steps one timed call takes: enough for :data:`CALL_SECONDS` at the measured
    seconds per step (at most the run's chunk, :data:`physgrad.engine.step.CHUNK`).

    Why: a run takes its steps in chunks of up to 1,024 per dispatch, so a step below a
    millisecond costs the run its compiled work plus a share of one dispatch. A one-step
    call adds a whole dispatch and host round trip (0.1–0.6 ms on a CPU) to every step: it
    read a 0.07 ms Adam step on ``hig_toy`` as 0.67 ms, and cheap methods' steps as more
    alike than they are."""
    from ..engine.step import CHUNK

    if not math.isfinite(seconds_per_step) or seconds_per_step <= 0:
        return 1
    return int(min(CHUNK, max(1, math.ceil(CALL_SECONDS / seconds_per_step))))


def _chunk_call(chunk: Callable[[Any], Any], count: Any) -> int:
    """One timed call of a chunk of ``count`` steps; the steps it computed (those applied,
    and a divergent one where the chunk stopped at it) for :func:`time_programs`."""
    import jax

    _, _, taken, diverged, _ = jax.block_until_ready(chunk(count))
    return int(taken) + int(bool(diverged))


def calibrate(
    configs: Mapping[str, RunConfig],
    *,
    repeats: int = REPEATS,
    max_seconds: float = MAX_SECONDS,
    devices: int | str | None = 1,
    echo: Callable[[str], None] = print,
    clock: Callable[[], float] | None = None,
    programs: Callable[[RunConfig], tuple[list[Program], list[float], list[Any]]] | None = None,
    record_failures: bool = False,
) -> dict[str, Any]:
    """Time every method of ``configs`` (``{method spec: its seed-0 run configuration}``,
    one problem) and return the calibration record (``calibration.json``'s contents).

    ``programs`` builds a configuration's step programs (default :func:`step_programs`; a
    test passes fakes with a fake ``clock``). With ``record_failures`` a method whose step
    cannot be built (the memory guard's refusal, a crash) is recorded with its error and
    the others are timed; otherwise the error stops the calibration. ``clock``: the timer
    (None: :data:`CLOCKS`' entry named by ``$PHYSGRAD_CALIBRATION_CLOCK``, default wall-clock)."""
    rundir.fault("calibrating")  # test hook: a signal while a study calibrates
    from ..cpu import report
    from ..precision import float64_scope
    from .failures import recordable
    from .train import problem_of

    name = "custom" if clock is not None else clock_name()
    timer = clock if clock is not None else CLOCKS[name]
    build = programs or (lambda c: step_programs(c, devices, clock=timer))
    entries: dict[str, dict[str, Any]] = {}
    built: dict[str, tuple[list[Program], list[float], list[Any]]] = {}
    before = load()
    first = next(iter(configs.values()), None)
    needs64 = first is not None and programs is None and problem_of(first).needs_float64
    with float64_scope(needs64) if needs64 else contextlib.nullcontext():
        for spec, config in configs.items():
            try:
                built[spec] = build(config)
            except Exception as e:
                if not (record_failures and recordable(e)):
                    raise
                entries[spec] = {"fingerprint": fingerprint(config), "stages": [], "error": f"{type(e).__name__}: {e}"}
                echo(f"calibration: {spec}: could not build its step ({entries[spec]['error']})")
        times = time_programs({k: v[0] for k, v in built.items()}, repeats=repeats, max_seconds=max_seconds,
                              clock=timer)  # fmt: skip
    for spec, (programs_of_spec, warmups, stages) in built.items():
        config = configs[spec]
        costs = []
        for i, (phase, values) in enumerate(zip(config.phases, times[spec])):
            stage = stages[i] if i < len(stages) else None
            batch = getattr(stage, "batch_size", phase.batch_size)
            costs.append(StageCost(method=phase.method, batch_size=int(batch), steps=phase.steps,
                                   route=str(phase.hyperparameters.get("route", "")), compile_seconds=warmups[i],
                                   steps_per_call=int(getattr(programs_of_spec[i], "steps_per_call", 1)),
                                   **summarize_times(values)))  # fmt: skip
        entries[spec] = {"fingerprint": fingerprint(config), "stages": [dataclasses.asdict(c) for c in costs],
                         "error": None}  # fmt: skip
    threads = report()
    setting = threads.get("setting")
    return {
        "version": VERSION,
        "problem": first.problem if first is not None else None,
        "measured": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "machine": machine() if programs is None else {},
        "load_before": before,
        "load_after": load(),
        "threads": setting.get("requested") if isinstance(setting, dict) else setting,  # None: the libraries' own
        "thread_pools": threads,
        "devices": devices,
        "rule": RULE,
        "clock": name,
        "repeats": repeats,
        "max_seconds": max_seconds,
        "methods": entries,
    }


class Calibration:
    """A study's calibration record, read: each method's stage costs, its step budget for
    a number of seconds, and the calibrated time after a number of steps."""

    def __init__(self, record: dict[str, Any]):
        self.record = record

    def stages(self, spec: str) -> list[StageCost]:
        entry = self.record["methods"].get(spec) or {}
        return [StageCost(**s) for s in entry.get("stages", [])]

    def has(self, spec: str) -> bool:
        return bool(self.stages(spec))

    def steps(self, spec: str, seconds: float) -> int:
        return steps_for(seconds, self.stages(spec))

    def time_at(self, spec: str, step: float) -> float:
        stages = self.stages(spec)
        return time_at(step, stages) if stages else math.nan

    def seconds_per_step(self, spec: str) -> float:
        """The last stage's calibrated seconds per step (the one a budget is spent on)."""
        stages = self.stages(spec)
        return stages[-1].seconds if stages else math.nan

    def error(self, spec: str) -> str | None:
        return (self.record["methods"].get(spec) or {}).get("error")


def read(out: str | Path) -> Calibration | None:
    """A study directory's calibration, or None where it has none."""
    path = Path(out) / CALIBRATION_FILE
    if not path.exists():
        return None
    try:
        return Calibration(json.loads(path.read_text()))
    except (OSError, ValueError):
        raise ConfigError(f"{path} cannot be read; move it away to calibrate again") from None


def study_calibration(
    out: str | Path,
    configs: Mapping[str, RunConfig],
    *,
    echo: Callable[[str], None] = print,
    devices: int | str | None = 1,
    record_failures: bool = False,
    **options: Any,
) -> Calibration:
    """The calibration of a study in ``out``: the recorded one where it covers every method
    of ``configs`` with the same configuration (a resumed study does not time again); the
    methods it lacks (new, or configured differently) are timed now, together, and added.
    Written as ``calibration.json`` and ``calibration.csv``."""
    out = Path(out)
    old = read(out)
    record = old.record if old is not None else None
    # Every configuration ever timed here, by its fingerprint (two studies sharing one --out
    # keep their own measurements); "methods" maps this study's names to theirs.
    timed = dict((record or {}).get("by_fingerprint") or {})
    for entry in ((record or {}).get("methods") or {}).values():  # a record written before by_fingerprint
        if entry.get("fingerprint") and entry.get("stages"):
            timed.setdefault(entry["fingerprint"], entry)
    prints = {spec: fingerprint(c) for spec, c in configs.items()}
    missing = {spec: c for spec, c in configs.items() if not (timed.get(prints[spec]) or {}).get("stages")}
    if not missing:
        view = {**record, "by_fingerprint": timed, "methods": {spec: timed[prints[spec]] for spec in configs}}  # type: ignore[arg-type]
        echo(f"calibration: reusing {out / CALIBRATION_FILE} (measured {record['measured']})")  # type: ignore[index]
        if view != record:  # this study's names now point at its own measurements
            rundir.atomic_write(out / CALIBRATION_FILE, json.dumps(view, indent=2, default=str) + "\n")
            write_csv(out / CALIBRATION_CSV, csv_rows(Calibration(view), list(configs)))
        return Calibration(view)
    echo(f"calibration: timing the compiled step of {', '.join(missing)} (interleaved rounds, median; "
         "compilation excluded)")  # fmt: skip
    if record is not None and "clock" not in options:
        # a study keeps one timer: the methods it adds are timed with its record's clock
        kept = record.get("clock", "wall")
        options["clock"] = CLOCKS.get(kept, time.perf_counter)
        if kept != clock_name():
            echo(f"calibration: {out / CALIBRATION_FILE} was timed with the {kept} clock; {', '.join(missing)} "
                 f"are timed with it too (${CLOCK_VARIABLE} applies to a new study)")  # fmt: skip
    fresh = calibrate(missing, echo=echo, devices=devices, record_failures=record_failures, **options)
    if record is not None and fresh.get("clock") == "custom":
        fresh["clock"] = record.get("clock", "wall")
    if record is not None:  # keep the earlier measurements, with their own conditions
        if record.get("version", 1) != VERSION:
            echo(f"calibration: {out / CALIBRATION_FILE} was timed by an earlier rule (version {record.get('version', 1)}); "
                 f"{', '.join(missing)} are timed as the run's own chunks between evaluations, so their costs are not "
                 "comparable to the recorded ones (move the file away to time every method again)")  # fmt: skip
        stamped = {k: {**v, "measured": fresh["measured"], "load": fresh["load_before"], "version": VERSION}
                   for k, v in fresh["methods"].items()}  # fmt: skip
        fresh = {**record, "methods": stamped}
    timed.update({prints[spec]: entry for spec, entry in fresh["methods"].items() if entry.get("stages")})
    fresh["by_fingerprint"] = timed
    fresh["methods"] = {spec: timed.get(prints[spec]) or fresh["methods"].get(spec) or {} for spec in configs}
    rundir.atomic_write(out / CALIBRATION_FILE, json.dumps(fresh, indent=2, default=str) + "\n")
    calibration = Calibration(fresh)
    write_csv(out / CALIBRATION_CSV, csv_rows(calibration, list(configs)))
    for spec in missing:
        if calibration.has(spec):
            costs = ", ".join(f"{s.method} {1e3 * s.seconds:.3g} ms/step [{1e3 * s.q25:.3g}, {1e3 * s.q75:.3g}]"
                              for s in calibration.stages(spec))  # fmt: skip
            echo(f"calibration: {spec}: {costs} ({calibration.stages(spec)[-1].rounds} rounds)")
    return calibration
