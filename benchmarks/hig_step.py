"""Median time per training step of adam, gn and hig (both half-inverse routes) on `oscillators`.

Prints one table from one run: each step's median time, and its ratio to the cost floor of
the curvature methods, the per-sample Jacobian alone (vmap(jacrev) at the same batch).

    python benchmarks/hig_step.py [--batch-size 128] [--repeats 30] [--set name=value ...]
"""

from __future__ import annotations

import platform

import jax

import physgrad
from common import benchmark_parser, median_seconds, settings_from, training_step
from physgrad.jacobian import stacked_jacobian


def main():
    args = benchmark_parser(__doc__.splitlines()[0], "oscillators").parse_args()
    settings = settings_from(args)

    cases = [("adam", {}), ("gn", {"route": "gram"}), ("hig", {"route": "svd"}), ("hig", {"route": "gram"})]
    rows, jac_time = [], {}
    for method, extra in cases:
        config, setup, step, step_args = training_step(args.problem, method, {**settings, **extra})
        t_step = median_seconds(step, step_args, args.repeats)
        b = config.phases[0].batch_size
        if b not in jac_time:
            batch = jax.tree.map(lambda a: a[:b], setup.data["train"])
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
