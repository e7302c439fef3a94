"""A Jacobian method's ``physgrad.fit`` beside one busy BLAS neighbour: ``threads=1`` (the default) against ``threads=None``.

A user's script calls :func:`physgrad.fit`, not the command line. HIG's float64 ``eigh``
runs in jaxlib's CPU LAPACK kernels on SciPy's OpenBLAS, whose pool starts one spinning
thread per core; beside a process that keeps the cores busy those threads wait for each
other and the step collapses (issue 53: 170 ms a step with the default pools against
6.4 ms inside ``physgrad.threads(1)``). ``fit`` limits the pools for its own duration
(``threads=1``); this script checks that this holds a ``fit`` beside a neighbour near its
idle speed.

It trains HIG (``JacobianPower(-0.5)`` by SGD, the paper's η = 1 and τ = 10⁻⁶) on the HIG
paper's oscillators with ``physgrad.fit`` on a budget of ``--seconds`` training seconds,
in memory, first idle, then beside one neighbour process that multiplies two N × N float64
matrices in a loop with NumPy's default BLAS threads (one per core; ``--neighbour-threads 1``:
one thread, i.e. one busy core), each condition with
``threads=1`` and ``threads=None`` alternating over ``--rounds`` rounds (so a change of the
machine's load hits both). A run's time per step is ``summary["train_seconds"] /
summary["steps"]`` (compilation and evaluation excluded); the median over the rounds is
printed per condition and mode, with each mode's ratio to its own idle time and, as the
floor that no one-thread step can beat on this machine, the same ratio for a fixed
single-threaded pure-Python loop (``threads.py``'s) timed in the same condition.

The goal (issue 53, item 3): ``threads=1`` beside one busy neighbour within 1.5× of idle.

    python benchmarks/fit_under_load.py [--problem oscillators] [--batch-size 128]
        [--seconds 4] [--rounds 3] [--matrix 1000] [--neighbour-threads 1] [--xla-threads 1]

``--xla-threads 1`` calls :func:`physgrad.cpu.start_xla` first, as a script may at its top:
XLA sizes its intra-op pool (its matrix products) once, when JAX's backend starts, from the
CPUs the process may use, and ``fit``'s ``threads=1`` cannot change it afterwards. With
XLA's default pool (two threads on two cores) a step waits for whichever of its threads a
neighbour has preempted.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import time

# One BLAS neighbour: a NumPy matmul loop with the library's default pools (one thread per core).
NEIGHBOUR = """
import numpy as np
a = np.random.default_rng(0).random(({n}, {n}))
while True:
    a @ a
"""
# variables that would fix the neighbour's pools: it gets the libraries' defaults
POOL_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def main():
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--problem", default="oscillators", choices=("oscillators", "hig_toy"))
    parser.add_argument("--batch-size", type=int, default=None, help="default: the problem's (the paper's)")
    parser.add_argument("--seconds", type=float, default=4.0, help="training seconds per fit")
    parser.add_argument("--rounds", type=int, default=3, help="fits per condition and mode, alternating the modes")
    parser.add_argument("--matrix", type=int, default=1000, help="the neighbour's matrix size N")
    parser.add_argument("--neighbour-threads", type=int, default=None,
                        help="the neighbour's BLAS threads; default: the library's (one per core, so on a 2-core "
                             "machine it keeps every core busy); 1: one busy core")  # fmt: skip
    parser.add_argument("--xla-threads", type=int, default=None,
                        help="size XLA's intra-op pool first (physgrad.cpu.start_xla), as a script may at its top; "
                             "default: XLA's pool as JAX starts it (one thread per usable CPU)")  # fmt: skip
    args = parser.parse_args()
    xla = "XLA's default pool"
    if args.xla_threads is not None:  # before anything computes with JAX, as a user's script would
        import physgrad.cpu

        xla = f"XLA's pool: {physgrad.cpu.start_xla(args.xla_threads)}"

    import jax
    import optax
    from threadpoolctl import threadpool_info
    from threads import python_loop_seconds

    import physgrad
    from physgrad.methods import JacobianPower
    from physgrad.problems import HigToy, Oscillators

    problem = {"oscillators": Oscillators, "hig_toy": HigToy}[args.problem]()
    hig = physgrad.Method(JacobianPower(-0.5, 1e-6), optax.sgd(1.0))
    batch = args.batch_size or problem.default_batch_size
    budget = physgrad.Seconds(args.seconds)
    # one evaluation at the start and one at the end: evaluation is not training time anyway
    settings = physgrad.TrainSettings(eval_every=1_000_000)

    def ms_per_step(threads: int | None) -> float:
        result = physgrad.fit(problem, hig, budget=budget, batch_size=batch, settings=settings, threads=threads,
                              progress=False)  # fmt: skip
        summary = result.summary
        if summary["status"] != "finished":
            raise SystemExit(f"the fit ended {summary['status']!r}: {summary}")
        return 1e3 * summary["train_seconds"] / summary["steps"]

    neighbour_threads = ("default threads" if args.neighbour_threads is None
                         else f"{args.neighbour_threads} BLAS thread(s)")  # fmt: skip
    ms_per_step(1)  # JAX's backend, SciPy's LAPACK and the problem's data are loaded now
    pools = ", ".join(f"{p['prefix']} {p['num_threads']}" for p in threadpool_info() if p["user_api"] == "blas")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"physgrad {physgrad.__version__} | jax {jax.__version__} | {platform.processor() or platform.machine()} | "
          f"{cores} usable of {os.cpu_count()} cores | load average before {os.getloadavg()[0]:.2f}")  # fmt: skip
    print(f"HIG on {args.problem}, batch {batch}, {args.seconds:g} s of training per fit, {args.rounds} fits per "
          f"cell; this process's BLAS pools by default: {pools}; neighbour: {args.matrix}x{args.matrix} float64 "
          f"matmul loop, {neighbour_threads}; {xla}")  # fmt: skip

    environment = {k: v for k, v in os.environ.items() if k not in POOL_VARIABLES}
    if args.neighbour_threads is not None:
        environment.update(dict.fromkeys(POOL_VARIABLES, str(args.neighbour_threads)))
    modes = {"threads=1": 1, "threads=None": None}
    results: dict[str, dict[str, float]] = {}
    for condition, neighbours in (("idle", 0), ("1 BLAS neighbour", 1)):
        busy = [subprocess.Popen([sys.executable, "-c", NEIGHBOUR.format(n=args.matrix)], env=environment)
                for _ in range(neighbours)]  # fmt: skip
        try:
            time.sleep(2.0 if neighbours else 0.0)  # the neighbour has started multiplying
            times: dict[str, list[float]] = {mode: [] for mode in modes}
            for _ in range(args.rounds):
                for mode, threads in modes.items():
                    times[mode].append(ms_per_step(threads))
            results[condition] = {mode: statistics.median(t) for mode, t in times.items()}
            results[condition]["loop"] = 1e3 * python_loop_seconds()
            load = os.getloadavg()[0]
        finally:
            for p in busy:
                p.kill()
                p.wait()
        spread = "; ".join(f"{mode} " + ", ".join(f"{t:.1f}" for t in times[mode]) for mode in modes)
        print(f"  {condition}: {spread} ms/step (load average {load:.2f})", flush=True)

    idle = results["idle"]
    print("\n| condition | threads=1 (default): ms/step | threads=None: ms/step | None / 1 "
          "| threads=1 / its idle | threads=None / its idle | Python loop / its idle (floor) |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for condition, r in results.items():
        print(f"| {condition} | {r['threads=1']:.2f} | {r['threads=None']:.2f} | "
              f"{r['threads=None'] / r['threads=1']:.2f} | {r['threads=1'] / idle['threads=1']:.2f} | "
              f"{r['threads=None'] / idle['threads=None']:.2f} | {r['loop'] / idle['loop']:.2f} |")  # fmt: skip
    ratio = results["1 BLAS neighbour"]["threads=1"] / idle["threads=1"]
    floor = results["1 BLAS neighbour"]["loop"] / idle["loop"]
    print(f"\nthreads=1 beside one busy neighbour: {ratio:.2f}x its idle time (goal: within 1.5x); one thread of "
          f"pure Python got {floor:.2f}x in the same condition, so {ratio / floor:.2f}x of what the machine gave "
          f"one thread")  # fmt: skip


if __name__ == "__main__":
    main()
