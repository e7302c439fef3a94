"""Levenberg–Marquardt: the damped filter against NumPy float64, its limits, Nielsen's rule
by hand, the gain ratio on a model that is exact, and training from the command line."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from physgrad import Objective, half_inverse, routes
from physgrad.harness.cli import main
from physgrad.methods import JacobianPower, LevenbergMarquardt, adapt_damping, predicted_decrease
from physgrad.nets import MLP
from physgrad.routes import Damped


def numpy_lm(j, g, lam):
    """Jᵀ (J Jᵀ + λ I)⁻¹ g in float64 (the textbook formula, no SVD)."""
    j, g = np.asarray(j, np.float64), np.asarray(g, np.float64)
    return j.T @ np.linalg.solve(j @ j.T + lam * np.eye(j.shape[0]), g)


@pytest.mark.parametrize("shape", [(12, 40), (40, 12)])
@pytest.mark.parametrize("route", [routes.SVD(), routes.Gram()])
@pytest.mark.parametrize("lam", [1e-3, 0.3, 20.0])
def test_damped_filter_matches_the_numpy_formula(shape, route, lam):
    rng = np.random.default_rng(0)
    j, g = rng.standard_normal(shape), rng.standard_normal(shape[0])
    got = half_inverse(
        jnp.asarray(j), jnp.asarray(g), exponent=Damped(lam, relative=False), truncation=0.0, route=route
    )
    # For a tall J, J Jᵀ is singular: the formula still holds with λ > 0.
    np.testing.assert_allclose(np.asarray(got), numpy_lm(j, g, lam), rtol=1e-8, atol=1e-10)


def test_relative_damping_is_in_units_of_the_largest_squared_singular_value():
    rng = np.random.default_rng(1)
    j, g = 7.0 * rng.standard_normal((10, 30)), rng.standard_normal(10)
    s_max = np.linalg.svd(j, compute_uv=False).max()
    got = half_inverse(jnp.asarray(j), jnp.asarray(g), exponent=Damped(0.05), truncation=0.0, route=routes.Gram())
    np.testing.assert_allclose(np.asarray(got), numpy_lm(j, g, 0.05 * s_max**2), rtol=1e-8)


@pytest.mark.parametrize("route", [routes.SVD(), routes.Gram()])
def test_zero_damping_is_gauss_newton_and_large_damping_the_scaled_gradient(route):
    rng = np.random.default_rng(2)
    j, g = rng.standard_normal((15, 50)), rng.standard_normal(15)
    J, G = jnp.asarray(j), jnp.asarray(g)
    gn = np.linalg.pinv(j) @ g
    small = half_inverse(J, G, exponent=Damped(1e-14), truncation=0.0, route=route)
    np.testing.assert_allclose(np.asarray(small), gn, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(small), np.asarray(half_inverse(J, G, exponent=-1.0, route=route)), rtol=1e-7)
    lam = 1e9
    large = half_inverse(J, G, exponent=Damped(lam, relative=False), truncation=0.0, route=route)
    np.testing.assert_allclose(lam * np.asarray(large), j.T @ g, rtol=1e-6)


def _problem(key=0):
    """A small tanh network through a nonlinear simulator with a squared-error loss."""
    net = jax.tree.map(lambda a: a.astype(jnp.float64), MLP((3, 8, 2), jax.nn.tanh, key=jax.random.key(key)))
    params = net

    def predict(p, s):
        u = p(s["x"])
        return jnp.sin(u) + 0.5 * u

    def loss(y, s):
        return 0.5 * jnp.sum((y - s["t"]) ** 2)

    rng = np.random.default_rng(key)
    batch = {"x": jnp.asarray(rng.standard_normal((6, 3))), "t": jnp.asarray(rng.standard_normal((6, 2)))}
    return Objective(predict, loss), params, batch


def _dense_jacobian_and_gradient(objective, params, batch):
    flat, unravel = ravel_pytree(params)
    outputs = lambda th: jax.vmap(lambda s: objective.predict(unravel(th), s))(batch).ravel()  # noqa: E731
    j = np.asarray(jax.jit(jax.jacfwd(outputs))(flat))
    g = (np.asarray(jax.jit(outputs)(flat)) - np.asarray(batch["t"]).ravel()) / batch["x"].shape[0]
    return j, g


@pytest.fixture(scope="module")
def damped_case():
    """The problem and its dense J and g, built once for every route (they do not depend on it)."""
    objective, params, batch = _problem()
    return objective, params, batch, *_dense_jacobian_and_gradient(objective, params, batch)


@pytest.mark.parametrize(
    "route", [routes.Gram(), routes.SVD(), routes.Structured(), routes.BlockGram(3), routes.Lanczos(12)]
)
def test_every_route_gives_the_damped_direction(route, damped_case):
    objective, params, batch, j, g = damped_case
    lam = 0.01
    s_max = np.linalg.svd(j, compute_uv=False).max()
    # the route's direction compiled as one program, as a step runs it (eagerly, each of its
    # operations compiles on its own: twice the CPU)
    filtered = eqx.filter_jit(lambda p, b: JacobianPower(-1.0, 0.0, route).filtered(objective, p, b, Damped(lam)))
    direction, _ = filtered(params, batch)
    want = numpy_lm(j, g, lam * s_max**2)
    np.testing.assert_allclose(np.asarray(ravel_pytree(direction)[0]), want, rtol=1e-6, atol=1e-9 * np.abs(want).max())


def test_nielsen_rule_on_a_hand_made_sequence_of_gain_ratios():
    # μ ← μ·max(1/3, 1 − (2ρ − 1)³), ν ← 2 when ρ > 0; μ ← μ·ν, ν ← 2ν otherwise.
    ratios = [0.9, 0.5, -1.0, np.nan, 0.1, 2.0, 0.0]
    want = [  # (μ, ν, accepted), worked by hand from μ = 1, ν = 2
        (0.488, 2.0, True),  # 1 − 0.8³ = 0.488
        (0.488, 2.0, True),  # 1 − 0³ = 1
        (0.976, 4.0, False),
        (3.904, 8.0, False),  # NaN: rejected
        (5.902848, 2.0, True),  # 1 + 0.8³ = 1.512
        (1.967616, 2.0, True),  # 1 − 3³ < 1/3
        (3.935232, 4.0, False),  # ρ = 0 is not a decrease
    ]
    mu, nu = jnp.float64(1.0), jnp.float64(2.0)
    for rho, (mu_want, nu_want, ok_want) in zip(ratios, want):
        mu, nu, ok = adapt_damping(mu, nu, jnp.float64(rho))
        assert float(mu) == pytest.approx(mu_want, rel=1e-12)
        assert float(nu) == nu_want and bool(ok) == ok_want


def test_predicted_decrease_is_exact_for_linear_physics_and_a_quadratic_loss():
    rng = np.random.default_rng(3)
    a, q = jnp.asarray(rng.standard_normal((4, 5))), jnp.asarray(np.diag([1.0, 2.0, 3.0, 0.5]))

    def predict(p, s):
        return a @ (p["w"] @ s["x"])

    def loss(y, s):
        r = y - s["t"]
        return 0.5 * r @ q @ r + jnp.sum(r)

    objective = Objective(predict, loss)
    params = {"w": jnp.asarray(rng.standard_normal((5, 3)))}
    batch = {"x": jnp.asarray(rng.standard_normal((7, 3))), "t": jnp.asarray(rng.standard_normal((7, 4)))}
    delta = {"w": jnp.asarray(rng.standard_normal((5, 3)))}
    after = jax.tree.map(jnp.add, params, delta)
    actual = objective.batch_loss(params, batch) - objective.batch_loss(after, batch)
    np.testing.assert_allclose(float(predicted_decrease(objective, params, batch, delta)), float(actual), rtol=1e-10)


def test_lm_step_accepts_good_steps_and_rejects_bad_ones():
    objective, params, batch = _problem()
    method = LevenbergMarquardt(JacobianPower(-1.0, 0.0, routes.Gram()), damping=1e-2)
    state = method.init(params)
    step = jax.jit(method.step, static_argnums=0)
    new, state1, stats = step(objective, params, state, batch)
    assert bool(stats["accepted"]) and float(stats["gain_ratio"]) > 0
    assert float(objective.batch_loss(new, batch)) < float(stats["loss"])
    assert float(state1.acceptance.damping) < 1e-2  # a good step shrinks the damping
    # An optimizer that overshoots 50-fold makes the loss rise: the step is refused.
    bad = LevenbergMarquardt(method.rule, __import__("optax").sgd(50.0), damping=1e-2)
    same, state2, stats = jax.jit(bad.step, static_argnums=0)(objective, params, bad.init(params), batch)
    assert not bool(stats["accepted"])
    assert all(np.array_equal(x, y) for x, y in zip(jax.tree.leaves(same), jax.tree.leaves(params)))
    assert float(state2.acceptance.damping) == pytest.approx(2e-2) and float(state2.acceptance.growth) == 4.0


def test_levenberg_marquardt_entry_point_is_the_method_with_the_users_chain_under_plain_jit():
    """physgrad.levenberg_marquardt(predict, loss, optimizer=chain): jax.jit(lm.step) as it is,
    on a whole Equinox module, gives the method's own step bit for bit (accepted and refused)."""
    import optax

    import physgrad

    objective, params, batch = _problem()
    for lr, accepted in ((1.0, True), (50.0, False)):
        lm = physgrad.levenberg_marquardt(objective.predict, objective.loss, optimizer=optax.sgd(lr), damping=1e-2,
                                          truncation=0.0, route=routes.Gram())  # fmt: skip
        new, state, stats = jax.jit(lm.step)(params, lm.init(params), batch)
        method = LevenbergMarquardt(JacobianPower(-1.0, 0.0, routes.Gram()), optax.sgd(lr), damping=1e-2)
        want, want_state, _ = jax.jit(method.step, static_argnums=0)(objective, params, method.init(params), batch)
        assert bool(stats["accepted"]) is accepted
        for a, b in zip(jax.tree.leaves((new, state)), jax.tree.leaves((want, want_state))):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ValueError, match="damping"):
        physgrad.levenberg_marquardt(objective.predict, objective.loss, damping=0.0)


@pytest.mark.slow
def test_lm_trains_an_open_loop_problem_from_the_command_line(tmp_path, capsys):
    out = tmp_path / "study"
    settings = ["--set", "n_steps=8", "--set", "hidden=6", "--set", "n_train=64", "--set", "n_test=32",
                "--set", "batch_size=16"]  # fmt: skip
    code = main(
        ["compare", "oscillators", "--methods", "gn,lm", "--steps", "60", "--out", str(out), "--quiet", *settings]
    )
    assert code == 0
    import csv

    rows = {r["method"]: r for r in csv.DictReader(open(out / "summary.csv"))}
    assert rows["lm"]["status"] == "finished"
    first = [r for r in csv.DictReader(open(out / "results.csv")) if r["method"] == "lm" and r["split"] == "test"]
    losses = [float(r["value"]) for r in first if r["metric"] == "loss"]
    assert losses[-1] < 0.5 * losses[0]


@pytest.mark.skipif(jax.device_count() < 4, reason="needs 4 (forced host) devices")
@pytest.mark.parametrize("route", [routes.Gram(), routes.Structured()])
def test_lm_step_sharded_over_devices_equals_one_device(route):
    from physgrad.distributed import make_mesh, replicated, shard_batch, use_mesh

    objective, params, batch = _problem()
    batch = jax.tree.map(lambda a: jnp.concatenate([a, 0.5 * a[:2]]), batch)  # 8 samples
    method = LevenbergMarquardt(JacobianPower(-1.0, 1e-6, route), damping=1e-2)
    want = jax.jit(method.step, static_argnums=0)(objective, params, method.init(params), batch)
    with use_mesh(make_mesh(4)):
        got = jax.jit(lambda p, s, b: method.step(objective, replicated(p), s, shard_batch(b)))(
            params, method.init(params), batch
        )
    for x, y in zip(
        jax.tree.leaves((want[0], want[1].acceptance.damping)), jax.tree.leaves((got[0], got[1].acceptance.damping))
    ):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=1e-9, atol=1e-12)


def test_lm_takes_gauss_newtons_paper_settings_on_a_problem():
    from physgrad import Budget
    from physgrad.harness.config import make_config

    lm = make_config("poisson_hig", "lm", budget=Budget(steps=1)).phases[0]
    gn = make_config("poisson_hig", "gn", budget=Budget(steps=1)).phases[0]
    assert lm.batch_size == gn.batch_size
    assert {k: lm.hyperparameters[k] for k in ("lr", "truncation")} == {
        k: gn.hyperparameters[k] for k in ("lr", "truncation")
    }
