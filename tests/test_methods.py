"""Every registered method: one step against an independent reference, and training."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from physgrad import Budget
from physgrad.engine import Placement, Steps
from physgrad.harness.config import make_config
from physgrad.harness.registry import METHODS
from physgrad.harness.train import build, make_evaluate, make_step, settings_of

TINY = {"n_steps": "8", "hidden": "6", "n_train": "64", "n_test": "64", "dtype": "float64", "batch_size": "16"}


def tiny_setup(method, **extra):
    config = make_config("oscillators", method, budget=Budget(steps=1), settings={**TINY, **extra})
    setup = build(config)
    batch = jax.tree.map(lambda a: a[:16], setup.data["train"])
    return config, setup, batch


def central_differences(f, flat, eps=1e-6):
    """(f(θ + ε e_j) − f(θ − ε e_j)) / 2ε for every j, stacked along the last axis. The 2P
    perturbed parameter vectors are formed in NumPy and evaluated by one vmapped call of the
    jitted ``f`` (one at a time, each ``flat.at[j].add`` and call costs an eager dispatch)."""
    theta, shifts = np.asarray(flat), eps * np.eye(flat.size)
    values = np.asarray(jax.jit(jax.vmap(f))(jnp.asarray(np.concatenate([theta + shifts, theta - shifts]))))
    return np.moveaxis((values[: flat.size] - values[flat.size :]) / (2 * eps), 0, -1)


def numpy_gradient(setup, batch, eps=1e-6):
    flat, unravel = ravel_pytree(setup.params)
    return central_differences(lambda th: setup.objective.batch_loss(unravel(th), batch), flat, eps)


def test_dp_gradient_and_adam_step_against_hand_written_adam():
    config, setup, batch = tiny_setup("adam", lr="0.01")
    flat, unravel = ravel_pytree(setup.params)
    g = numpy_gradient(setup, batch)
    params, state = setup.params, setup.method.init(setup.params)
    theta, m, v = np.asarray(flat), np.zeros_like(g), np.zeros_like(g)
    lr, b1, b2, eps = 0.01, 0.9, 0.999, 1e-7
    m, v = (1 - b1) * g, (1 - b2) * g**2
    want = theta - lr * (m / (1 - b1)) / (np.sqrt(v / (1 - b2)) + eps)
    # jitted as the engine runs it: one program, where an eager step compiles op by op
    params, state, stats = jax.jit(lambda p, s, b: setup.method.step(setup.objective, p, s, b))(params, state, batch)
    np.testing.assert_allclose(np.asarray(ravel_pytree(params)[0]), want, rtol=1e-6, atol=1e-9)
    assert float(stats["loss"]) == pytest.approx(float(setup.objective.batch_loss(setup.params, batch)))


# make test: each exponent once and each route once (the step is the same code for both
# exponents, which only change the spectral filter; half_inverse's every exponent × route is
# test_half_inverse::test_matches_numpy_formula); the other two pairings in the slow tier.
@pytest.mark.parametrize(
    "method,exponent,route",
    [("hig", -0.5, "svd"), ("gn", -1.0, "gram"),
     pytest.param("hig", -0.5, "gram", marks=pytest.mark.slow), pytest.param("gn", -1.0, "svd", marks=pytest.mark.slow)],
)  # fmt: skip
def test_jacobian_power_step_against_numpy(method, exponent, route):
    # τ = 1e-3 keeps the finite-difference Jacobian's error from being amplified by σ^κ.
    config, setup, batch = tiny_setup(method, lr="0.5", truncation="1e-3", route=route)
    flat, unravel = ravel_pytree(setup.params)
    # independent pieces: J from finite differences of the outputs, g = 2 (y − y*) / b
    outputs = lambda th: jax.vmap(lambda s: setup.objective.predict(unravel(th), s))(batch).ravel()  # noqa: E731
    jac = central_differences(outputs, flat)
    g = 2 * (np.asarray(jax.jit(outputs)(flat)) - np.asarray(batch["x0"]).ravel()) / 16
    u, s, vt = np.linalg.svd(jac, full_matrices=False)
    keep = s > 1e-3 * s.max()
    want = np.asarray(flat) - 0.5 * vt[keep].T @ (s[keep] ** exponent * (u[:, keep].T @ g))
    step = jax.jit(lambda p, b: setup.method.step(setup.objective, p, setup.method.init(p), b))
    params, _, _ = step(setup.params, batch)
    np.testing.assert_allclose(np.asarray(ravel_pytree(params)[0]), want, rtol=1e-4, atol=1e-6)


ROLLOUT_METHODS = ("bptt", "sbptt_m", "sbptt_c", "no_temporal")
STEPPER_METHODS = ("one", "nog", "wig")


# make test: one method per update-rule family; the rest (more optax optimizers, newton, the
# other rollout policies and modalities, kfac) in the slow tier
FAST_METHODS = {"adam", "gn", "hig", "lm", "sip", "sbptt_c", "one", "wig"}


@pytest.mark.parametrize(
    "method", [m if m in FAST_METHODS else pytest.param(m, marks=pytest.mark.slow) for m in sorted(METHODS)]
)
def test_every_method_lowers_the_loss_in_float32_without_recompiling(method):
    settings = {k: v for k, v in TINY.items() if k != "dtype"}
    if method == "gn":
        # This 6-unit ReLU net's Jacobian has singular values down to 1e-10 σ_max; the full
        # inverse of those just above τ = 1e-6 blows up (GN's known instability).
        settings["truncation"] = "1e-2"
    if method == "newton":
        # A network's loss Hessian is indefinite: undamped Newton steps toward saddles.
        settings["damping"] = "10.0"
    problem = "oscillators"
    if method in ROLLOUT_METHODS:  # these need a closed loop
        problem, settings = (
            "cartpole",
            {"n_train": "64", "n_test": "16", "batch_size": "16", "dt": "0.1", "n_steps": "10"},
        )
    if method in STEPPER_METHODS:  # these need a time-stepper: 4 trajectories x 16 windows
        problem, settings = (
            "advection_1d",
            {"n_train": "4", "n_test": "2", "horizon": "20", "batch_size": "16", "iterations": "4"},
        )
    config = make_config(problem, method, budget=Budget(steps=1), settings=settings)
    setup = build(config)
    step = make_step(setup, config.phases[0].batch_size)
    evaluate = make_evaluate(setup)
    data = setup.data["train"]
    steps = Steps(setup, Placement(), settings_of(config), config.seed)  # the engine's batch order (shuffled: steppers)
    params, state = setup.params, setup.method.init(setup.params)
    before = float(evaluate(params, data)["loss"])
    for i in range(40):
        epoch, batch = divmod(i, 4)
        params, state, _ = step(params, state, data, steps.order(0, epoch), jnp.int32(batch))
    assert step._cache_size() == 1
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(params))
    assert float(evaluate(params, data)["loss"]) < before


def test_short_hig_run_lowers_test_loss_tenfold():
    config = make_config(
        "oscillators", "hig", budget=Budget(steps=1),
        settings={"n_steps": "24", "n_train": "256", "n_test": "256", "batch_size": "32"},
    )  # fmt: skip
    setup = build(config)
    step, evaluate = make_step(setup, 32), make_evaluate(setup)
    train, test = setup.data["train"], setup.data["test"]
    order = jnp.arange(256, dtype=jnp.int32)
    params, state = setup.params, setup.method.init(setup.params)
    before = float(evaluate(params, test)["loss"])
    # 5 epochs of 8 batches: the test loss is ~150x lower after 40 steps (~100x after 25), far
    # past the tenfold asked; 200 steps only added run time.
    for i in range(40):
        params, state, _ = step(params, state, train, order, jnp.int32(i % 8))
    after = float(evaluate(params, test)["loss"])
    assert after < before / 10, (before, after)
