"""Median time per training step of adam, gn and hig (both half-inverse routes) on `oscillators`.

Prints one table from one run: each step's median time, and its ratio to the cost floor of
the curvature methods, the per-sample Jacobian alone (vmap(jacrev) at the same batch).

    python benchmarks/hig_step.py [--batch-size 128] [--repeats 30] [--set name=value ...]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import jax
import jax.numpy as jnp

import physgrad
from physgrad import Budget, make_config
from physgrad.jacobian import stacked_jacobian
from physgrad.train import build, make_step


def median_seconds(fn, args, repeats: int) -> float:
    jax.block_until_ready(fn(*args))  # compile and warm up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="oscillators")
    parser.add_argument("--batch-size", type=int, default=None, help="one batch size for every method")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    settings = dict(s.split("=", 1) for s in args.set)
    if args.batch_size:
        settings["batch_size"] = str(args.batch_size)

    cases = [("adam", {}), ("gn", {"route": "gram"}), ("hig", {"route": "svd"}), ("hig", {"route": "gram"})]
    rows, jac_time = [], {}
    for method, extra in cases:
        config = make_config(args.problem, method, budget=Budget(steps=1), settings={**settings, **extra})
        setup = build(config)
        state = setup.method.init(setup.params)
        data = setup.data["train"]
        order = jnp.arange(jax.tree.leaves(data)[0].shape[0], dtype=jnp.int32)
        step = make_step(setup, config.phases[0].batch_size)
        t_step = median_seconds(step, (setup.params, state, data, order, jnp.int32(0)), args.repeats)
        b = config.phases[0].batch_size
        if b not in jac_time:
            batch = jax.tree.map(lambda a: a[:b], data)
            jac = jax.jit(lambda p, x: stacked_jacobian(setup.objective.predict, p, x)[0])
            jac_time[b] = median_seconds(jac, (setup.params, batch), args.repeats)
            rows_j = jax.eval_shape(jac, setup.params, batch).shape
        label = method + (f" ({extra['route']})" if extra else "")
        rows.append((label, b, tuple(rows_j) if extra else "-", t_step, t_step / jac_time[b]))

    print(f"physgrad {physgrad.__version__} | jax {jax.__version__} | {jax.devices()[0]} | {platform.processor() or platform.machine()}")
    print(f"problem {args.problem}; median of {args.repeats} steps; settings {settings or 'paper defaults'}")
    print(f"{'step':<14}{'batch':>6}{'J shape':>14}{'ms/step':>10}{'x Jacobian':>12}")
    for b, t in jac_time.items():
        print(f"{'Jacobian only':<14}{b:>6}{'':>14}{t * 1e3:>10.2f}{1.0:>12.2f}")
    for label, b, shape, t, ratio in rows:
        print(f"{label:<14}{b:>6}{str(shape):>14}{t * 1e3:>10.2f}{ratio:>12.2f}")


if __name__ == "__main__":
    main()
