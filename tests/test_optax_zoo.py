"""The optax zoo: optax optimizers by name on DP gradients, against hand-written updates."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad import Budget, Objective
from physgrad.errors import ConfigError
from physgrad.harness.cli import main
from physgrad.harness.config import make_config, method_slug, parse_method, split_methods
from physgrad.harness.registry import METHODS, describe, hyperparameters, optax_names


def quadratic():
    """L = mean_i ½‖A w − t_i‖² with a fixed A: a convex least-squares objective."""
    rng = np.random.default_rng(0)
    a = jnp.asarray(rng.standard_normal((6, 4)))
    objective = Objective(lambda p, s: a @ p["w"], lambda y, s: 0.5 * jnp.sum((y - s["t"]) ** 2))
    batch = {"t": jnp.asarray(rng.standard_normal((5, 6)))}
    return objective, {"w": jnp.asarray(rng.standard_normal(4))}, batch, np.asarray(a), np.asarray(batch["t"])


def test_lion_step_equals_the_hand_written_update():
    objective, params, batch, a, t = quadratic()
    lr, b1, b2, wd = 0.05, 0.9, 0.99, 0.01
    method = METHODS["optax:lion"](lr=lr, b1=b1, b2=b2, weight_decay=wd)
    state = method.init(params)
    w, m = np.asarray(params["w"]), np.zeros(4)
    for _ in range(3):
        g = a.T @ (a @ w - t.mean(0))  # ∇ of the batch-mean loss
        c = b1 * m + (1 - b1) * g  # Lion (Chen et al. 2023, Alg. 2)
        w = w - lr * (np.sign(c) + wd * w)
        m = b2 * m + (1 - b2) * g
        params, state, _ = method.step(objective, params, state, batch)
        np.testing.assert_allclose(np.asarray(params["w"]), w, rtol=1e-10)


def test_line_search_lbfgs_gets_the_loss_function_and_solves_least_squares():
    objective, params, batch, a, t = quadratic()
    method = METHODS["optax:lbfgs"]()  # lr 1: the line search decides the step
    state = method.init(params)
    step = jax.jit(method.step, static_argnums=0)
    for _ in range(20):
        params, state, _ = step(objective, params, state, batch)
    want = np.linalg.lstsq(a, t.mean(0), rcond=None)[0]
    np.testing.assert_allclose(np.asarray(params["w"]), want, rtol=1e-6, atol=1e-8)


def test_sophia_gets_the_objective_for_its_hessian_estimate():
    objective, params, batch, *_ = quadratic()
    method = METHODS["optax.contrib:sophia"](lr=0.05)
    state = method.init(params)
    before = float(objective.batch_loss(params, batch))
    step = jax.jit(method.step, static_argnums=0)  # once: a jit made inside the loop recompiles every iteration
    for _ in range(30):
        params, state, _ = step(objective, params, state, batch)
    assert float(objective.batch_loss(params, batch)) < before


def test_names_hyperparameters_and_defaults():
    names = optax_names()
    assert {"optax:lion", "optax:adamw", "optax.contrib:muon", "optax.contrib:sophia"} <= set(names)
    assert "optax:dpsgd" not in names  # needs per-example gradients
    assert "optax:lion" in METHODS and "optax:nope" not in METHODS
    assert hyperparameters("optax:lion") == {"lr": 1e-3, "b1": 0.9, "b2": 0.99, "weight_decay": 1e-3}
    assert hyperparameters("optax.contrib:prodigy")["lr"] == 1.0  # learning-rate free: optax's own default
    assert describe("optax:adamw").startswith("optax:adamw on DP gradients")
    # On a problem, a zoo entry takes Adam's batch size and, when optax needs one, its learning rate.
    config = make_config("oscillators", "optax:lion", budget=Budget(steps=1), settings={"b1": "0.8"})
    adam = make_config("oscillators", "adam", budget=Budget(steps=1))
    (phase,) = config.phases
    assert phase.batch_size == adam.phases[0].batch_size
    assert phase.hyperparameters["lr"] == adam.phases[0].hyperparameters["lr"] and phase.hyperparameters["b1"] == 0.8
    prodigy = make_config("oscillators", "optax.contrib:prodigy", budget=Budget(steps=1))
    assert prodigy.phases[0].hyperparameters["lr"] == 1.0


def test_sequences_with_optax_names():
    assert parse_method("optax:lion") == [("optax:lion", None)]
    assert parse_method("optax:lion:100,hig") == [("optax:lion", 100), ("hig", None)]
    assert parse_method("adam:5,optax.contrib:muon") == [("adam", 5), ("optax.contrib:muon", None)]
    assert split_methods("adam,optax:lion,optax:adamw:20,hig") == ["adam", "optax:lion", "optax:adamw:20,hig"]
    assert method_slug("optax:adamw:20,hig") == "optaxadamw20+hig"
    with pytest.raises(ConfigError, match="valid choices: optax:adabelief"):
        parse_method("optax:lionn")
    with pytest.raises(ConfigError, match="optax:NAME"):
        parse_method("adamm")


@pytest.mark.parametrize("argv", [["--methods", "optax:lionn"], ["--methods", "adam", "--set", "optax:lion.b1=0.5"]])
def test_bad_optax_input_is_one_line_exit_2(argv, tmp_path, capsys):
    assert main(["compare", "hig_toy", "--steps", "2", "--out", str(tmp_path / "x"), *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "valid choices" in err


@pytest.mark.parametrize("name", ["optax:adamw", "optax:lion", "optax.contrib:muon", "optax.contrib:prodigy"])
def test_zoo_entries_train_an_open_loop_problem(name, tmp_path):
    import csv

    out = tmp_path / "study"
    assert main(["compare", "hig_toy", "--methods", name, "--steps", "40", "--out", str(out), "--quiet"]) == 0
    rows = [r for r in csv.DictReader(open(out / "results.csv")) if r["split"] == "test" and r["metric"] == "loss"]
    assert float(rows[-1]["value"]) < float(rows[0]["value"])
