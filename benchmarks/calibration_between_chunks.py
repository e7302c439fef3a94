"""What the run's work between two chunks adds to the next chunk's CPU seconds (issue 50, item 4).

A run times each chunk of steps from its dispatch to its read-back. Between two chunks it
does work that is not timed: it adds up the step statistics, evaluates and appends the
metrics rows, and saves a checkpoint after every evaluation. The chunk that follows still
pays for some of that work. Two parts, each in one process, on the CPU clock the runs use
(``physgrad.engine.cpu_clock.run_cpu_time``):

``after``: one chunk of the run's compiled program, timed as ``engine.run.loop`` times it,
after each kind of untimed work: none (back to back), the evaluation alone, the
``Recorder`` (the evaluation and its metrics row), the checkpoint, and both. ``--pairs`` of
each, in random order.

``versions``: the calibration's replay of the run's chunks (``harness.run_chunks.Replay``)
with the run's work between chunks (version 4, ``Bookkeeping``) against one with only the
evaluations (version 3). Interleaved calls on the same compiled program
(``harness.calibration.time_programs``), ``--rounds`` each.

    python benchmarks/calibration_between_chunks.py after hig_toy adam [--pairs 150]
    python benchmarks/calibration_between_chunks.py versions oscillators hig [--rounds 30]

On ``oscillators`` the demo's settings are used: an evaluation every 64 steps, GN and HIG at
batch 32. Print the load beside every number.
"""

from __future__ import annotations

import argparse
import copy
import os
import random
import statistics
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from physgrad import distributed
from physgrad.engine.cpu_clock import run_cpu_time
from physgrad.engine.recording import Checkpointer, MetricsLog, Recorder
from physgrad.engine.step import Steps
from physgrad.engine.strategies import Fidelity, Placement
from physgrad.engine.types import Steps as StepsBudget
from physgrad.engine.types import TrainState
from physgrad.harness.calibration import step_programs, time_programs
from physgrad.harness.study.running import plan
from physgrad.harness.train import build, settings_of


def config_of(problem: str, method: str):
    """The seed-0 configuration; on the oscillators the demo's settings."""
    settings = {}
    if problem == "oscillators":
        settings = {"eval_every": "64", **({f"{method}.batch_size": "32"} if method in ("gn", "hig") else {})}
    return plan(problem, [method], [0], StepsBudget(1), settings)[0]


def after(problem: str, method: str, pairs: int) -> None:
    config = config_of(problem, method)
    settings = settings_of(config)
    setup, placement = build(config), Placement(1)
    steps = Steps(setup, placement, settings, 0)
    state = TrainState(placement.put(setup.params), placement.put(setup.method.init(setup.params)))
    compiled, state = steps.compile(state, setup)
    order = steps.order(0, 0)
    count = min(compiled.chunk, setup.stages[0].steps_per_epoch, settings.eval_every or 10**9)
    directory = Path(tempfile.mkdtemp(prefix="between-chunks-"))
    fidelity = Fidelity.of(setup.problem, settings)
    recorder = Recorder(setup, settings=settings, placement=placement, fidelity=fidelity,
                        log=MetricsLog(directory / "metrics.csv"))  # fmt: skip
    checkpointer = Checkpointer(directory, settings.checkpoint_seconds, True)
    splits = [*recorder.splits.values(), *([recorder.val] if recorder.val is not None else [])]

    def evaluate(s):
        with placement.scope():
            for data in splits:
                {k: float(v) for k, v in recorder.evaluate(s.params, data).items()}
        return s

    def chunk(s):  # as engine.run.loop times it
        start = run_cpu_time()
        params, opt_state, taken, diverged, stats = compiled(s.params, s.opt_state, steps.data, order, np.int32(0),
                                                             np.int32(count))  # fmt: skip
        taken, diverged, stats = jax.device_get(distributed.to_host((taken, diverged, stats)))
        seconds = run_cpu_time() - start
        s = recorder.accumulate(s, stats, int(taken))._replace(
            params=params, opt_state=opt_state, step=s.step + int(taken)
        )
        return s, seconds / max(int(taken), 1)

    work = {
        "back to back": lambda s: s,
        "evaluation": evaluate,
        "Recorder": lambda s: recorder(s, final=False)[0],
        "checkpoint": lambda s: (checkpointer.save(s), s)[1],
        "Recorder+checkpoint": lambda s: (lambda r: (checkpointer.save(r), r)[1])(recorder(s, final=False)[0]),
    }
    for _ in range(5):
        state, _ = chunk(state)
    kinds = [k for k in work for _ in range(pairs)]
    random.Random(0).shuffle(kinds)
    seconds: dict[str, list[float]] = {k: [] for k in work}
    load = os.getloadavg()
    for kind in kinds:
        state, per_step = chunk(work[kind](state))
        seconds[kind].append(per_step)
    print(f"{problem} {method}: a chunk of {count} steps after each kind of work, {pairs} of each; "
          f"load {load[0]:.1f} -> {os.getloadavg()[0]:.1f}")  # fmt: skip
    base = statistics.median(seconds["back to back"])
    for kind, values in seconds.items():
        median = statistics.median(values)
        print(f"  {kind:20} CPU ms/step median {1e3 * median:.4f} ({median / base:.2f}x back to back)")


def versions(problem: str, method: str, rounds: int) -> None:
    config = config_of(problem, method)
    (new,), _, _ = step_programs(config, clock=run_cpu_time)
    recorder = new.between.recorder
    splits = [*recorder.splits.values(), *([recorder.val] if recorder.val is not None else [])]

    def evaluations_only(params, opt_state, stats, taken, evaluated):
        if evaluated:
            with recorder.placement.scope():
                for data in splits:
                    {k: float(v) for k, v in recorder.evaluate(params, data).items()}

    old = copy.copy(new)
    old.between = evaluations_only
    load = os.getloadavg()
    t0 = time.perf_counter()
    times = time_programs({"4": [new], "3": [old]}, repeats=rounds, max_seconds=1e9, clock=run_cpu_time)
    v4, v3 = (statistics.median(times[k][0]) for k in ("4", "3"))
    paired = statistics.median(a / b for a, b in zip(times["4"][0], times["3"][0]))
    print(f"{problem} {method}: chunks {[c for *_, c in new.chunks][:6]}..., evaluated after "
          f"{sum(new.evaluated)} of {len(new.evaluated)}; {rounds} interleaved calls each in {time.perf_counter() - t0:.0f} s, "
          f"load {load[0]:.1f} -> {os.getloadavg()[0]:.1f}")  # fmt: skip
    print(f"  version 4 (the run's work between chunks) {1e3 * v4:.4f} CPU ms/step, version 3 (evaluations only) "
          f"{1e3 * v3:.4f}: {v4 / v3:.3f}x (median of the paired ratios {paired:.3f})")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("part", choices=["after", "versions"])
    parser.add_argument("problem")
    parser.add_argument("method")
    parser.add_argument("--pairs", type=int, default=150, help="after: chunks after each kind of work")
    parser.add_argument("--rounds", type=int, default=60, help="versions: interleaved calls of each")
    args = parser.parse_args()
    if args.part == "after":
        after(args.problem, args.method, args.pairs)
    else:
        versions(args.problem, args.method, args.rounds)


if __name__ == "__main__":
    main()
