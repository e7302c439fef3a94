"""XLA compilations and compile seconds of the demo and of a 3-seed comparison.

Counts JAX's backend compilations (its public monitoring events) while the command line
runs ``physgrad demo`` and ``physgrad compare oscillators --methods adam,gn,hig --seeds 3``
on small step budgets, in this process. The count does not depend on the machine's load;
the seconds do. To compare two versions of physgrad, run the script once with each on the
path, e.g. from a worktree of the older commit:

    python benchmarks/compile_counts.py
    PYTHONPATH=../old/src python benchmarks/compile_counts.py
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import jax

import physgrad
from physgrad.harness.cli import main as cli


class Counter:
    def __init__(self):
        self.count, self.seconds = 0, 0.0
        jax.monitoring.register_event_duration_secs_listener(self._event)

    def _event(self, event, duration, **kwargs):
        if event == "/jax/core/compile/backend_compile_duration":
            self.count += 1
            self.seconds += duration


def measure(counter: Counter, name: str, argv: list[str]):
    n0, s0, t0 = counter.count, counter.seconds, time.perf_counter()
    code = cli(argv)
    wall = time.perf_counter() - t0
    print(f"{name:42s} exit {code}  compilations {counter.count - n0:5d}  "
          f"compile {counter.seconds - s0:7.1f} s  wall {wall:7.1f} s", flush=True)  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo-seconds", type=float, default=5.0, help="the demo's training seconds per run")
    parser.add_argument("--steps", type=int, default=50, help="steps per run of the comparison")
    parser.add_argument("--only", choices=("demo", "compare"), help="run one of the two (each in a fresh process)")
    args = parser.parse_args()
    print(
        f"physgrad {getattr(physgrad, '__version__', '?')} from {Path(physgrad.__file__).parent}, jax {jax.__version__}"
    )
    counter = Counter()
    with tempfile.TemporaryDirectory() as out:
        if args.only != "compare":
            demo = ["demo", "--out", f"{out}/demo", "--seconds", str(args.demo_seconds)]
            measure(counter, f"demo (--seconds {args.demo_seconds:g})", demo)
        if args.only != "demo":
            compare = ["compare", "oscillators", "--methods", "adam,gn,hig", "--seeds", "3", "--steps", str(args.steps),
                       "--out", f"{out}/compare", "--quiet"]  # fmt: skip
            measure(counter, "compare oscillators adam,gn,hig x 3 seeds", compare)


if __name__ == "__main__":
    main()
