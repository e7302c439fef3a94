"""Scale: time and memory per training step against devices and against network size.

    python benchmarks/scale.py devices [--counts 1,2,4,8] [--repeats 10]
    python benchmarks/scale.py sizes [--rows 256,1024] [--hidden 20,100,200,370,683] [--routes gram,structured,svd,blockgram,lanczos]
    python benchmarks/scale.py accuracy [--batch 64] [--hidden 20,100] [--steps 16,64,128,256]

``devices``: each case (method on a problem at its paper batch) on 1, 2, 4, 8 devices; on
a CPU-only machine these are forced host devices (``XLA_FLAGS=
--xla_force_host_platform_device_count=N``, one subprocess per count) that share the same
cores, so the table shows the memory split and the collectives' overhead, not a speed-up.
``sizes``: one HIG step on ``oscillators`` with the hidden width set so that P runs from
3k to 1M parameters (P = 2h² + 103h + 96), for each half-inverse route, at each of
``--rows`` Jacobian rows (batch = rows / 4), beside the floor of an exact step measured in
the same process (one backward pass per row to the pre-activations + ``eigh`` of the
m × m Gram matrix, ``common.half_inverse_floor``). ``accuracy``: the block-Gram and Lanczos directions
against the exact Gram route on one batch where J fits.

Every measurement runs in its own subprocess (fresh memory statistics; a route that runs
out of memory or time is reported as such and the table goes on) and prints: median
seconds per step; XLA's per-device memory of the compiled step (arguments + outputs +
temporaries, ``compiled.memory_analysis()``); the process's peak resident memory
(including the ~0.3 GB JAX runtime and the data set).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))

DEVICE_CASES = [  # (label, problem, method, settings)
    # The example: J is 4096 × 24,896 (408 MB in float32, 816 MB as float64).
    ("poisson_hig hig (gram)", "poisson_hig", "hig", {"n_train": "256", "n_test": "64"}),
    ("oscillators hig (gram)", "oscillators", "hig", {"n_train": "1024", "n_test": "64"}),
    ("oscillators adam", "oscillators", "adam", {"n_train": "1024", "n_test": "64"}),
    ("poisson sip", "poisson", "sip", {"n_train": "256", "n_test": "16"}),
    ("cartpole sbptt_c", "cartpole", "sbptt_c", {"n_train": "64", "n_test": "8", "batch_size": "32"}),
]


def measure(args) -> dict:
    """One case in this process: compile, time, memory; a JSON line on stdout."""
    import jax
    import numpy as np

    sys.path.insert(0, HERE)
    from common import half_inverse_floor, median_seconds, training_step

    from physgrad.distributed import make_mesh, replicate, use_mesh
    from physgrad.harness.train import make_step

    settings = dict(s.split("=", 1) for s in args.set)
    config, setup, _, step_args = training_step(args.problem, args.method, settings)
    mesh = make_mesh(args.devices)
    with use_mesh(mesh):
        step = make_step(setup, config.phases[0].batch_size)
        inputs = (*replicate(step_args[:4], mesh), np.int32(0))
        compiled = step.lower(*inputs).compile()
        seconds = median_seconds(compiled, inputs, args.repeats)
    floor = half_inverse_floor(setup, config.phases[0].batch_size, args.repeats) if args.floor else None
    mem = compiled.memory_analysis()
    per_device = (
        mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes - mem.alias_size_in_bytes
    )
    from physgrad.nets import parameter_count

    return {
        "seconds": seconds,
        "xla_bytes": int(per_device),
        "temp_bytes": int(mem.temp_size_in_bytes),
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "params": parameter_count(setup.params),
        "batch": config.phases[0].batch_size,
        "device": str(jax.devices()[0]),
        "devices": args.devices,
        "floor": floor,
    }


def run_case(problem, method, settings, devices=1, repeats=10, timeout=900, forced=None, floor=False):
    """``measure`` in a subprocess; the result dict, or {"error": ...}."""
    env = dict(os.environ)
    if forced:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={forced}".strip()
    cmd = [sys.executable, __file__, "measure", "--problem", problem, "--method", method, "--devices", str(devices),
           "--repeats", str(repeats), *[f"--set={k}={v}" for k, v in settings.items()]] + (["--floor"] if floor else [])  # fmt: skip
    try:
        done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"over {timeout} s"}
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["?"])[-1]
        return {
            "error": "out of memory"
            if done.returncode in (-9, 137) or "RESOURCE_EXHAUSTED" in done.stderr
            else tail[:80]
        }
    return json.loads(done.stdout.strip().splitlines()[-1])


def gib(n):
    return f"{n / 2**30:.3f}"


def header():
    import jax

    import physgrad

    return (f"physgrad {physgrad.__version__} | jax {jax.__version__} | {jax.default_backend()} | "
            f"{platform.processor() or platform.machine()} | {os.cpu_count()} cores")  # fmt: skip


def cmd_devices(args):
    import jax

    counts = [int(c) for c in args.counts.split(",")]
    on_cpu = jax.default_backend() == "cpu"
    print(header())
    print(f"median of {args.repeats} steps; {'forced host devices sharing the cores' if on_cpu else 'real devices'}")
    print("| case | batch | devices | ms/step | × 1 device | XLA MiB/device | peak RSS GiB |")
    print("|---|---|---|---|---|---|---|")
    for label, problem, method, settings in DEVICE_CASES:
        if args.only and not any(word in label for word in args.only.split(",")):
            continue
        base = None
        for n in counts:
            r = run_case(problem, method, settings, devices=n, repeats=args.repeats, forced=n if on_cpu else None)
            if "error" in r:
                print(f"| {label} | | {n} | {r['error']} | | | |", flush=True)
                continue
            base = base or r["seconds"]
            print(f"| {label} | {r['batch']} | {n} | {r['seconds'] * 1e3:.2f} | {r['seconds'] / base:.2f} | "
                  f"{r['xla_bytes'] / 2**20:.1f} | {gib(r['peak_rss_bytes'])} |", flush=True)  # fmt: skip


def cmd_sizes(args):
    print(header())
    print(f"HIG step on oscillators; median of {args.repeats} steps; blockgram blocks={args.blocks}, "
          f"lanczos k={args.lanczos_steps}; floor = backward to pre-activations + eigh(rows), same process")  # fmt: skip
    print("| rows | P | route | ms/step | × floor | × gram | XLA MiB | peak RSS GiB | J alone MiB (float32) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for rows in [int(r) for r in args.rows.split(",")]:
        batch = rows // 4  # oscillators: 2 oscillators × (q, p) = 4 outputs per sample
        for h in [int(h) for h in args.hidden.split(",")]:
            p = 2 * h * h + 103 * h + 96
            gram = None
            for k, route in enumerate(args.routes.split(",")):
                settings = {"hidden": str(h), "batch_size": str(batch), "n_train": str(batch), "n_test": "16",
                            "route": route, "blocks": str(args.blocks), "lanczos_steps": str(args.lanczos_steps)}  # fmt: skip
                r = run_case("oscillators", "hig", settings, repeats=args.repeats, timeout=args.timeout, floor=k == 0)
                if k == 0:
                    floor = r.get("floor")
                    if floor:
                        print(f"| {rows} | {p:,} | floor | {floor['floor'] * 1e3:.1f} (backward {floor['backward'] * 1e3:.1f}"
                              f" + eigh {floor['eigh'] * 1e3:.1f}) | 1.00 | | | | |", flush=True)  # fmt: skip
                if "error" in r:
                    print(
                        f"| {rows} | {p:,} | {route} | {r['error']} | | | | | {rows * p * 4 / 2**20:.0f} |", flush=True
                    )
                    continue
                gram = r["seconds"] if route == "gram" else gram
                x_floor = f"{r['seconds'] / floor['floor']:.2f}" if floor else ""
                x_gram = f"{r['seconds'] / gram:.2f}" if gram else ""
                print(f"| {rows} | {r['params']:,} | {route} | {r['seconds'] * 1e3:.1f} | {x_floor} | {x_gram} | "
                      f"{r['xla_bytes'] / 2**20:.1f} | {gib(r['peak_rss_bytes'])} | {rows * p * 4 / 2**20:.0f} |", flush=True)  # fmt: skip


def cmd_accuracy(args):
    """The matrix-free routes against the exact Gram route on one HIG batch (where J fits)."""
    import jax
    import jax.numpy as jnp

    from physgrad import Budget
    from physgrad.harness.config import make_config
    from physgrad.harness.train import build
    from physgrad.routes import Gram, JointJacobian, blockgram_half_inverse, half_inverse, lanczos_half_inverse

    print(header())
    print(f"one HIG direction on oscillators, batch {args.batch} (rows {4 * args.batch}), τ = {args.truncation}; "
          "relative error ‖d − d_gram‖/‖d_gram‖, float32 network")  # fmt: skip
    print("| P | route | rel. error vs gram | Lanczos estimate ‖x_k − x_{k−1}‖/‖x_k‖ |")
    print("|---|---|---|---|")
    for h in [int(h) for h in args.hidden.split(",")]:
        settings = {"hidden": str(h), "batch_size": str(args.batch), "n_train": str(args.batch), "n_test": "16"}
        setup = build(make_config("oscillators", "hig", budget=Budget(steps=1), settings=settings))
        batch = setup.data["train"]
        pieces = jax.jit(lambda p, b: JointJacobian.of(setup.objective, p, b).jacobian_and_gradient())
        jac, g, _ = pieces(setup.params, batch)
        ref = half_inverse(jac, g, route=Gram(), truncation=args.truncation)
        err = lambda d: float(jnp.linalg.norm(d - ref) / jnp.linalg.norm(ref))  # noqa: E731
        p = jac.shape[1]
        d = jax.jit(lambda p, b, g: blockgram_half_inverse(setup.objective.predict, p, b, g, blocks=8,
                                                           truncation=args.truncation))(setup.params, batch, g)  # fmt: skip
        print(f"| {p:,} | blockgram (8 groups) | {err(d):.1e} | |")
        for k in [int(k) for k in args.steps.split(",")]:
            run = jax.jit(lambda p, b, g: lanczos_half_inverse(setup.objective.predict, p, b, g, steps=k,
                                                               truncation=args.truncation))  # fmt: skip
            d, estimate = run(setup.params, batch, g)
            print(f"| {p:,} | lanczos k = {min(k, g.size)} | {err(d):.1e} | {float(estimate):.1e} |", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("devices")
    p.add_argument("--counts", default="1,2,4,8")
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--only", help="comma-separated words: only the cases whose label contains one")
    p = sub.add_parser("sizes")
    p.add_argument("--rows", default="256,1024")
    p.add_argument("--hidden", default="20,100,200,370,683")
    p.add_argument(
        "--routes", default="gram,structured,svd,blockgram,lanczos", help="the first also measures the floor"
    )
    p.add_argument("--blocks", type=int, default=8)
    p.add_argument("--lanczos-steps", type=int, default=64)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--timeout", type=int, default=900)
    p = sub.add_parser("accuracy")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--hidden", default="20,100")
    p.add_argument("--steps", default="16,64,128,256")
    p.add_argument("--truncation", type=float, default=1e-6)
    p = sub.add_parser("measure")
    p.add_argument("--problem", required=True)
    p.add_argument("--method", required=True)
    p.add_argument("--devices", type=int, default=1)
    p.add_argument("--repeats", type=int, default=10)
    p.add_argument("--set", action="append", default=[])
    p.add_argument("--floor", action="store_true", help="also measure the floor of an exact half-inverse step")
    args = parser.parse_args()
    if args.command == "measure":
        print(json.dumps(measure(args)))
    else:
        {"devices": cmd_devices, "sizes": cmd_sizes, "accuracy": cmd_accuracy}[args.command](args)


if __name__ == "__main__":
    main()
