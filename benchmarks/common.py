"""What the step benchmarks share: the command line, one compiled training step, timing."""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import physgrad  # noqa: F401  (float64 on)
from physgrad import Budget
from physgrad.config import make_config
from physgrad.train import build, make_step


def benchmark_parser(description: str, default_problem: str) -> argparse.ArgumentParser:
    """--problem, --batch-size, --repeats and --set, as every step benchmark takes them."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--problem", default=default_problem)
    parser.add_argument("--batch-size", type=int, default=None, help="one batch size for every method")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    return parser


def settings_from(args: argparse.Namespace) -> dict[str, str]:
    """The --set pairs, with --batch-size as the batch_size setting."""
    settings = dict(s.split("=", 1) for s in args.set)
    if args.batch_size:
        settings["batch_size"] = str(args.batch_size)
    return settings


def training_step(problem: str, method: str, settings: dict[str, str]):
    """(config, setup, step, step_args): the engine's jitted step on batch 0 of the train split."""
    config = make_config(problem, method, budget=Budget(steps=1), settings=settings)
    setup = build(config)
    data = setup.data["train"]
    order = jnp.arange(jax.tree.leaves(data)[0].shape[0], dtype=jnp.int32)
    step = make_step(setup, config.phases[0].batch_size)
    return config, setup, step, (setup.params, setup.method.init(setup.params), data, order, jnp.int32(0))


def median_seconds(fn, args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # compile and warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)
