"""Time per training step of ``khig`` on the U-Net problems, against Adam (the floor), K-FAC and exact HIG.

For each shipped U-Net problem at a CPU size (``SIZES``; ``--set`` overrides; ``--problems ks``
adds the KS corrector, whose unrolled network reads each kernel once per step), the engine's
compiled step of

* ``adam`` — the floor: one forward and one backward pass;
* ``khig`` — fresh KFC convolution factors every step (``probes`` random output directions
  per sample for G), their eigendecompositions every step (one ``eigh`` per factor on a CPU);
* ``khig-stacked`` — the same with same-size factors stacked into one ``eigh`` call per size;
* ``khig-k`` — running factors (``AveragedKronecker``: ``curvature_ema`` β = ``--ema``) collected
  and eigendecomposed every ``--period`` k steps (``curvature_every = inverse_every = k``); the
  other k − 1 steps compute only the gradient and reuse the stored eigendecompositions;
* ``kfac`` and ``hig`` (its default route; ``--hig-repeats`` rounds only).

Every method's state is carried from step to step (so ``khig-k`` refreshes on one step in k),
the parameters stay fixed. Each round takes k consecutive steps of every method in turn (adam,
khig, …, adam, …), so that a change in the machine's load hits every method alike; a method's
time per step is the round's total over k (``khig-k``: its amortised cost, one refresh and
k − 1 reuse steps), its median over the rounds, in CPU time (``time.process_time``: the pools
are one thread, so it is the step's own work, not the load) and in wall time. The ratio is to
Adam's median from the same rounds. ``khig-k``'s refresh and reuse steps are also reported
apart. Prints the load average before and after.

The thread pools are one thread (``PHYSGRAD_THREADS=1``, as ``physgrad train`` runs) unless
``PHYSGRAD_THREADS`` says otherwise: with OpenBLAS's default pool, jaxlib's LAPACK ``eigh``
spins its threads on every call, and on a loaded 2-core machine a 145-wide float64 ``eigh``
took 156 ms of CPU instead of 2.7 ms (``docs/methods.md``).

    python benchmarks/khig_conv_step.py [--problems poisson,heat,navier_stokes] [--methods adam,khig,khig-k]
                                        [--period 10] [--ema 0.95] [--batch-size 8] [--probes 1] [--repeats 5]
"""

from __future__ import annotations

import os

os.environ.setdefault("PHYSGRAD_THREADS", "1")  # read by common, before JAX's backend starts

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
from common import load_average, machine_line, problem_precision, settings_from, training_step, warmed_steps  # noqa: E402

import physgrad  # noqa: E402
from physgrad.engine.step import make_step  # noqa: E402

PROBLEMS = ("poisson", "heat", "navier_stokes")
METHODS = ("adam", "khig", "khig-k", "kfac")
# CPU sizes: 32² grids with the papers' U-Nets (4 levels × 16 filters; navier_stokes 5 levels
# need 16 | 32), small data sets (only the step is timed)
SIZES = {
    "poisson": {"resolution": "32", "n_train": "32", "n_test": "8"},
    "heat": {"resolution": "32", "n_train": "32", "n_test": "8"},
    "navier_stokes": {"resolution": "32", "size": "64.0", "box": "28.0", "swirl_sigma": "10.0", "falloff": "40.0",
                      "n_train": "32", "n_test": "4"},
    # the KS corrector at the paper's network (26 × 8, 33,125 parameters), unrolled m = 3 steps:
    # each kernel is read once per step (one KFC layer, its uses more positions); small data
    "ks": {"setup": "correction", "frames": "40", "warmup_frames": "20", "n_ics": "1", "n_test": "1",
           "long_horizon": "12", "dataset_fraction": "1.0"},
}  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--problems", default=",".join(PROBLEMS))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--batch-size", type=int, default=8)
    parser.add_argument("--probes", type=int, default=1)
    parser.add_argument("--period", type=int, default=10, help="k: khig-k's steps between curvature refreshes")
    parser.add_argument("--ema", type=float, default=0.95, help="β: khig-k's curvature_ema")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--hig-repeats", type=int, default=1)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    methods, k = args.methods.split(","), args.period

    pools = physgrad.cpu.report().get("setting") or {}
    print(f"{machine_line()} | threads {pools.get('requested')} | "
          f"load {load_average()}; median of {args.repeats} interleaved rounds of {k} steps (hig: {args.hig_repeats}); "
          f"khig probes={args.probes}; khig-k: curvature_ema={args.ema}, curvature_every=inverse_every={k}")  # fmt: skip
    print("| problem | batch | parameters | method | CPU ms/step | × Adam (CPU) | wall ms/step | × Adam (wall) |")
    print("|---|---|---|---|---|---|---|---|")
    summary = []
    for problem in args.problems.split(","):
        base = {**SIZES.get(problem, {}), **settings_from(args)}

        def prepare(method, problem=problem, base=base):
            name = "khig" if method.startswith("khig") else method
            settings = {**base, "probes": str(args.probes)} if name == "khig" else base
            if method == "khig-k":
                settings = {**settings, "curvature_ema": str(args.ema), "inverse_every": str(k),
                            "curvature_every": str(k)}  # fmt: skip
            _, setup, step, step_args = training_step(problem, name, settings)
            if method == "khig-stacked":  # the same rule, same-size factors in one eigh call
                rule = dataclasses.replace(setup.method.rule, eigh_batched=True)
                step = make_step(setup, args.batch_size, dataclasses.replace(setup.method, rule=rule))
            return setup, step, list(step_args)  # a list: the state is carried from step to step

        with problem_precision(problem, base):
            steps, refused = warmed_steps(methods, prepare)
            size = physgrad.nets.parameter_count(next(iter(steps.values()))[0].params) if steps else 0
            cpu: dict[str, list[float]] = {m: [] for m in steps}
            wall: dict[str, list[float]] = {m: [] for m in steps}
            split: dict[str, list[float]] = {"refresh": [], "reuse": []}
            for r in range(args.repeats):
                for method, (_, step, step_args) in steps.items():
                    if method == "hig" and r >= args.hig_repeats:
                        continue
                    c0, w0 = time.process_time(), time.perf_counter()
                    for i in range(k):  # the state carried: khig-k refreshes on the round's first step
                        c1 = time.process_time()
                        _, state, _ = jax.block_until_ready(step(*step_args))
                        step_args[1] = state
                        if method == "khig-k":
                            split["refresh" if i == 0 else "reuse"].append(time.process_time() - c1)
                    cpu[method].append((time.process_time() - c0) / k)
                    wall[method].append((time.perf_counter() - w0) / k)
        cpu_m = {m: statistics.median(t) for m, t in cpu.items()}
        wall_m = {m: statistics.median(t) for m, t in wall.items()}
        for method in methods:
            if method in refused:
                print(f"| {problem} | {args.batch_size} | {size} | {method} | refused: {refused[method]} | | | |")
                continue
            ratios = [f"{m[method] / m['adam']:.2f}" if "adam" in m else "" for m in (cpu_m, wall_m)]
            print(f"| {problem} | {args.batch_size} | {size} | {method} | {cpu_m[method] * 1e3:.1f} | {ratios[0]} | "
                  f"{wall_m[method] * 1e3:.1f} | {ratios[1]} |", flush=True)  # fmt: skip
        if "adam" in cpu_m:
            line = f"{problem}: Adam steps per step (CPU): " + ", ".join(
                f"{m} {cpu_m[m] / cpu_m['adam']:.2f}" for m in cpu_m if m != "adam"
            )
            if split["refresh"]:
                line += (f"; khig-k refresh step {statistics.median(split['refresh']) * 1e3:.1f} ms, reuse step "
                         f"{statistics.median(split['reuse']) * 1e3:.1f} ms CPU")  # fmt: skip
            summary.append(line)
    print("\n".join(summary))
    print(f"load after: {load_average()}")


if __name__ == "__main__":
    main()
