"""Median time per training step of SIP (each applicable local inverse solver) against Adam.

The PBDL book (Thuerey et al., *Physics-based Deep Learning*, arXiv:2109.05237), in its
chapter on SIP training, reports SIP at about 3× Adam's time per iteration on the rotated
sine problem of Holl, Koltun & Thuerey (NeurIPS 2022, Fig. 5), because of the per-sample
Hessian evaluation of its saddle-free Newton inverse; this prints, for one problem, each
step's median time and its ratio to Adam's step measured in the same run (same batch size,
same network).

    python benchmarks/sip_step.py [--problem sine] [--solvers analytic,gauss_newton,...]
                                  [--batch-size B] [--repeats 30] [--set name=value ...]
                                  [--vary name=v1,v2]

``--vary`` repeats every case for each value of one problem setting, back to back in the
same process, with ratios to Adam at the first value: e.g. the Navier–Stokes step with
physgrad's JAX solver and with the same step written in PhiFlow,

    python benchmarks/sip_step.py --problem navier_stokes --set n_train=64 --repeats 5 \
        --vary simulator=jax,phiflow
"""

from __future__ import annotations

import platform

import jax
from common import benchmark_parser, median_seconds, problem_precision, settings_from, training_step

from physgrad.harness.config import ConfigError

DEFAULT_SOLVERS = {
    "sine": "saddle_free_newton,gauss_newton,lbfgs",
    "exp_inverse": "analytic,gauss_newton,lbfgs,linear_solve",
    "linear_oscillators": "gauss_newton,linear_solve",
    "poisson": "analytic,linear_solve",
    "heat": "analytic",
    "toy2d": "analytic,gauss_newton,saddle_free_newton,lbfgs",
    "navier_stokes": "analytic",
}


def main():
    parser = benchmark_parser(__doc__.splitlines()[0], "sine")
    parser.add_argument("--solvers", help="comma-separated (default: those that apply to the problem)")
    parser.add_argument("--vary", metavar="NAME=V1,V2", help="repeat every case for each value of one setting")
    args = parser.parse_args()
    base = settings_from(args)
    name, values = args.vary.split("=", 1) if args.vary else (None, "")
    variants = [{**base, name: v} for v in values.split(",")] if name else [base]
    solvers = (args.solvers or DEFAULT_SOLVERS.get(args.problem, "auto")).split(",")
    # linear_solve on the Poisson problem: P = ∇⁻² is symmetric negative definite, and CG on
    # its condition number (≈ 1,700) stalls in float32; the oscillators' J is 4 × 24.
    krylov = {
        "poisson": {"krylov": "cg_negative", "precision": "float64", "max_steps": "300"},
        "linear_oscillators": {"krylov": "normal_cg"},
    }.get(args.problem, {"krylov": "gmres"})

    cases = [("adam", {})] + [("sip", {"solver": s, **(krylov if s == "linear_solve" else {})}) for s in solvers]
    rows = []
    for settings in variants:
        label = f", {name}={settings[name]}" if name else ""
        for method, extra in cases:
            try:
                with problem_precision(args.problem, settings):  # heat computes in float64
                    config, _, step, step_args = training_step(args.problem, method, {**settings, **extra})
                    t = median_seconds(step, step_args, args.repeats)
                    stats = step(*step_args)[2]
            except ConfigError as e:
                rows.append((method, extra.get("solver", ""), None, str(e) + label))
                continue
            failed = f", {int(stats['inverse_failures'])} failed solves" if "inverse_failures" in stats else ""
            rows.append((method, extra.get("solver", ""), t, f"batch {config.phases[0].batch_size}{failed}{label}"))

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
