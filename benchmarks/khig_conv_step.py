"""Time per training step of ``khig`` on the U-Net problems, against Adam (the floor), K-FAC and exact HIG.

For each shipped U-Net problem at a CPU size (``SIZES``; ``--set`` overrides), the engine's
compiled step of ``adam`` (the floor: one forward and one backward pass), ``khig`` with its
KFC convolution factors (``probes`` random output directions per sample for G; on a CPU one
``eigh`` call per factor, its default there), the same rule with same-size factors stacked
into one ``eigh`` call per size (``khig-stacked``: issue 51's batching, before/after),
``kfac`` and ``hig`` (its default route; ``--hig-repeats`` rounds only). The
steps are timed in interleaved rounds (adam, khig, khig-stacked, kfac, hig, adam, …) so that a
change in the machine's load hits every method alike. Prints the median ms/step and its
ratio to Adam's median from the same rounds, "Adam steps per khig step", the eigh batching's
before/after, and the load average before and after.

    taskset -c 0 python benchmarks/khig_conv_step.py [--problems poisson,heat,navier_stokes]
                                                     [--batch-size 8] [--probes 1] [--repeats 9]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import statistics
import time

import jax
from common import problem_precision, training_step

import physgrad
from physgrad.engine.step import make_step

PROBLEMS = ("poisson", "heat", "navier_stokes")
METHODS = ("adam", "khig", "khig-stacked", "kfac", "hig")
# CPU sizes: 32² grids with the papers' U-Nets (4 levels × 16 filters; navier_stokes 5 levels
# need 16 | 32), small data sets (only the step is timed)
SIZES = {
    "poisson": {"resolution": "32", "n_train": "32", "n_test": "8"},
    "heat": {"resolution": "32", "n_train": "32", "n_test": "8"},
    "navier_stokes": {"resolution": "32", "size": "64.0", "box": "28.0", "swirl_sigma": "10.0", "falloff": "40.0",
                      "n_train": "32", "n_test": "4"},
}  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--problems", default=",".join(PROBLEMS))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--probes", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--hig-repeats", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    methods = args.methods.split(",")

    affinity = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"physgrad {physgrad.__version__} | jax {jax.__version__} | {jax.devices()[0]} | "
          f"{platform.processor() or platform.machine()} | {affinity} core(s) | load {_load()}; median of "
          f"{args.repeats} interleaved rounds (hig: {args.hig_repeats}); khig probes={args.probes}")  # fmt: skip
    print("| problem | batch | parameters | method | ms/step | × Adam |")
    print("|---|---|---|---|---|---|")
    summary = []
    for problem in args.problems.split(","):
        base = {**SIZES.get(problem, {}), **dict(s.split("=", 1) for s in args.set),
                "batch_size": str(args.batch_size)}  # fmt: skip
        with problem_precision(problem, base):
            steps, refused, size = {}, {}, 0
            for method in methods:
                name = "khig" if method.startswith("khig") else method
                settings = {**base, "probes": str(args.probes)} if name == "khig" else base
                try:
                    _, setup, step, step_args = training_step(problem, name, settings)
                    if method == "khig-stacked":  # the same rule, same-size factors in one eigh call
                        rule = dataclasses.replace(setup.method.rule, eigh_batched=True)
                        step = make_step(setup, args.batch_size, dataclasses.replace(setup.method, rule=rule))
                    jax.block_until_ready(step(*step_args))  # compile and warm up
                    size = physgrad.nets.parameter_count(setup.params)
                except Exception as error:  # a method that refuses this problem: its one-line reason
                    refused[method] = str(error).splitlines()[0]
                    continue
                steps[method] = (step, step_args)
            times: dict[str, list[float]] = {m: [] for m in steps}
            for r in range(args.repeats):
                for method, (step, step_args) in steps.items():
                    if method == "hig" and r >= args.hig_repeats:
                        continue
                    t0 = time.perf_counter()
                    jax.block_until_ready(step(*step_args))
                    times[method].append(time.perf_counter() - t0)
        medians = {m: statistics.median(t) for m, t in times.items()}
        floor = medians.get("adam")
        for method in methods:
            if method in refused:
                print(f"| {problem} | {args.batch_size} | {size} | {method} | refused: {refused[method]} | |")
                continue
            ratio = f"{medians[method] / floor:.1f}" if floor else ""
            print(f"| {problem} | {args.batch_size} | {size} | {method} | {medians[method] * 1e3:.1f} | {ratio} |",
                  flush=True)  # fmt: skip
        if floor and "khig" in medians:
            line = f"{problem}: Adam steps per khig step {medians['khig'] / floor:.1f}"
            if "khig-stacked" in medians:
                line += (f"; eigh per factor {medians['khig'] * 1e3:.1f} ms -> stacked by size "
                         f"{medians['khig-stacked'] * 1e3:.1f} ms ({medians['khig'] / medians['khig-stacked']:.2f}x)")  # fmt: skip
            summary.append(line)
    print("\n".join(summary))
    print(f"load after: {_load()}")


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


if __name__ == "__main__":
    main()
