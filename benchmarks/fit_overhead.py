"""Per-step overhead of :func:`physgrad.fit` over a hand-written ``jax.jit`` Adam loop.

Both train the same small problem (a user's own: recover x from y = x + 0.1·x³ with an
MLP) with the same data, network, batches and Adam, back to back in one process. The
per-step cost of each is the marginal wall time of a longer run over a shorter one,

    ms/step = (T(steps_long) - T(steps_short)) / (steps_long - steps_short),

so what every run pays once (data, network, compilation, the first and the final
evaluation, the summary) cancels and what remains is the step plus whatever the loop does
around it (host syncs, Python work, metric recording, checkpoints, the progress meter).
The median of ``--repeats`` differences is printed for each, with the ratio fit / hand.

    taskset -c 0 python benchmarks/fit_overhead.py [--width 64] [--batch-size 64]
        [--short 500] [--long 5500] [--repeats 5] [--out DIR]

``--out DIR`` runs ``fit`` into run directories under DIR (files, checkpoints every 60 s);
without it ``fit`` runs in memory (``out=None``). Evaluations: at step 0 and at the end
only (``eval_every`` = the long budget), as a hand loop that prints its first and last loss.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import tempfile
import time
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import optax

import physgrad
from physgrad.methods import Gradient


class Cubic(physgrad.AbstractProblem):
    """Recover x from y = x + 0.1·x³ (per component) with an MLP of ``width`` units."""

    n: int = 4096
    width: int = 64
    name: ClassVar[str] = "cubic"
    description: ClassVar[str] = "the overhead benchmark's problem"
    source: ClassVar[str] = "benchmarks/fit_overhead.py"

    def make_data(self, key):
        x = jax.random.uniform(key, (2 * self.n, 2), jnp.float32, -1.0, 1.0)
        data = {"x": x, "y": x + 0.1 * x**3}
        return {"train": jax.tree.map(lambda a: a[: self.n], data), "test": jax.tree.map(lambda a: a[self.n :], data)}

    def make_network(self, key):
        return physgrad.MLP((2, self.width, self.width, 2), "tanh", key=key)

    def network_output(self, network, sample):
        return network(sample["y"])

    def simulate(self, x, sample):
        return x + 0.1 * x**3

    def loss(self, y, sample):
        return jnp.sum((y - sample["y"]) ** 2)


def hand_loop(problem: Cubic, *, lr: float, batch_size: int, steps: int, seed: int = 0) -> float:
    """A hand-written training loop: fit's keys for data and network, one jitted Adam step
    per batch in the fixed order, the loss read back once at the end; returns seconds."""
    t0 = time.perf_counter()
    key = jax.random.key(seed)
    data = problem.make_data(jax.random.fold_in(key, 0))
    network = problem.initial_network(jax.random.fold_in(key, 1), data)
    params, static = eqx.partition(network, eqx.is_inexact_array)
    optimizer = optax.adam(lr)
    opt_state = optimizer.init(params)
    train = data["train"]
    per_epoch = train["x"].shape[0] // batch_size

    def batch_loss(params, batch):
        net = eqx.combine(params, static)
        per_sample = jax.vmap(lambda s: problem.loss(problem.simulate(problem.network_output(net, s), s), s))
        return jnp.mean(per_sample(batch))

    @jax.jit
    def step(params, opt_state, index):
        batch = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, index * batch_size, batch_size), train)
        loss, grad = jax.value_and_grad(batch_loss)(params, batch)
        updates, opt_state = optimizer.update(grad, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    float(batch_loss(params, data["test"]))  # the first evaluation
    for i in range(steps):
        params, opt_state, _ = step(params, opt_state, i % per_epoch)
    float(batch_loss(params, data["test"]))  # the final evaluation waits for every step
    return time.perf_counter() - t0


def fit_run(problem: Cubic, *, lr: float, batch_size: int, steps: int, long: int, out: str | None) -> float:
    """:func:`physgrad.fit` with Adam for ``steps`` steps, evaluating at 0 and the end; seconds."""
    method = physgrad.Method(Gradient(), optax.adam(lr))
    settings = physgrad.TrainSettings(eval_every=long)
    run_dir = None if out is None else tempfile.mkdtemp(dir=out)
    t0 = time.perf_counter()
    physgrad.fit(problem, method, budget=physgrad.Budget(steps=steps), out=run_dir and os.path.join(run_dir, "run"),
                 batch_size=batch_size, settings=settings, name="adam")  # fmt: skip
    seconds = time.perf_counter() - t0
    if run_dir is not None:
        shutil.rmtree(run_dir)
    return seconds


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--short", type=int, default=500)
    parser.add_argument("--long", type=int, default=5500)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--out", default=None, help="run fit into run directories under this folder")
    args = parser.parse_args()
    problem = Cubic(width=args.width)
    common = dict(lr=args.lr, batch_size=args.batch_size)
    runs = {
        "hand": lambda steps: hand_loop(problem, steps=steps, **common),
        "fit": lambda steps: fit_run(problem, steps=steps, long=args.long, out=args.out, **common),
    }
    for run in runs.values():  # compile and warm up (fit's compiled programs are shared in-process)
        run(args.short)
    per_step = {name: [] for name in runs}
    for _ in range(args.repeats):  # back to back, alternating, so load changes hit both alike
        for name, run in runs.items():
            short, long = run(args.short), run(args.long)
            per_step[name].append((long - short) / (args.long - args.short))
    ms = {name: 1e3 * statistics.median(values) for name, values in per_step.items()}
    where = f"run directories under {args.out}" if args.out else "in memory (out=None)"
    print(f"problem: MLP width {args.width}, batch {args.batch_size}, Adam; fit {where}; "
          f"steps {args.short} vs {args.long}, {args.repeats} repeats; jax {jax.__version__}, {jax.default_backend()}")  # fmt: skip
    for name, value in ms.items():
        spread = ", ".join(f"{1e3 * v:.4f}" for v in per_step[name])
        print(f"{name:>5}: {value:.4f} ms/step (median; each repeat: {spread})")
    print(f"ratio fit / hand: {ms['fit'] / ms['hand']:.3f} (overhead {100 * (ms['fit'] / ms['hand'] - 1):+.1f}%)")


if __name__ == "__main__":
    main()
