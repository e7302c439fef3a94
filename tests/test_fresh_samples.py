"""fresh_samples: every epoch after the first trains on a new train split from make_data
(the SIP and HIG papers draw every batch fresh), checked against a hand-written loop."""

import json

import equinox as eqx
import jax
import numpy as np
import pytest

from physgrad import Budget
from physgrad.engine import _identity
from physgrad.harness.config import make_config, train_settings
from physgrad.harness.registry import PROBLEMS
from physgrad.harness.train import build, train

SETTINGS = {"n_train": 8, "n_test": 4, "batch_size": 4, "lr": 0.05, "eval_every": 2}
STEPS = 6  # three epochs of two batches


def hand_written_sgd(fresh: bool, seed: int = 0):
    """SGD on exp_inverse's batch loss, batches in fixed order; epoch e > 0 of a fresh run
    trains on make_data(fold_in(fold_in(fold_in(key(seed), 3), 0), e))["train"]."""
    config = make_config(
        "exp_inverse", "sgd", budget=Budget(steps=1), seed=seed, settings={"n_train": 8, "n_test": 4, "batch_size": 4}
    )
    setup = build(config)
    loss = jax.jit(jax.value_and_grad(setup.objective.batch_loss))
    params = setup.params
    for step in range(STEPS):
        epoch, b = divmod(step, 2)
        data = setup.data["train"]
        if fresh and epoch > 0:
            key = jax.random.fold_in(jax.random.fold_in(jax.random.fold_in(jax.random.key(seed), 3), 0), epoch)
            data = setup.problem.make_data(key)["train"]
        batch = jax.tree.map(lambda a: a[4 * b : 4 * b + 4], data)
        _, g = loss(params, batch)
        params = jax.tree.map(lambda p, d: p - 0.05 * d, params, g)
    return params


def trained(tmp_path, name, **extra):
    config = make_config("exp_inverse", "sgd", budget=Budget(steps=STEPS), settings={**SETTINGS, **extra})
    summary = train(config, tmp_path / name)
    params = eqx.tree_deserialise_leaves(tmp_path / name / "params.eqx", build(config).params)
    return summary, params


@pytest.mark.parametrize("fresh", [True, False])
def test_training_follows_the_hand_written_loop(tmp_path, fresh):
    summary, params = trained(tmp_path, str(fresh), fresh_samples=str(fresh).lower())
    assert summary["status"] == "finished"
    want = hand_written_sgd(fresh)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(want)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=2e-5, atol=1e-7)
    other = hand_written_sgd(not fresh)  # the two protocols train different networks
    assert any(
        not np.allclose(np.asarray(a), np.asarray(b)) for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(other))
    )


def test_a_resumed_fresh_run_draws_the_same_samples(tmp_path):
    _, whole = trained(tmp_path, "whole", fresh_samples="true")
    config = make_config("exp_inverse", "sgd", budget=Budget(steps=3), settings={**SETTINGS, "fresh_samples": "true"})
    train(config, tmp_path / "parts")
    config = make_config(
        "exp_inverse", "sgd", budget=Budget(steps=STEPS), settings={**SETTINGS, "fresh_samples": "true"}
    )
    train(config, tmp_path / "parts", resume=True)
    assert (tmp_path / "parts" / "params.eqx").read_bytes() == (tmp_path / "whole" / "params.eqx").read_bytes()


def test_the_papers_streams_default_to_fresh_samples_and_the_rest_to_one_set():
    fresh = {name for name, cls in PROBLEMS.items() if cls.default_fresh_samples}
    assert fresh == {"heat", "poisson", "poisson_hig", "sine", "exp_inverse"}
    assert train_settings("heat")["fresh_samples"] and not train_settings("oscillators")["fresh_samples"]


def test_runs_recorded_before_the_setting_keep_their_identity():
    old = make_config("oscillators", "adam", budget=Budget(steps=5), settings={"n_train": 8})
    record = old.canonical_dict()
    assert "fresh_samples" not in record  # the digest of a run without it is unchanged
    on = make_config("oscillators", "adam", budget=Budget(steps=5), settings={"n_train": 8, "fresh_samples": "true"})
    assert on.digest() != old.digest()
    # fit's record: a run recorded without the setting resumes under its old value
    recorded = {"problem": "p", "settings": {"shuffle": False}}
    assert _identity(recorded) == _identity(
        json.loads(json.dumps({**recorded, "settings": {"shuffle": False, "fresh_samples": False}}))
    )
    assert _identity(recorded) != _identity({**recorded, "settings": {"shuffle": False, "fresh_samples": True}})
