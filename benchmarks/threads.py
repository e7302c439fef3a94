"""One compiled HIG step beside busy neighbours: the libraries' default threads against one thread.

A Jacobian method's float64 ``eigh`` runs on SciPy's OpenBLAS (jaxlib's CPU LAPACK kernels),
whose threads spin and wait for each other when other processes hold the cores. This
script compiles one training step (default: HIG on the oscillators at the paper's batch,
``common.training_step``) and times it idle and beside 1 and 2 busy neighbour processes
(pure-Python loops), in each condition with the BLAS/LAPACK pools at their default and
inside ``physgrad.threads(1)``, back to back: the two modes alternate in rounds, so a
change of the machine's load hits both. Prints the median per condition and mode (wall
time, and in brackets the process's CPU time: what the step's threads burned, spinning
included), the ratio default / limited and each mode's ratio to its idle time, beside the
same ratio for a single-threaded pure-Python loop (what one thread gets on this machine
beside the neighbours: the floor for any one-thread step). A cell stops after
``--cell-seconds`` (a collapsed default step can take seconds).

    python benchmarks/threads.py [--problem oscillators] [--method hig] [--neighbours 0,1,2]
                                 [--repeats 40] [--rounds 4] [--default-threads N] [--xla-threads N]
                                 [--set name=value ...]

``--default-threads N`` sets the "default" mode's BLAS pools to N (e.g. 2, a 2-core
machine's default, when the script is pinned to one core with ``taskset -c 0``: OpenBLAS
then sizes its pool from the one core it sees). ``--xla-threads N`` sizes XLA's own intra-op pool to N
threads with ``physgrad.cpu.start_xla(N)`` before JAX's backend starts
(``physgrad.threads`` cannot change it later; the ``physgrad`` command line sets both,
``--threads``).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import time

BUSY = "while True: pass"


def python_loop_seconds(repeats: int = 7) -> float:
    """Median seconds of a fixed single-threaded pure-Python loop (~50 ms idle): what the
    machine gives one thread beside the neighbours, the reference for a one-thread step."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        total = 0
        for i in range(1_000_000):
            total += i
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problem", default="oscillators")
    parser.add_argument("--method", default="hig")
    parser.add_argument("--neighbours", default="0,1,2")
    parser.add_argument("--repeats", type=int, default=40, help="steps per mode and condition")
    parser.add_argument("--rounds", type=int, default=4, help="alternations of the two modes per condition")
    parser.add_argument("--cell-seconds", type=float, default=30.0,
                        help="at most this long per mode and condition (at least 2 steps a round): a collapsed "
                             "default step can take seconds")  # fmt: skip
    parser.add_argument("--default-threads", type=int, default=None)
    parser.add_argument("--xla-threads", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    if args.xla_threads is not None:  # before JAX's backend starts (it has not: nothing ran yet)
        from physgrad.cpu import start_xla

        print(f"XLA's pool: {start_xla(args.xla_threads)}")

    os.environ.pop("PHYSGRAD_THREADS", None)  # common.py must leave the pools alone: both modes are set here
    import jax
    from common import training_step
    from threadpoolctl import threadpool_info, threadpool_limits

    import physgrad

    settings = dict(s.split("=", 1) for s in args.set)
    config, _, step, step_args = training_step(args.problem, args.method, settings)
    jax.block_until_ready(step(*step_args))  # compile and warm up (SciPy's LAPACK is loaded now)
    jax.block_until_ready(step(*step_args))
    default = threadpool_limits(limits=args.default_threads) if args.default_threads else None
    pools = ", ".join(f"{p['prefix']} {p['num_threads']}" for p in threadpool_info() if p["user_api"] == "blas")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"physgrad {physgrad.__version__} | jax {jax.__version__} | {platform.processor() or platform.machine()} | "
          f"{cores} usable of {os.cpu_count()} cores | load average before {os.getloadavg()[0]:.2f}")  # fmt: skip
    print(f"{args.method} on {args.problem}, batch {config.phases[0].batch_size}; default BLAS pools: {pools}; "
          f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}; median of {args.repeats} steps per cell")  # fmt: skip

    def timed(n: int, seconds: float) -> tuple[list[float], list[float]]:
        """(wall, CPU) seconds of up to ``n`` steps; CPU: this process's, every thread's."""
        wall: list[float] = []
        cpu: list[float] = []
        while len(wall) < n and (len(wall) < 2 or sum(wall) < seconds):
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(step(*step_args))
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        return wall, cpu

    results = {}
    for k in [int(n) for n in args.neighbours.split(",")]:
        busy = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(k)]
        try:
            time.sleep(1.0 if k else 0.0)  # the neighbours are running
            times: dict[str, list[float]] = {"default": [], "limited": [], "default cpu": [], "limited cpu": []}
            per_round = max(1, args.repeats // args.rounds)
            budget = args.cell_seconds / args.rounds
            for _ in range(args.rounds):
                wall, cpu = timed(per_round, budget)
                times["default"] += wall
                times["default cpu"] += cpu
                with physgrad.threads(1):
                    wall, cpu = timed(per_round, budget)
                times["limited"] += wall
                times["limited cpu"] += cpu
            results[k] = {mode: statistics.median(t) for mode, t in times.items()}
            results[k]["loop"] = python_loop_seconds()
            counts = {mode: len(t) for mode, t in times.items()}
            load = os.getloadavg()[0]
        finally:
            for p in busy:
                p.kill()
                p.wait()
        r = results[k]
        print(f"  {k} busy neighbour(s): default {1e3 * r['default']:.1f} ms ({counts['default']} steps), threads(1) "
              f"{1e3 * r['limited']:.1f} ms ({counts['limited']} steps) (load average {load:.2f})", flush=True)  # fmt: skip
    idle = results.get(0)
    print("\n| busy neighbours | default threads: ms/step (CPU ms) | physgrad.threads(1): ms/step (CPU ms) "
          "| default / limited | default / its idle | limited / its idle | Python loop / its idle |")  # fmt: skip
    print("|---|---|---|---|---|---|---|")
    for k, r in results.items():
        to_idle = (f"{r['default'] / idle['default']:.2f} | {r['limited'] / idle['limited']:.2f} | "
                   f"{r['loop'] / idle['loop']:.2f}" if idle else "- | - | -")  # fmt: skip
        print(f"| {k} | {1e3 * r['default']:.1f} ({1e3 * r['default cpu']:.0f}) | {1e3 * r['limited']:.1f} "
              f"({1e3 * r['limited cpu']:.0f}) | {r['default'] / r['limited']:.2f} | {to_idle} |")  # fmt: skip
    if default is not None:
        default.restore_original_limits()


if __name__ == "__main__":
    main()
