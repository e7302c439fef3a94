"""Stabilised BPTT: the three control problems' physics against independent references,
the methods on them, and sweeps from the command line."""

import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad.harness.cli import main
from physgrad.harness.config import Budget, ConfigError, make_config
from physgrad.harness.train import build, make_step
from physgrad.problems import CartPole, Guidance, QuantumControl
from physgrad.problems.quantum_control import QuantumController

# --- cart-pole -------------------------------------------------------------------------


def cartpole_numpy(s, force, dt=0.01, g=9.8, m=0.1, big_m=1.1, l=0.5):
    """One semi-implicit Euler step of the authors' multi-pole equations, a loop in float64."""
    s = np.array(s, dtype=np.float64)
    x_acc_sum, theta_acc = 0.0, []
    for theta, omega in s[1:]:
        a = (force + m * l * math.sin(theta) * omega**2) / big_m
        acc = (g * math.sin(theta) - math.cos(theta) * a) / (l * (4 / 3 - m * math.cos(theta) ** 2 / big_m))
        theta_acc.append(acc)
        x_acc_sum += math.sin(theta) * omega**2 - acc * math.cos(theta)
    x_acc = (force + m * l * x_acc_sum) / big_m
    out = s.copy()
    out[:, 1] += dt * np.array([x_acc] + theta_acc)
    out[:, 0] += dt * out[:, 1]
    return out


def test_cartpole_step_equals_a_numpy_loop():
    problem = CartPole(poles=3)
    s = problem.make_data(None)["train"][5]
    physics = jax.jit(problem.physics)  # one program for the three forces
    for force in (0.0, 3.7, -12.0):
        got = physics(s, jnp.float32(force))
        np.testing.assert_allclose(got, cartpole_numpy(s, force), rtol=2e-5, atol=2e-6)


def cartpole_invariants(s, m=0.1, big_m=1.1, l=0.5, g=9.8):
    """Energy and horizontal momentum of a single rod (half-length l) on a cart, F = 0."""
    (x, v), (theta, omega) = s
    energy = 0.5 * big_m * v**2 + m * l * v * omega * np.cos(theta) + 0.5 * (4 / 3) * m * l**2 * omega**2
    return energy + m * g * l * np.cos(theta), big_m * v + m * l * omega * np.cos(theta)


def test_single_pole_conserves_energy_and_momentum_as_dt_shrinks():
    """With F = 0 the one-pole equations are the exact Lagrangian dynamics of a rod on a cart:
    energy and momentum are conserved; semi-implicit Euler's drift falls with dt (order 1)."""
    s0 = np.array([[0.0, 0.3], [2.5, -1.0]])
    drifts = []
    for dt in (1e-3, 5e-4):
        problem = CartPole(poles=1, dt=dt)
        step = jax.jit(lambda s: problem.physics(s, jnp.float64(0.0)))
        s = jnp.asarray(s0)
        for _ in range(int(round(1.0 / dt))):
            s = step(s)
        e0, p0 = cartpole_invariants(s0)
        e1, p1 = cartpole_invariants(np.asarray(s))
        drifts.append((abs(e1 - e0), abs(p1 - p0)))
    assert drifts[1][0] < 1e-3 and drifts[1][1] < 1e-3, drifts
    assert drifts[1][0] < 0.7 * drifts[0][0] and drifts[1][1] < 0.7 * drifts[0][1], drifts


def test_cartpole_data_network_and_loss_follow_the_protocol():
    problem = CartPole(poles=2)
    data = problem.make_data(jax.random.key(0))
    assert data["train"].shape == (256, 3, 2) and data["test"].shape == (256, 3, 2)
    np.testing.assert_array_equal(data["train"], problem.make_data(jax.random.key(7))["train"])  # data seed 42
    theta = np.asarray(data["train"][:, 1:, 0])
    assert np.all(np.abs(theta - np.pi) <= np.pi / 6 + 1e-6)
    assert np.all(np.abs(np.asarray(data["train"][:, 0, :])) <= 1)
    assert physgrad.parameter_count(CartPole(poles=1).make_network(jax.random.key(0))) == 10_701
    assert physgrad.parameter_count(CartPole(poles=4).make_network(jax.random.key(0))) == 11_301
    net = problem.make_network(jax.random.key(0))
    assert float(problem.control(net, data["train"][0])) == 0.0  # zero-initialised last kernel
    y = problem.predict(net, data["train"][0])
    np.testing.assert_allclose(problem.loss(y, data["train"][0]), 1 - np.mean(np.cos(y[0][-1, 1:, 0])), rtol=1e-6)


# --- guidance by repulsion ------------------------------------------------------------------


def guidance_numpy(s, c, p: Guidance):
    """The authors' forces as a loop over agents in float64, then an explicit Euler step."""
    s, c = np.asarray(s, np.float64), np.asarray(c, np.float64)
    nd = p.drivers
    x, v = s[:, 0], s[:, 1]
    dist = lambda r: p.eps + np.linalg.norm(r)  # noqa: E731
    acc = np.zeros_like(x)
    centre = x[nd:].sum(axis=0)
    for d in range(nd):
        rel = x[d] - centre
        acc[d] = c[d, 0] * rel + c[d, 1] * np.array([-rel[1], rel[0]]) - p.friction_driver * v[d]
        for o in range(nd):
            if o != d:
                acc[d] += p.c_spread * (x[d] - x[o]) / dist(x[d] - x[o]) ** 2
    for e in range(nd, len(x)):
        acc[e] = -p.friction_evader * v[e]
        for d in range(nd):
            acc[e] += p.c_evade * (x[e] - x[d]) / dist(x[d] - x[e]) ** 2
        for o in range(nd, len(x)):
            if o != e:
                r = x[o] - x[e]
                acc[e] += p.c_flock * (p.flock_distance / dist(r) - 1) / dist(r) * r
    return np.stack([x + p.dt * v, v + p.dt * acc], axis=1)


def test_guidance_step_equals_a_numpy_loop():
    problem = Guidance()
    s = problem.make_data(None)["train"][3]
    s = s.at[:, 1].set(jax.random.normal(jax.random.key(1), (6, 2), jnp.float32))  # non-zero velocities
    c = jax.random.normal(jax.random.key(2), (2, 2), jnp.float32)
    np.testing.assert_allclose(jax.jit(problem.physics)(s, c), guidance_numpy(s, c, problem), rtol=1e-5, atol=1e-5)


def test_guidance_data_network_and_the_degenerate_stopped_gradient():
    problem = Guidance(rc=0.01)
    data = problem.make_data(None)["train"]
    assert data.shape == (256, 6, 2, 2)
    radius = np.linalg.norm(np.asarray(data[:, :2, 0]), axis=-1)
    assert np.all((radius >= 3 - 1e-5) & (radius <= 4 + 1e-5))
    assert np.all(np.asarray(data[:, :, 1]) == 0)
    assert physgrad.parameter_count(problem.make_network(jax.random.key(0))) == 13_004
    # S: c_k moves only the drivers' velocities, the loss reads evader positions one step
    # later, and the control term vanishes at a zero output, so the gradient is exactly 0.
    setup = build(make_config("guidance", "no_temporal", budget=Budget(steps=1), settings={"rc": "0.01"}))
    system, batch = setup.objective.rollout, setup.data["train"][:8]
    grad = jax.jit(lambda p, b, policy: physgrad.rollout.value_and_grad(system, p, b, policy)[1], static_argnums=2)
    g = grad(setup.params, batch, physgrad.rollout.S())
    assert all(float(jnp.max(jnp.abs(x))) == 0.0 for x in jax.tree.leaves(g))
    g = grad(setup.params, batch, physgrad.rollout.R())
    assert max(float(jnp.max(jnp.abs(x))) for x in jax.tree.leaves(g)) > 0


# --- quantum control ----------------------------------------------------------------


def test_crank_nicolson_is_unitary_and_evolves_eigenstates_by_the_cayley_phase():
    problem = QuantumControl()
    psi = problem.make_data(None)["train"][0]
    controls = 5 * jax.random.normal(jax.random.key(0), (128,), jnp.float32)
    states, _ = problem.simulate(controls, psi)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(states), axis=1), 1.0, atol=2e-5)
    # u = 0: φ_n is an eigenvector of H with λ_n = (2 − 2 cos(π n/33))/dx², so CN multiplies
    # it by the Cayley factor (1 − i dt λ/2)/(1 + i dt λ/2) each step.
    n, steps = 4, 128
    phi = problem.box.eigenstate(n).astype(jnp.complex64)
    lam = (2 - 2 * np.cos(np.pi * n / 33)) / (2 / 33) ** 2
    factor = (1 - 0.5j * problem.dt * lam) / (1 + 0.5j * problem.dt * lam)
    states, _ = problem.simulate(jnp.zeros(steps, jnp.float32), phi)
    np.testing.assert_allclose(states[-1], factor**steps * np.asarray(phi), atol=5e-5)


def test_quantum_controller_equals_equinox_convolutions():
    net = QuantumController(32, 60, key=jax.random.key(0))
    assert physgrad.parameter_count(net) == 11_701
    net = eqx.tree_at(
        lambda m: (m.bias1, m.bias2),
        net,
        (0.1 * jnp.arange(60.0, dtype=jnp.float32), -0.05 * jnp.ones(60, jnp.float32)),
    )
    conv2 = eqx.nn.Conv2d(1, 60, (3, 2), stride=2, key=jax.random.key(1), dtype=jnp.float32)
    conv2 = eqx.tree_at(lambda c: (c.weight, c.bias), conv2, (net.kernel1[:, None], net.bias1[:, None, None]))
    conv1 = eqx.nn.Conv1d(60, 60, 3, stride=2, key=jax.random.key(2), dtype=jnp.float32)
    conv1 = eqx.tree_at(
        lambda c: (c.weight, c.bias), conv1, (jnp.transpose(net.kernel2, (0, 2, 1)), net.bias2[:, None])
    )
    psi = QuantumControl().make_data(None)["test"][1]
    h = jnp.tanh(conv2(jnp.stack([psi.real, psi.imag], -1)[None]))[:, :, 0]  # (60, 15)
    h = jnp.tanh(conv1(h))  # (60, 7)
    reference = net.out(h.T.ravel())[0]  # (row, channel) order, as the einsum route flattens
    np.testing.assert_allclose(net(psi), reference, rtol=1e-5, atol=1e-6)


def test_quantum_loss_vanishes_at_the_target_eigenstate_only():
    problem = QuantumControl(eigenstate=4)
    phi = [problem.box.eigenstate(n).astype(jnp.complex64) for n in (3, 4, 5)]
    losses = [float(problem.step_loss(p, 0.0, 0)) for p in phi]
    np.testing.assert_allclose(losses, [1.0, 0.0, 1.0], atol=1e-6)
    states, controls = problem.simulate(jnp.zeros(128, jnp.float32), phi[1])  # stays there, up to phase
    assert abs(float(problem.loss((states, controls), phi[1]))) < 1e-3


def test_quantum_data_are_normalised_superpositions_of_the_two_lowest_states():
    problem = QuantumControl(eigenstate=5)
    psi = np.asarray(problem.make_data(None)["train"])
    assert psi.shape == (256, 32) and psi.dtype == np.complex64
    np.testing.assert_allclose(np.linalg.norm(psi, axis=1), 1.0, atol=1e-5)
    basis = np.stack([problem.box.eigenstate(1), problem.box.eigenstate(2)])
    inside = np.abs(psi @ basis.T) ** 2
    np.testing.assert_allclose(inside.sum(axis=1), 1.0, atol=1e-5)
    y = problem.predict(problem.make_network(jax.random.key(0)), jnp.asarray(psi[0]))
    assert 0 < float(problem.loss(y, psi[0])) <= 128


# --- the methods on the problems -------------------------------------------------------


def one_update(problem, method, settings=None):
    setup = build(make_config(problem, method, budget=Budget(steps=1), settings=settings or {}))
    step = make_step(setup, 8)
    state = setup.method.init(setup.params)
    order = jnp.arange(256)
    return setup, step(setup.params, state, setup.data["train"], order, 3)


# the combination is the same code for every problem: cart-pole runs in `make test`, guidance
# and quantum control (the costliest to compile) in the slow tier
@pytest.mark.parametrize(
    "problem",
    [
        "cartpole",
        pytest.param("guidance", marks=pytest.mark.slow),
        pytest.param("quantum_control", marks=pytest.mark.slow),
    ],
)
@pytest.mark.costly("the fast tier's one check of the one-pass combination: two setups, one program of four gradients")
def test_one_pass_and_two_pass_combination_give_the_same_gradient(problem):
    # Not zero-initialised: at a zero last kernel ∂N/∂s = 0 and g_M = g_R, masking nothing.
    settings = {"poles": "2", "zero_init": "false"} if problem == "cartpole" else {}
    settings = {"zero_init": "false"} if problem == "guidance" else settings
    # the setups alone: a training step of sbptt_c through the engine is test_methods' (FAST_METHODS)
    setup = build(make_config(problem, "sbptt_c", budget=Budget(steps=1), settings={**settings, "one_pass": "true"}))
    two = build(make_config(problem, "sbptt_c", budget=Budget(steps=1), settings={**settings, "one_pass": "false"}))
    system, batch = setup.objective.rollout, setup.data["train"][:8]

    @jax.jit  # one program for the four gradients, not two programs and two eager rollouts
    def gradients(p, b):
        _, g_m = physgrad.rollout.value_and_grad(system, p, b, physgrad.rollout.M())
        _, g_r = physgrad.rollout.value_and_grad(system, p, b, physgrad.rollout.R())
        return setup.method.rule.gradient(system, p, b), two.method.rule.gradient(system, p, b), g_m, g_r

    (l1, g1, s1), (l2, g2, s2), g_m, g_r = gradients(setup.params, batch)
    np.testing.assert_allclose(l1, l2, rtol=1e-6)
    np.testing.assert_allclose(s1["cos_mr"], s2["cos_mr"], rtol=1e-4, atol=1e-6)
    masked = 0
    for a, b, m_, r in zip(*(jax.tree.leaves(t) for t in (g1, g2, g_m, g_r))):
        scale = float(jnp.max(jnp.abs(b))) + 1e-30
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-5 * scale)
        np.testing.assert_allclose(b, jnp.where(jnp.sign(m_) == jnp.sign(r), m_, 0), rtol=1e-4, atol=1e-5 * scale)
        masked += int(jnp.sum((b == 0) & (m_ != 0)))
    assert masked > 0  # g_M and g_R differ in sign somewhere, so the mask acts


def test_methods_log_squared_gradient_norm_before_clipping():
    setup, (params, _, stats) = one_update("guidance", "bptt", {"clip": "norm", "rc": "0.01"})
    reference = jax.jit(lambda p, b: physgrad.rollout.value_and_grad(setup.objective.rollout, p, b)[1])  # one program
    grads = reference(setup.params, setup.data["train"][24:32])
    norm2 = sum(float(jnp.vdot(g, g)) for g in jax.tree.leaves(grads))
    assert norm2 > 10  # far above the clip threshold 1: a norm logged after clipping would be 1
    np.testing.assert_allclose(stats["grad_norm2"], norm2, rtol=1e-4)


def test_rollout_methods_refuse_open_loop_problems_and_bad_clip_modes():
    with pytest.raises(ConfigError, match="closed-loop problem"):
        build(make_config("oscillators", "bptt", budget=Budget(steps=1)))
    with pytest.raises(ConfigError, match="valid choices: value, norm, none"):
        make_config("cartpole", "sbptt_c", budget=Budget(steps=1), settings={"clip": "max"})


@pytest.mark.slow
def test_cli_sweep_runs_every_cell_and_draws_panels(tmp_path, capsys):
    out = tmp_path / "grid"
    code = main(["compare", "cartpole", "--methods", "bptt,sbptt_c", "--steps", "4", "--set", "poles=1,2",
                 "--set", "clip=value,none", "--set", "eval_every=2", "--set", "n_train=16", "--set", "n_test=8",
                 "--out", str(out), "--quiet"])  # fmt: skip
    assert code == 0
    grid = json.loads((out / "grid.json").read_text())
    assert grid["grid"] == {"poles": ["1", "2"], "clip": ["value", "none"]}
    cells = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert cells == ["poles1_clipnone", "poles1_clipvalue", "poles2_clipnone", "poles2_clipvalue"]
    assert (out / "grid.png").exists() and (out / "grid_summary.csv").exists()
    assert "poles=2, clip=none" in capsys.readouterr().out
    assert main(["report", str(out), "--panel", "clip"]) == 0
    # a second run skips every finished run
    assert main(["compare", "cartpole", "--methods", "bptt,sbptt_c", "--steps", "4", "--set", "poles=1,2",
                 "--set", "clip=value,none", "--set", "eval_every=2", "--set", "n_train=16", "--set", "n_test=8",
                 "--out", str(out), "--quiet"]) == 0  # fmt: skip
    assert capsys.readouterr().out.count("done already") == 8


def test_cli_sweep_with_a_bad_value_is_one_line(tmp_path, capsys):
    code = main(["compare", "cartpole", "--methods", "bptt", "--steps", "2", "--set", "clip=value,max",
                 "--out", str(tmp_path / "g")])  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "valid choices: value, norm, none" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "g").exists()


def test_grid_panels_survive_a_partly_finished_grid(tmp_path):
    from physgrad.harness.plots import grid_panels

    rows = [{"method": "bptt", "seed": "0", "epoch": e, "value": str(1.0 / (e + 1))} for e in range(5)]
    path = grid_panels(
        [({"poles": "1"}, []), ({"poles": "2"}, rows)], tmp_path / "g.png", panel="poles", methods=["bptt"]
    )
    assert path.exists()
    assert grid_panels([], tmp_path / "empty.png", panel="poles", methods=["bptt"]).exists()


@pytest.mark.slow  # an end-to-end command-line study
def test_a_reused_study_directory_reports_only_its_planned_runs(tmp_path, capsys):
    out = tmp_path / "s"
    base = [
        "compare",
        "cartpole",
        "--methods",
        "bptt",
        "--set",
        "n_train=16",
        "--set",
        "n_test=8",
        "--out",
        str(out),
        "--quiet",
    ]
    assert main([*base, "--steps", "2"]) == 0
    assert main([*base, "--steps", "3"]) == 0  # same names, another budget: new run dirs beside the old
    assert len(list((out / "runs").iterdir())) == 2
    from physgrad.harness.study import read_csv

    rows = read_csv(out / "summary.csv")
    assert [r["steps"] for r in rows] == ["3"]
