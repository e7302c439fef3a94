"""Time per training step of Kronecker-factored HIG (``khig``) against Adam, exact HIG and K-FAC.

For each problem at one batch size (64 by default), the engine's compiled step of ``adam``
(the floor: one forward and one backward pass), ``khig``, ``hig`` (its default route,
``auto``) and ``kfac``, each on its own paper/default settings but the same batch. The steps
are timed in interleaved rounds (adam, khig, hig, kfac, adam, …) so that a change in the
machine's load hits every method alike; exact HIG takes part in the first ``--hig-repeats``
rounds only (a step of seconds on the larger problems). Prints the median ms/step, its
ratio to Adam's median from the same rounds, and the load average before and after.

    taskset -c 0 python benchmarks/khig_step.py [--problems oscillators,quantum_dipole,poisson_hig]
                                                [--batch-size 64] [--repeats 15] [--hig-repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
from common import load_average, machine_line, settings_from, training_step, warmed_steps

PROBLEMS = ("oscillators", "quantum_dipole", "poisson_hig")
METHODS = ("adam", "khig", "hig", "kfac")


def main():
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--problems", default=",".join(PROBLEMS))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--hig-repeats", type=int, default=3)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    base = settings_from(args)
    methods = args.methods.split(",")

    print(f"{machine_line()} | load {load_average()}; median of {args.repeats} interleaved rounds "
          f"(hig: {args.hig_repeats})")  # fmt: skip
    print("| problem | batch | method | ms/step | × Adam |")
    print("|---|---|---|---|---|")
    for problem in args.problems.split(","):
        steps, refused = warmed_steps(methods, lambda method: training_step(problem, method, base)[1:])
        times: dict[str, list[float]] = {m: [] for m in steps}
        for r in range(args.repeats):
            for method, (_, step, step_args) in steps.items():
                if method == "hig" and r >= args.hig_repeats:
                    continue
                t0 = time.perf_counter()
                jax.block_until_ready(step(*step_args))
                times[method].append(time.perf_counter() - t0)
        medians = {m: statistics.median(t) for m, t in times.items()}
        floor = medians.get("adam")
        for method in methods:
            if method in refused:
                print(f"| {problem} | {args.batch_size} | {method} | refused: {refused[method]} | |")
                continue
            ratio = f"{medians[method] / floor:.1f}" if floor else ""
            print(f"| {problem} | {args.batch_size} | {method} | {medians[method] * 1e3:.2f} | {ratio} |", flush=True)
    print(f"load after: {load_average()}")


if __name__ == "__main__":
    main()
