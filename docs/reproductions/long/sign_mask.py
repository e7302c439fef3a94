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

from physgrad.config import RunConfig
from physgrad.rollout import M, R, joint_gradients
from physgrad.train import build, load_network

DATA = Path(__file__).resolve().parent.parent / "data"
RUNS = [  # (study, method directory, seeds)
    ("quantum_control_1000ep", "sbptt_c", (0, 1, 2)),
    ("quantum_control_1000ep", "sbptt_m", (0, 1, 2)),
    ("guidance_1000ep", "sbptt_c-clipvalue", (0, 1, 2)),
]


def flat(tree) -> np.ndarray:
    return np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in jax.tree.leaves(tree)])


def mask_statistics(run: Path, trained: bool, batches: int = 4, batch_size: int = 8) -> np.ndarray:
    """Mean over ``batches`` training batches of (loss, agree, |g_C|/|g_M|, cos, |g_R|/|g_M|)."""
    setup = build(RunConfig.from_dict(json.loads((run / "config.json").read_text())))
    params, static = eqx.partition(load_network(run) if trained else setup.network(), eqx.is_inexact_array)
    system = setup.problem.objective(static).rollout
    rows = []
    for i in range(batches):
        batch = jax.tree.map(lambda x: x[i * batch_size : (i + 1) * batch_size], setup.data["train"])
        loss, g_m, g_r = joint_gradients(system, params, system.initial_state(batch), M(), R())
        a, b = flat(g_m), flat(g_r)
        agree = np.sign(a) == np.sign(b)
        na, nb = np.linalg.norm(a), np.linalg.norm(b)
        rows.append((float(loss), agree.mean(), np.linalg.norm(a * agree) / na, a @ b / (na * nb), nb / na))
    return np.mean(rows, axis=0)


def main() -> None:
    print("| study | method | seed | network | loss | agree | \\|g_C\\|/\\|g_M\\| | cos(g_M, g_R) | \\|g_R\\|/\\|g_M\\| |")
    print("|---|---|---|---|---|---|---|---|---|")
    for study, method, seeds in RUNS:
        for seed in seeds:
            found = sorted((DATA / study / method / "runs").glob(f"*-seed{seed}-*"))
            if not found or not (found[0] / "params.eqx").exists():
                continue  # not finished yet
            for trained in (False, True) if seed == 0 else (True,):
                loss, agree, kept, cos, ratio = mask_statistics(found[0], trained)
                print(f"| {study} | {method} | {seed} | {'trained' if trained else 'initial'} | {loss:.3g} | "
                      f"{agree:.2f} | {kept:.2f} | {cos:.2f} | {ratio:.2g} |", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
