"""How much of M's gradient survives C's sign mask, on the trained networks of the long
studies (the cause of C not beating M; stable_bptt.md, "The paper's 1000 epochs").

Stabilised BPTT (C) keeps M's gradient where its sign agrees with the regular gradient R's:
g_C = where(sign g_M = sign g_R, g_M, 0). For each run this script rebuilds the problem from
the run's config.json, loads its network (the initial one and the trained params.eqx), and
on four training batches of 8 computes g_M and g_R in one pass, then prints

- ``agree``: the fraction of parameters whose signs agree (0.5 for independent signs),
- ``|g_C|/|g_M|``: the share of M's gradient norm that the mask keeps,
- ``cos``: the cosine between g_M and g_R,
- ``|g_R|/|g_M|``: how much larger the regular gradient is,

averaged over the four batches.

    python docs/reproductions/long/sign_mask.py            # about 2 min on one core
"""

from __future__ import annotations

import json
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from physgrad.harness.config import RunConfig
from physgrad.harness.train import build, load_network
from physgrad.rollout import M, R, cosine, joint_gradients, sign_mask

DATA = Path(__file__).resolve().parent.parent / "data"
RUNS = [  # (study, method directory, seeds)
    ("quantum_control_1000ep", "sbptt_c", (0, 1, 2)),
    ("quantum_control_1000ep", "sbptt_m", (0, 1, 2)),
    ("guidance_1000ep", "sbptt_c-clipvalue", (0, 1, 2)),
]


def flat(tree) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree.leaves(tree)])


def mask_statistics(setup, network, batches: int = 4, batch_size: int = 8) -> np.ndarray:
    """Mean over ``batches`` training batches of (loss, agree, |g_C|/|g_M|, cos, |g_R|/|g_M|),
    with g_C from C's own :func:`~physgrad.rollout.sign_mask`."""
    params, static = eqx.partition(network, eqx.is_inexact_array)
    system = setup.problem.objective(static).rollout
    rows = []
    for i in range(batches):
        batch = jax.tree.map(lambda x: x[i * batch_size : (i + 1) * batch_size], setup.data["train"])
        loss, g_m, g_r = joint_gradients(system, params, system.initial_state(batch), M(), R())
        a, b, c = flat(g_m), flat(g_r), flat(sign_mask(g_m, g_r))
        na = np.linalg.norm(a)
        agree = np.mean(np.sign(a) == np.sign(b))
        rows.append((float(loss), agree, np.linalg.norm(c) / na, float(cosine(g_m, g_r)), np.linalg.norm(b) / na))
    return np.mean(rows, axis=0)


def main() -> None:
    print(
        "| study | method | seed | network | loss | agree | \\|g_C\\|/\\|g_M\\| | cos(g_M, g_R) | \\|g_R\\|/\\|g_M\\| |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for study, method, seeds in RUNS:
        for seed in seeds:
            found = sorted((DATA / study / method / "runs").glob(f"*-seed{seed}-*"))
            if not found or not (found[0] / "params.eqx").exists():
                continue  # not finished yet
            setup = build(RunConfig.from_dict(json.loads((found[0] / "config.json").read_text())))
            for trained in (False, True) if seed == 0 else (True,):
                network = load_network(found[0], like=setup.network()) if trained else setup.network()
                loss, agree, kept, cos, ratio = mask_statistics(setup, network)
                print(f"| {study} | {method} | {seed} | {'trained' if trained else 'initial'} | {loss:.3g} | "
                      f"{agree:.2f} | {kept:.2f} | {cos:.2f} | {ratio:.2g} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
