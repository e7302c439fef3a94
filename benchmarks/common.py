"""What the step benchmarks share: the command line, one compiled training step, timing."""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import platform
import statistics

import jax
import jax.numpy as jnp

import physgrad
from physgrad import Budget
from physgrad.harness.calibration import time_programs
from physgrad.harness.config import make_config
from physgrad.harness.train import build, make_step

# The step benchmarks' thread pools: $PHYSGRAD_THREADS (N or ``default``), as the command
# line's --threads, applied here before JAX's backend starts (so XLA's pool too) and kept
# for the process. Unset: the libraries' own pools, as the numbers in docs/performance.md
# were measured (threads.py sets its pools itself). physgrad.cpu.report() says what is in force.
if os.environ.get("PHYSGRAD_THREADS"):
    from physgrad.cpu import process_threads
    from physgrad.harness.arguments import threads_of

    _THREADS = contextlib.ExitStack()
    _THREADS.enter_context(process_threads(threads_of(argparse.Namespace(threads=None))))


def benchmark_parser(description: str, default_problem: str) -> argparse.ArgumentParser:
    """--problem, --batch-size, --repeats and --set, as every step benchmark takes them."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--problem", default=default_problem)
    parser.add_argument("--batch-size", type=int, default=None, help="one batch size for every method")
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    return parser


def settings_from(args: argparse.Namespace) -> dict[str, str]:
    """The --set pairs, with --batch-size as the batch_size setting."""
    settings = dict(s.split("=", 1) for s in args.set)
    if args.batch_size:
        settings["batch_size"] = str(args.batch_size)
    return settings


def machine_line() -> str:
    """``physgrad … | jax … | device | processor | N core(s)``: the versions and the machine a
    step table was measured on (the cores this process may run on, not the machine's count)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return (f"physgrad {physgrad.__version__} | jax {jax.__version__} | {jax.devices()[0]} | "
            f"{platform.processor() or platform.machine()} | {cores} core(s)")  # fmt: skip


def load_average() -> str:
    """The 1-, 5- and 15-minute load averages, printed beside a timing (the load distorts wall time)."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def warmed_steps(methods, prepare) -> tuple[dict, dict[str, str]]:
    """``(steps, refused)``: ``steps[method]`` = ``prepare(method)``, a tuple ``(setup, step,
    step_args)`` whose step has been called once (compiled and warmed up); a method whose
    ``prepare`` or first call raises (it refuses the problem) is left out of ``steps``, its
    error's first line in ``refused[method]``, so a table can print the reason in its row."""
    steps, refused = {}, {}
    for method in methods:
        try:
            prepared = prepare(method)
            jax.block_until_ready(prepared[1](*prepared[2]))
        except Exception as error:  # a method that refuses this problem: its one-line reason
            refused[method] = str(error).splitlines()[0]
            continue
        steps[method] = prepared
    return steps, refused


def training_step(problem: str, method: str, settings: dict[str, str]):
    """(config, setup, step, step_args): the engine's jitted step on batch 0 of the train split."""
    config = make_config(problem, method, budget=Budget(steps=1), settings=settings)
    setup = build(config)
    data = setup.data["train"]
    order = jnp.arange(jax.tree.leaves(data)[0].shape[0], dtype=jnp.int32)
    step = make_step(setup, config.phases[0].batch_size)
    return config, setup, step, (setup.params, setup.method.init(setup.params), data, order, jnp.int32(0))


def problem_precision(problem: str, settings: dict[str, str]):
    """``jax.enable_x64(True)`` where the configured problem computes in float64
    (``needs_float64``: heat; the HIG problems' float64 settings), else a no-op context: build,
    trace and time a step inside it, as a run and ``physgrad.fit`` scope it."""
    from physgrad.harness.train import problem_of
    from physgrad.precision import float64_scope

    config = make_config(problem, "adam", budget=Budget(steps=1), settings=settings)
    return float64_scope(problem_of(config).needs_float64)


def median_seconds(fn, args, repeats: int) -> float:
    """Median seconds per call over ``repeats`` calls after a warm-up call, timed by the
    harness's :func:`physgrad.harness.calibration.time_programs` (a calibrated study uses it
    too, with each call a chunk of the run's loop; here a call is one call of ``fn``)."""
    jax.block_until_ready(fn(*args))  # compile and warm up
    # the timed call returns None (one step): time_programs reads a returned tuple as a
    # replay's (steps, seconds), and fn's own result may be a tuple (a loss and its gradient)
    times = time_programs({"step": [lambda: (jax.block_until_ready(fn(*args)), None)[1]]}, repeats=repeats,
                          max_seconds=math.inf)  # fmt: skip
    return statistics.median(times["step"][0])


def half_inverse_floor(setup, batch_size: int, repeats: int) -> dict:
    """The cost floor of an exact half-inverse step at this batch, measured here:

    - ``backward``: one backward pass per Jacobian row to the dense layers'
      pre-activations (the signals D of the structured route, with the forward pass and
      no parameter derivatives);
    - ``eigh``: the float64 eigendecomposition of the m × m Gram matrix, m = min(rows, P)
      (the structured route's own matrix, so its spectrum is the real one).

    Returns seconds for both, ``floor`` = their sum, and ``rows``, ``P``, ``m``."""
    from physgrad.precision import float64_scope
    from physgrad.routes import JointJacobian, structured

    batch = jax.tree.map(lambda a: a[:batch_size], setup.data["train"])
    params, objective = setup.params, setup.objective
    jacobian = JointJacobian.of(objective, params, batch)
    rows, size = jacobian.shape
    plan = jacobian.structure
    backward = jax.jit(lambda p, b: structured.factors(plan, p, b, groups=())[0].D)
    t_backward = median_seconds(backward, (params, batch), repeats)
    if rows <= size:
        block = jax.jit(lambda p, b: structured.factors(plan, p, b, groups=tuple(range(len(plan.groups))))[0])(
            params, batch
        )
        with float64_scope():
            gram = jax.jit(lambda f: structured.cross_gram(plan, f, f))(block)
            t_eigh = median_seconds(jax.jit(jnp.linalg.eigh), (gram,), max(1, repeats // 3))
    else:  # tall: the P × P matrix
        with float64_scope():
            a = jax.random.normal(jax.random.key(0), (size, size), jnp.float64)
            t_eigh = median_seconds(jax.jit(jnp.linalg.eigh), (a @ a.T,), max(1, repeats // 3))
    return {"backward": t_backward, "eigh": t_eigh, "floor": t_backward + t_eigh, "rows": rows, "P": size,
            "m": min(rows, size)}  # fmt: skip


def step_bytes(step, args) -> int:
    """XLA's memory of the compiled step: arguments + outputs + temporaries − aliased."""
    mem = step.lower(*args).compile().memory_analysis()
    return int(mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes - mem.alias_size_in_bytes)
