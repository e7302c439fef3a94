"""Compile time a user pays on every new shape: how often tracing one jitted HIG step calls
the user's ``predict`` (issue 30). The step's joint-Jacobian value traces it once and the
routes replay that program; 7 calls with ``Auto()`` and 1 with ``Gram()`` before."""

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
import pytest

import physgrad
from physgrad import routes


def _case(sizes, batch_size):
    """A float32 MLP (``sizes``: in, hidden..., out) through a nonlinear map; a counter of
    ``predict``'s calls; a jittable step of HIG with plain SGD."""
    net = physgrad.MLP(sizes, jax.nn.tanh, key=jax.random.key(0))
    params, static = eqx.partition(net, eqx.is_inexact_array)
    calls = []

    def predict(p, s):
        calls.append(1)  # a Python side effect: runs once per trace, never in the compiled step
        u = eqx.combine(p, static)(s["x"])
        return u + 0.1 * u**2

    def loss(y, s):
        return 0.5 * jnp.sum((y - s["t"]) ** 2)

    keys = jax.random.split(jax.random.key(1))
    batch = {"x": jax.random.normal(keys[0], (batch_size, sizes[0])),
             "t": jax.random.normal(keys[1], (batch_size, sizes[-1]))}  # fmt: skip
    return params, batch, predict, loss, calls


def _traces(route, sizes, batch_size):
    """(predict calls while lowering one jitted step, the route that ran)."""
    params, batch, predict, loss, calls = _case(sizes, batch_size)
    estimate = physgrad.hig(predict, loss, route=route)
    optimizer = optax.sgd(0.1)

    def step(p, state, b):
        direction, stats = estimate(p, b)
        updates, state = optimizer.update(direction, state, p)
        return optax.apply_updates(p, updates), state, stats

    ran = estimate.describe(params, batch)["route"]
    calls.clear()
    jax.jit(step).lower(params, optimizer.init(params), batch)
    return len(calls), ran


# (in, hidden..., out), batch: J wide with dense layers (Auto: structured), tall (gram),
# nearly square (svd)
CASES = {"structured": ((3, 16, 16, 2), 4), "gram": ((3, 2, 10), 8), "svd": ((3, 4, 5), 8)}


@pytest.mark.parametrize("expected", sorted(CASES))
def test_auto_traces_predict_once_per_step(expected):
    sizes, b = CASES[expected]
    count, ran = _traces(routes.Auto(), sizes, b)
    assert ran == expected
    assert count == 1  # issue 30 asks for at most 2; the value's one trace is replayed


@pytest.mark.parametrize("case", sorted(CASES))
def test_gram_traces_predict_once_per_step(case):
    sizes, b = CASES[case]
    count, ran = _traces(routes.Gram(), sizes, b)
    assert ran == "gram" and count == 1
