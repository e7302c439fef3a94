"""The run's compiled steps against the bare step, per step, back to back in one process.

The engine dispatches its steps in chunks of a ``lax.while_loop`` (``engine.step.make_steps``)
so that a sub-millisecond step is not dominated by a dispatch; on a CPU, XLA runs a
convolution inside a loop body 5–70× slower than outside one (``engine.step.loop_chunk``),
so for a convolutional step the run compiles the step alone. Three programs per problem:

- ``bare``: the jitted step, one call per step (the floor: ``engine.step.make_step``);
- ``run``: the program the run compiles (``Steps.compile``), one call of one step;
- ``loop``: the chunked program forced (``make_steps`` with its full chunk), one step per call:
  what every run used before the convolution rule (a heat U-Net step 5.6 s → 57 s).

Prints ms per step (median of ``--repeats``) and the ratios run/bare and loop/bare. For a
convolutional problem on a CPU run/bare should read ≈1 and loop/bare shows the slowdown
avoided; for a dense problem the run keeps its loop (its chunk column reads 1024).

    taskset -c 0 python benchmarks/loop_step.py [--problems heat,ks,oscillators] [--repeats 3]
"""

from __future__ import annotations

import argparse

import jax
import numpy as np
from common import median_seconds, problem_precision, training_step

from physgrad.engine.step import CHUNK, Steps, make_steps
from physgrad.engine.strategies import Placement
from physgrad.engine.types import TrainState
from physgrad.harness.train import settings_of

# small data splits, so a problem builds in seconds (the step's cost does not depend on them)
SETTINGS = {"heat": {"n_train": "256", "n_test": "16"}, "poisson": {"n_train": "256", "n_test": "16"}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", default="heat,ks,oscillators")
    parser.add_argument("--method", default="adam")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"jax {jax.__version__}, backend {jax.default_backend()}; ms per step, median of {args.repeats}")
    print(f"{'problem':14s} {'chunk':>5s} {'bare':>10s} {'run':>10s} {'loop':>10s} {'run/bare':>9s} {'loop/bare':>9s}")
    for name in args.problems.split(","):
        with problem_precision(name, SETTINGS.get(name, {})):  # as the run trains it (heat: float64)
            config, setup, step, step_args = training_step(name, args.method, SETTINGS.get(name, {}))
            batch_size = config.phases[0].batch_size
            steps = Steps(setup, Placement(), settings_of(config), 0)
            program, _ = steps.compile(TrainState(setup.params, setup.method.init(setup.params)), setup)
            loop = make_steps(setup, batch_size, setup.method, CHUNK)
            chunk_args = (*step_args, np.int32(1))
            bare = median_seconds(step, step_args, args.repeats)
            run = median_seconds(program, chunk_args, args.repeats)
            looped = median_seconds(loop, chunk_args, args.repeats)
        print(f"{name:14s} {program.chunk:5d} {bare * 1e3:10.2f} {run * 1e3:10.2f} {looped * 1e3:10.2f} "
              f"{run / bare:9.2f} {looped / bare:9.2f}")  # fmt: skip


if __name__ == "__main__":
    main()
