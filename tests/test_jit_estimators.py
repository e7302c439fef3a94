"""Every public estimator goes inside a plain ``jax.jit`` and gives what it gives eagerly.

The README promises that an estimator ``(params, batch) -> (direction, stats)`` is pure and
traceable; ``jax.jit(physgrad.bptt(...))`` once raised "unhashable type" because the
estimator was hashed field by field and a rollout system holds its weights as an array.
The reference is the same estimator called op by op (no jit).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad
from physgrad import inverse, rollout


def _mlp(key, sizes):
    keys = jax.random.split(key, len(sizes) - 1)
    return [
        {"w": 0.5 * jax.random.normal(k, (m, n)), "b": jnp.zeros(n)} for k, m, n in zip(keys, sizes[:-1], sizes[1:])
    ]


def _forward(params, x):
    for layer in params[:-1]:
        x = jnp.tanh(x @ layer["w"] + layer["b"])
    return x @ params[-1]["w"] + params[-1]["b"]


def _open_loop():
    """A 3 → 8 → 2 network through a fixed linear 'simulator' to a squared-error target."""
    params = _mlp(jax.random.key(0), (3, 8, 2))
    physics = jnp.array([[2.0, 0.3], [0.0, 0.05]])

    def predict(p, sample):
        return _forward(p, sample["x"]) @ physics

    def loss(y, sample):
        return jnp.sum((y - sample["y"]) ** 2)

    key_x, key_y = jax.random.split(jax.random.key(1))
    batch = {"x": jax.random.normal(key_x, (6, 3)), "y": jax.random.normal(key_y, (6, 2))}
    return params, predict, loss, batch


def _sip():
    """SIP on an invertible per-sample linear map, with a closed-form and a Krylov inverse."""
    params = _mlp(jax.random.key(2), (2, 8, 2))

    def simulate(x, sample):
        return a_matrix() @ x

    batch = {"x": jax.random.normal(jax.random.key(3), (5, 2)), "y": jax.random.normal(jax.random.key(4), (5, 2))}
    return params, (lambda p, s: _forward(p, s["x"])), simulate, (lambda s: s["y"]), batch


def _closed_loop():
    """A point mass pushed by a network to x = 1 and rest over 6 steps (the README's example, smaller).

    6 steps: the eager reference runs the rollout and its reverse pass op by op (~50 ms of
    CPU a step); 6 > 4 still cuts the truncated policy's gradient."""
    params = _mlp(jax.random.key(5), (2, 8, 1))

    def control(p, s):
        return _forward(p, s)[0]

    def physics(s, c):
        return jnp.array([s[0] + 0.1 * s[1], s[1] + 0.1 * c])

    def step_loss(s, c, k):  # the velocity term gives the one-step (S, NOG) gradient something to see
        return (s[0] - 1.0) ** 2 + 0.1 * s[1] ** 2

    system = rollout.closed_loop(control, physics, step_loss, 6, jnp.full(6, 1 / 6))
    batch = jax.random.normal(jax.random.key(6), (4, 2))
    return params, system, batch


def _estimators():
    params, predict, loss, batch = _open_loop()
    open_loop = {
        "dp": physgrad.dp(predict, loss),
        "hig": physgrad.hig(predict, loss),
        "gauss_newton": physgrad.gauss_newton(predict, loss),
        "newton": physgrad.newton(predict, loss),
        "kronecker_hig": physgrad.kronecker_hig(predict, loss),
    }
    cases = {name: (estimate, params, batch) for name, estimate in open_loop.items()}
    params, network_output, simulate, target, batch = _sip()
    cases["sip_linear_solve"] = (
        physgrad.sip(network_output, simulate, target, solver=inverse.LinearSolve()),
        params,
        batch,
    )
    cases["sip_analytic"] = (
        physgrad.sip(
            network_output,
            simulate,
            target,
            solver=inverse.Analytic(lambda x, y, y_target, sample: x + jnp.linalg.solve(a_matrix(), y_target - y)),
        ),
        params,
        batch,
    )
    params, system, batch = _closed_loop()
    cases["bptt"] = (physgrad.bptt(system), params, batch)
    cases["bptt_truncated"] = (physgrad.bptt(system, policy=rollout.R(truncate=4)), params, batch)
    cases["stabilised_bptt"] = (physgrad.stabilised_bptt(system), params, batch)
    cases["unrolled"] = (physgrad.unrolled(system), params, batch)
    return cases


def a_matrix():
    return jnp.array([[3.0, 1.0], [0.5, 0.2]])


CASES = _estimators()
# The same jit-versus-eager contract for each: the fast tier keeps one estimator of each family
# (dp and hig: open loop; sip_analytic: SIP; bptt, bptt_truncated and unrolled: closed loop).
# These take 4-8 s of CPU each, most of it op by op (Newton's Hessian, the Gauss-Newton and
# K-FAC factors, GMRES, the stabilised rollout's two passes): the slow tier.
SLOW_CASES = {"gauss_newton", "kronecker_hig", "newton", "sip_linear_solve", "stabilised_bptt"}


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_CASES else n for n in sorted(CASES)]
)
def test_estimator_under_plain_jit_matches_eager(name):
    estimate, params, batch = CASES[name]
    hash(estimate)  # jax.jit hashes the function it wraps
    jitted_direction, jitted_stats = jax.jit(estimate)(params, batch)
    with jax.disable_jit():
        direction, stats = estimate(params, batch)
    for got, want in zip(jax.tree.leaves(jitted_direction), jax.tree.leaves(direction)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=2e-4, atol=1e-6)
    np.testing.assert_allclose(float(jitted_stats["loss"]), float(stats["loss"]), rtol=1e-5)
    assert any(np.abs(np.asarray(leaf)).max() > 0 for leaf in jax.tree.leaves(jitted_direction))
