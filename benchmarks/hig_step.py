"""Time and memory per HIG / Gauss–Newton step, every half-inverse route against its floor.

For each problem of the half-inverse paper at its paper batch (or ``--batch-size``), in
one process and back to back: the floor of an exact half-inverse step (one backward pass
per Jacobian row to the pre-activations + the float64 ``eigh`` of the m × m Gram matrix,
``common.half_inverse_floor``), then one training step of ``adam`` and of ``hig`` with
each route: median seconds, the ratio to the floor, the ratio to the ``gram`` route, and
XLA's memory of the compiled step.

    python benchmarks/hig_step.py [--problems oscillators,poisson_hig] [--routes gram,structured]
                                  [--batch-size B] [--repeats 5] [--set name=value ...]
"""

from __future__ import annotations

import argparse
import platform

import jax
from common import half_inverse_floor, median_seconds, settings_from, step_bytes, training_step

import physgrad

PROBLEMS = ("hig_toy", "oscillators", "quantum_dipole", "poisson_hig")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", default=",".join(PROBLEMS))
    parser.add_argument("--routes", default="gram,structured,svd")
    parser.add_argument("--method", default="hig", choices=("hig", "gn"))
    parser.add_argument("--batch-size", type=int, default=None)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    base = settings_from(args)

    print(f"physgrad {physgrad.__version__} | jax {jax.__version__} | {jax.devices()[0]} | "
          f"{platform.processor() or platform.machine()}; median of {args.repeats} steps")  # fmt: skip
    print("| problem | batch | J rows × P | step | ms/step | × floor | × gram | XLA MiB |")
    print("|---|---|---|---|---|---|---|---|")
    for problem in args.problems.split(","):
        config, setup, step, step_args = training_step(problem, args.method, base)
        b = config.phases[0].batch_size
        floor = half_inverse_floor(setup, b, args.repeats)
        shape = f"{floor['rows']:,} × {floor['P']:,}"
        print(
            f"| {problem} | {b} | {shape} | floor: backward to pre-activations | {floor['backward'] * 1e3:.1f} | | | |"
        )
        print(f"| {problem} | {b} | {shape} | floor: eigh({floor['m']}) float64 | {floor['eigh'] * 1e3:.1f} | | | |")
        cases = [("adam", {})] + [(args.method, {"route": r}) for r in args.routes.split(",")]
        gram = None
        for method, extra in cases:
            _, _, step, step_args = training_step(problem, method, {**base, "batch_size": str(b), **extra})
            t = median_seconds(step, step_args, args.repeats)
            gram = t if extra.get("route") == "gram" else gram
            label = method + (f" ({extra['route']})" if extra else "")
            vs_gram = f"{t / gram:.2f}" if gram and extra else ""
            print(f"| {problem} | {b} | {shape} | {label} | {t * 1e3:.1f} | {t / floor['floor']:.2f} | {vs_gram} | "
                  f"{step_bytes(step, step_args) / 2**20:.1f} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
