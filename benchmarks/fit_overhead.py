"""Per-step overhead of :func:`physgrad.fit` over a hand-written ``jax.jit`` Adam loop.

Both train the same small problem (a user's own: recover x from y = x + 0.1·x³ with an
MLP) with the same data, network, batches and Adam, back to back in one process. The
per-step cost of each is the marginal wall time of a longer run over a shorter one,

    ms/step = (T(steps_long) - T(steps_short)) / (steps_long - steps_short),

so what every run pays once (data, network, compilation, the first and the final
evaluation, the summary) cancels and what remains is the step plus whatever the loop does
around it (host syncs, Python work, metric recording, checkpoints, the progress meter).
The median of ``--repeats`` differences is printed for each, in wall-clock time and in
this process's CPU time (steadier on a loaded machine), with the ratio fit / hand. A third
loop, ``scan``, takes the same steps in one ``lax.fori_loop`` per epoch: the floor of any
loop on this problem.

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
        return physgrad.MLP((2, self.width, self.width, 2), jax.nn.tanh, key=key)

    def network_output(self, network, sample):
        return network(sample["y"])

    def simulate(self, x, sample):
        return x + 0.1 * x**3

    def loss(self, y, sample):
        return jnp.sum((y - sample["y"]) ** 2)


def _pieces(problem: Cubic, *, lr: float, batch_size: int, seed: int):
    """fit's data and network for ``seed`` (its keys), Adam, and the jitted loss of a batch."""
    key = jax.random.key(seed)
    data = problem.make_data(jax.random.fold_in(key, 0))
    network = problem.initial_network(jax.random.fold_in(key, 1), data)
    params, static = eqx.partition(network, eqx.is_inexact_array)
    optimizer = optax.adam(lr)

    def batch_loss(params, batch):
        net = eqx.combine(params, static)
        per_sample = jax.vmap(lambda s: problem.loss(problem.simulate(problem.network_output(net, s), s), s))
        return jnp.mean(per_sample(batch))

    def step(params, opt_state, index):  # batch ``index`` of the fixed order
        batch = jax.tree.map(lambda a: jax.lax.dynamic_slice_in_dim(a, index * batch_size, batch_size), data["train"])
        loss, grad = jax.value_and_grad(batch_loss)(params, batch)
        updates, opt_state = optimizer.update(grad, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, loss

    per_epoch = data["train"]["x"].shape[0] // batch_size
    return data, params, optimizer.init(params), jax.jit(batch_loss), step, per_epoch


def hand_loop(problem: Cubic, *, lr: float, batch_size: int, steps: int, seed: int = 0) -> None:
    """A hand-written training loop: one ``jax.jit`` Adam step per batch, dispatched
    without waiting, the test loss read at the start and the end."""
    data, params, opt_state, loss, step, per_epoch = _pieces(problem, lr=lr, batch_size=batch_size, seed=seed)
    step = jax.jit(step)
    float(loss(params, data["test"]))
    for i in range(steps):
        params, opt_state, _ = step(params, opt_state, i % per_epoch)
    float(loss(params, data["test"]))  # waits for every step


def scan_loop(problem: Cubic, *, lr: float, batch_size: int, steps: int, seed: int = 0) -> None:
    """The floor: the same steps in one ``lax.fori_loop`` per epoch (no host work per step)."""
    data, params, opt_state, loss, step, per_epoch = _pieces(problem, lr=lr, batch_size=batch_size, seed=seed)

    @jax.jit
    def steps_of(params, opt_state, start, count):
        def body(i, carry):
            return step(*carry, (start + i) % per_epoch)[:2]

        return jax.lax.fori_loop(0, count, body, (params, opt_state))

    float(loss(params, data["test"]))
    for start in range(0, steps, per_epoch):
        params, opt_state = steps_of(params, opt_state, start, min(per_epoch, steps - start))
    float(loss(params, data["test"]))


def fit_run(problem: Cubic, method, *, batch_size: int, steps: int, long: int, out: str | None) -> None:
    """:func:`physgrad.fit` with ``method`` for ``steps`` steps, evaluating at 0 and the end
    (the same method object every time: its compiled steps are shared, as in a study)."""
    settings = physgrad.TrainSettings(eval_every=long)
    run_dir = None if out is None else tempfile.mkdtemp(dir=out)
    physgrad.fit(problem, method, budget=physgrad.Budget(steps=steps), out=run_dir and os.path.join(run_dir, "run"),
                 batch_size=batch_size, settings=settings, name="adam")  # fmt: skip
    if run_dir is not None:
        shutil.rmtree(run_dir)


def timed(run, steps: int) -> tuple[float, float]:
    """Wall-clock and CPU seconds (this process's) of ``run(steps)``."""
    wall, cpu = time.perf_counter(), time.process_time()
    run(steps)
    return time.perf_counter() - wall, time.process_time() - cpu


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
    adam = physgrad.Method(Gradient(), optax.adam(args.lr))
    runs = {
        "hand": lambda steps: hand_loop(problem, steps=steps, **common),
        "fit": lambda steps: fit_run(
            problem, adam, steps=steps, long=args.long, out=args.out, batch_size=args.batch_size
        ),
        "scan": lambda steps: scan_loop(problem, steps=steps, **common),
    }
    for run in runs.values():  # compile and warm up (fit's compiled programs are shared in-process)
        run(args.short)
    wall = {name: [] for name in runs}
    cpu = {name: [] for name in runs}
    for _ in range(args.repeats):  # back to back, alternating, so load changes hit each alike
        for name, run in runs.items():
            (w0, c0), (w1, c1) = timed(run, args.short), timed(run, args.long)
            wall[name].append((w1 - w0) / (args.long - args.short))
            cpu[name].append((c1 - c0) / (args.long - args.short))
    where = f"run directories under {args.out}" if args.out else "in memory (out=None)"
    print(f"problem: MLP width {args.width}, batch {args.batch_size}, Adam; fit {where}; "
          f"steps {args.short} vs {args.long}, {args.repeats} repeats; jax {jax.__version__}, {jax.default_backend()}")  # fmt: skip
    for label, table in (("wall", wall), ("cpu", cpu)):
        ms = {name: 1e3 * statistics.median(values) for name, values in table.items()}
        for name, value in ms.items():
            spread = ", ".join(f"{1e3 * v:.4f}" for v in table[name])
            print(f"{label} {name:>5}: {value:.4f} ms/step (median; each repeat: {spread})")
        print(f"{label} ratio fit / hand: {ms['fit'] / ms['hand']:.3f} (overhead {100 * (ms['fit'] / ms['hand'] - 1):+.1f}%);"
              f" fit / scan (the floor): {ms['fit'] / ms['scan']:.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
