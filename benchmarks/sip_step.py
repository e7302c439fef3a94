"""Median time per training step of SIP (each applicable local inverse solver) against Adam.

The SIP book chapter reports SIP at about 3× Adam's time per iteration on the sine problem
(sip.md §2.4, §6); this prints, for one problem, each step's median time and its ratio to
Adam's step measured in the same run (same batch size, same network).

    python benchmarks/sip_step.py [--problem sine] [--solvers analytic,gauss_newton,...]
                                  [--batch-size B] [--repeats 30] [--set name=value ...]
"""

from __future__ import annotations

import argparse
import platform

import jax
import jax.numpy as jnp

import physgrad  # noqa: F401  (float64 on)
from hig_step import median_seconds
from physgrad import Budget, make_config
from physgrad.config import ConfigError
from physgrad.train import build, make_step

DEFAULT_SOLVERS = {
    "sine": "saddle_free_newton,gauss_newton,lbfgs",
    "exp_inverse": "analytic,gauss_newton,lbfgs,linear_solve",
    "linear_oscillators": "gauss_newton,linear_solve",
    "poisson": "analytic,linear_solve",
    "heat": "analytic",
    "toy2d": "analytic,gauss_newton,saddle_free_newton,lbfgs",
}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="sine")
    parser.add_argument("--solvers", help="comma-separated (default: those that apply to the problem)")
    parser.add_argument("--batch-size", type=int, default=None, help="one batch size for every method")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    settings = dict(s.split("=", 1) for s in args.set)
    if args.batch_size:
        settings["batch_size"] = str(args.batch_size)
    solvers = (args.solvers or DEFAULT_SOLVERS.get(args.problem, "auto")).split(",")
    # linear_solve on the Poisson problem: P = ∇⁻² is symmetric negative definite, and CG on
    # its condition number (≈ 1,700) stalls in float32; the oscillators' J is 4 × 24.
    krylov = {
        "poisson": {"krylov": "cg_negative", "precision": "float64", "max_steps": "300"},
        "linear_oscillators": {"krylov": "normal_cg"},
    }.get(args.problem, {"krylov": "gmres"})

    cases = [("adam", {})] + [("sip", {"solver": s, **(krylov if s == "linear_solve" else {})}) for s in solvers]
    rows = []
    for method, extra in cases:
        try:
            config = make_config(args.problem, method, budget=Budget(steps=1), settings={**settings, **extra})
            setup = build(config)
        except ConfigError as e:
            rows.append((method, extra.get("solver", ""), None, str(e)))
            continue
        state = setup.method.init(setup.params)
        data = setup.data["train"]
        order = jnp.arange(jax.tree.leaves(data)[0].shape[0], dtype=jnp.int32)
        step = make_step(setup, config.phases[0].batch_size)
        t = median_seconds(step, (setup.params, state, data, order, jnp.int32(0)), args.repeats)
        stats = step(setup.params, state, data, order, jnp.int32(0))[2]
        failed = f", {int(stats['inverse_failures'])} failed solves" if "inverse_failures" in stats else ""
        rows.append((method, extra.get("solver", ""), t, f"batch {config.phases[0].batch_size}{failed}"))

    adam = rows[0][2]
    print(f"{args.problem}: median seconds per training step, {args.repeats} repeats "
          f"({platform.processor() or platform.machine()}, {jax.devices()[0].platform}, jax {jax.__version__})")  # fmt: skip
    print(f"{'method':<8} {'solver':<20} {'ms/step':>10} {'/ adam':>8}  note")
    for method, solver, t, note in rows:
        if t is None:
            print(f"{method:<8} {solver:<20} {'-':>10} {'-':>8}  {note}")
        else:
            print(f"{method:<8} {solver:<20} {1e3 * t:>10.3f} {t / adam:>8.2f}  {note}")


if __name__ == "__main__":
    main()
