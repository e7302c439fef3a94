"""The same run on 1 device, on N forced host devices and as two processes over loopback.

    python benchmarks/distributed_check.py oscillators hig --steps 100 [--devices 4] [--set name=value ...]

Trains the run three times with the ``physgrad train`` command line (each in its own
process: the device count is fixed when JAX starts) and prints the final train and test
losses and the largest relative difference of the trained parameters against the
single-device run. Two processes use one CPU device each and 127.0.0.1 (the README's
example); N devices use ``XLA_FLAGS=--xla_force_host_platform_device_count=N``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def physgrad_train(problem, method, steps, settings, out, extra=(), forced=1):
    env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={forced}", "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "physgrad", "train", problem, "--method", method, "--steps", str(steps), "--quiet",
           "--out", str(out), *[f"--set={s}" for s in settings], *extra]  # fmt: skip
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(*procs):
    for p in procs:
        out, err = p.communicate()
        if p.returncode != 0:
            sys.exit(f"a run failed:\n{err[-3000:]}")


def flat_params(run_dir: Path) -> np.ndarray:
    import equinox as eqx
    from jax.flatten_util import ravel_pytree

    from physgrad.harness.train import load_network

    network = load_network(run_dir)
    return np.asarray(ravel_pytree(eqx.filter(network, eqx.is_inexact_array))[0])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem")
    parser.add_argument("method")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--devices", type=int, default=4)
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        common = (args.problem, args.method, args.steps, args.set)
        finish(physgrad_train(*common, tmp / "single"))
        finish(physgrad_train(*common, tmp / "devices", ("--devices", str(args.devices)), forced=args.devices))
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        multi = [
            ("--coordinator", f"127.0.0.1:{port}", "--num-processes", "2", "--process-id", str(i)) for i in range(2)
        ]
        finish(*[physgrad_train(*common, tmp / "processes", m) for m in multi])

        reference = flat_params(tmp / "single")
        print(f"{args.problem} {args.method}, {args.steps} steps, settings {args.set or 'paper defaults'}")
        print("| run | devices | final train loss | final test loss | max abs Δθ / max abs θ vs 1 device |")
        print("|---|---|---|---|---|")
        for name, label in (("single", "1 device"), ("devices", f"{args.devices} devices, 1 process"),
                            ("processes", "2 processes × 1 device (loopback)")):  # fmt: skip
            summary = json.loads((tmp / name / "summary.json").read_text())
            theta = flat_params(tmp / name)
            diff = np.abs(theta - reference).max() / np.abs(reference).max()
            print(f"| {label} | {summary['devices']} | {summary['final_train_loss']:.6e} | "
                  f"{summary['final_test_loss']:.6e} | {diff:.1e} |")  # fmt: skip


if __name__ == "__main__":
    main()
