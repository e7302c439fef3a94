"""The oscillator problem: equations, RK4 order, sizes and data."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.nets import parameter_count
from physgrad.problems import Oscillators
from physgrad.problems.sim.integrators import integrate, rk4_step


def rhs_loop(state, u, n, cubic=1.0, linear=0.0, gain=3.0):
    """The paper's equations of motion written as a plain loop over oscillators."""
    q, p = state[:n], state[n:]
    dp = np.zeros(n)
    for i in range(n):
        dp[i] = -q[i]
        for j in (i - 1, i + 1):
            if 0 <= j < n:
                dp[i] += cubic * (q[j] - q[i]) ** 3 + linear * (q[j] - q[i])
        if i == n - 1:
            dp[i] += gain * u
    return np.concatenate([p, dp])


@pytest.mark.parametrize("n", [1, 2, 5])
def test_rhs_matches_equations(n):
    rng = np.random.default_rng(n)
    problem = Oscillators(n_oscillators=n, linear_coupling=0.3, dtype="float64")
    s, u = rng.standard_normal(2 * n), 0.7
    got = problem.rhs(jnp.asarray(s), u)
    np.testing.assert_allclose(np.asarray(got), rhs_loop(s, u, n, linear=0.3), rtol=1e-12)


def test_rk4_is_fourth_order_on_uncoupled_chain():
    """Uncoupled, uncontrolled: q(t) = q0 cos t + p0 sin t; halving dt cuts the error 16×."""
    problem = Oscillators(cubic_coupling=0.0, dtype="float64")
    s0 = jnp.asarray([0.3, -0.8, 0.5, 0.2])
    t_end = 12.0
    q0, p0 = np.asarray(s0[:2]), np.asarray(s0[2:])
    exact = np.concatenate([q0 * np.cos(t_end) + p0 * np.sin(t_end), -q0 * np.sin(t_end) + p0 * np.cos(t_end)])
    errors = []
    for n_steps in (48, 96, 192, 384):
        final = integrate(rk4_step, problem.rhs, s0, jnp.zeros(n_steps), t_end / n_steps)
        errors.append(np.abs(np.asarray(final) - exact).max())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    np.testing.assert_allclose(orders, 4.0, atol=0.1)


def test_paper_sizes_and_data():
    problem = Oscillators()
    net = problem.make_network(jax.random.key(0))
    assert parameter_count(net) == 2956
    data = problem.make_data(jax.random.key(1))
    x = np.asarray(data["train"]["x0"])
    assert x.shape == (4096, 4) and data["test"]["x0"].shape == (4096, 4)
    assert x.dtype == np.float32 and x.min() >= 0 and x.max() < 1
    again = problem.make_data(jax.random.key(1))
    np.testing.assert_array_equal(np.asarray(again["test"]["x0"]), np.asarray(data["test"]["x0"]))
    controls = problem.network_output(net, jax.tree.map(lambda a: a[0], data["train"]))
    assert controls.shape == (96,)
    # Glorot-uniform kernels within their limit, zero biases.
    first = net.layers[0]
    assert np.abs(np.asarray(first.weight)).max() <= np.sqrt(6 / (4 + 20))
    assert not np.any(np.asarray(first.bias))


def test_loss_is_squared_distance_to_start():
    problem = Oscillators(dtype="float64")
    sample = {"x0": jnp.asarray([0.1, 0.2, 0.3, 0.4])}
    y = jnp.asarray([0.0, 0.0, 0.0, 1.0])
    assert float(problem.loss(y, sample)) == pytest.approx(0.01 + 0.04 + 0.09 + 0.36)
