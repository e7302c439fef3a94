"""Method sequences (``adam:N,hig``): parsing, exact hand-over, resume, evaluation schedule."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad import Budget, ConfigError
from physgrad.harness.cli import main
from physgrad.harness.config import make_config, parse_method, split_methods
from physgrad.harness.train import build, make_step, read_metrics, train

SMALL = {"n_train": "128", "n_test": "64", "adam.batch_size": "32", "hig.batch_size": "16"}


def flat(tree):
    return np.concatenate([np.ravel(np.asarray(x)) for x in jax.tree.leaves(eqx.filter(tree, eqx.is_inexact_array))])


def test_parse_and_split():
    assert parse_method("hig") == [("hig", None)]
    assert parse_method("adam:2000,hig") == [("adam", 2000), ("hig", None)]
    assert parse_method("adam:5,gn:3,hig") == [("adam", 5), ("gn", 3), ("hig", None)]
    assert split_methods("adam,hig,adam:2000,hig") == ["adam", "hig", "adam:2000,hig"]
    assert split_methods("adam:10,gn:3,hig, sgd") == ["adam:10,gn:3,hig", "sgd"]


@pytest.mark.parametrize(
    "spec, message",
    [
        ("adam:2000", "runs until the budget is spent"),
        ("adam,hig", "give adam's number of steps as adam:N"),
        ("adam:x,hig", "must be a number of steps"),
        ("adam:0,hig", "positive number of steps"),
        ("adam:5,nope", "unknown method 'nope'; valid choices:"),
    ],
)
def test_bad_sequences(spec, message):
    with pytest.raises(ConfigError, match=message):
        make_config("hig_toy", spec, budget=Budget(steps=1))


def test_scoped_settings_reach_their_stage_only():
    config = make_config("hig_toy", "adam:3,hig", budget=Budget(steps=5), settings={**SMALL, "hig.lr": "0.25"})
    adam, hig = config.phases
    assert (adam.method, adam.steps, adam.batch_size, adam.hyperparameters["lr"]) == ("adam", 3, 32, 1e-3)
    assert (hig.method, hig.steps, hig.batch_size, hig.hyperparameters["lr"]) == ("hig", None, 16, 0.25)
    with pytest.raises(ConfigError, match="'gn' is not a method of 'adam:3,hig'"):
        make_config("hig_toy", "adam:3,hig", budget=Budget(steps=5), settings={"gn.lr": "1"})


def test_hand_over_is_exact(tmp_path):
    """adam:3,hig for 5 steps equals 3 Adam steps, then 2 HIG steps from those parameters
    with a fresh method state and the stage's own batches (written out by hand)."""
    config = make_config("hig_toy", "adam:3,hig", budget=Budget(steps=5), settings=SMALL)
    summary = train(config, tmp_path / "run")
    assert summary["stage_steps"] == {"0:adam": 3, "1:hig": 2}

    setup = build(config)
    order = jnp.arange(128, dtype=jnp.int32)
    data = setup.data["train"]
    adam, hig = setup.stages[0].method, setup.stages[1].method
    params, state = setup.params, adam.init(setup.params)
    adam_step = make_step(setup, 32, adam)
    for i in range(3):
        params, state, _ = adam_step(params, state, data, order, jnp.int32(i))
    handed_over = params
    hig_step = make_step(setup, 16, hig)
    state = hig.init(params)
    for i in range(2):  # the HIG stage starts its own pass over the data at batch 0
        params, state, _ = hig_step(params, state, data, order, jnp.int32(i))
    got = physgrad.load_network(tmp_path / "run")
    np.testing.assert_array_equal(flat(got), flat(params))
    assert not np.array_equal(flat(handed_over), flat(params))
    # the stage boundary is evaluated, so the curve shows the switch
    assert 3 in {r["step"] for r in read_metrics(tmp_path / "run" / "metrics.csv")}


def test_resume_across_the_switch_equals_one_run(tmp_path):
    config = make_config("hig_toy", "adam:3,hig", budget=Budget(steps=5), settings=SMALL)
    train(config, tmp_path / "whole")
    first = make_config("hig_toy", "adam:3,hig", budget=Budget(steps=3), settings=SMALL)
    train(first, tmp_path / "parts")
    train(config, tmp_path / "parts", resume=True)
    np.testing.assert_array_equal(
        flat(physgrad.load_network(tmp_path / "parts")), flat(physgrad.load_network(tmp_path / "whole"))
    )


def test_epoch_budget_counts_each_stage_batch_size(tmp_path):
    # 128 samples: an Adam epoch is 4 steps (batch 32), a HIG epoch 8 steps (batch 16)
    config = make_config("hig_toy", "adam:4,hig", budget=Budget(epochs=2), settings=SMALL)
    summary = train(config, tmp_path / "run")
    assert summary["steps"] == 4 + 8 and summary["epochs"] == pytest.approx(2.0)


def test_eval_seconds_spaces_evaluations_in_training_time(tmp_path):
    settings = {"n_train": "128", "n_test": "64", "batch_size": "32", "eval_seconds": "0.2"}
    train(make_config("hig_toy", "adam", budget=Budget(seconds=0.6), settings=settings), tmp_path / "run")
    times = sorted({r["wall_time"] for r in read_metrics(tmp_path / "run" / "metrics.csv") if r["metric"] == "loss"})
    assert len(times) == 4  # at 0, then at the first chunk past 0.2, 0.4 and 0.6 s (the budget)
    # Each evaluation in its own 0.2 s window: none skipped, none doubled. How far past its
    # mark it lands is one chunk's time, which a loaded machine (or jaxtyping's run-time
    # checks in make test-typed) stretches; CI saw 0.47 for the mark at 0.4.
    for k, t in enumerate(times):
        assert 0.2 * k <= t < 0.2 * (k + 1), times


def test_compare_runs_a_sequence_next_to_plain_methods(tmp_path, capsys):
    out = tmp_path / "study"
    argv = ["compare", "hig_toy", "--methods", "adam,adam:3,hig", "--steps", "5", "--out", str(out), "--quiet"]
    argv += [x for k, v in SMALL.items() for x in ("--set", f"{k}={v}")]
    assert main(argv) == 0
    names = sorted(p.name.rsplit("-", 1)[0] for p in (out / "runs").iterdir())
    assert names == ["adam-seed0", "adam3+hig-seed0"]
    assert json.loads((out / "study.json").read_text())["methods"] == ["adam", "adam:3,hig"]
    assert "adam:3,hig" in capsys.readouterr().out
