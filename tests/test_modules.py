"""Whole Equinox modules as parameters (issue 33): every estimator and method takes an
``eqx.nn.MLP`` or a convolutional module as it is, differentiates its inexact-array leaves
only (as ``eqx.filter_grad``) and gives what the user's own partition gives.

The reference is the partitioned path the user had to write before: ``arrays, static =
eqx.partition(model, eqx.is_inexact_array)`` and the user's functions closing over
``static``, so the rule sees a tree of arrays.
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
import physgrad.methods.kfac  # a module of its own (kfac-jax), not imported by physgrad.methods
from physgrad import Method, Objective
from physgrad.methods import JacobianPower
from physgrad.methods.lm import LevenbergMarquardt


class ConvNet(eqx.Module):
    """Two 1-D convolutions (1 → 4 → 1 channels) with an activation function as a field:
    a leaf that is not an array, as in ``eqx.nn.MLP``."""

    convs: tuple[eqx.nn.Conv1d, eqx.nn.Conv1d]
    activation: Callable

    def __init__(self, key):
        k1, k2 = jax.random.split(key)
        self.convs = (eqx.nn.Conv1d(1, 4, 3, padding=1, key=k1), eqx.nn.Conv1d(4, 1, 3, padding=1, key=k2))
        self.activation = jax.nn.tanh

    def __call__(self, u):  # u: (8,)
        return self.convs[1](self.activation(self.convs[0](u[None])))[0]


def simulate(u):
    """A small nonlinear 'physics' on the network output."""
    return jnp.concatenate([u + 0.1 * u**2, jnp.sin(u[:2])])


def loss(y, sample):
    return 0.5 * jnp.sum((y - sample["target"]) ** 2)


def mlp_case():
    model = eqx.nn.MLP(3, 2, 8, 2, activation=jax.nn.tanh, key=jax.random.key(0))
    keys = jax.random.split(jax.random.key(1))
    batch = {"x": jax.random.normal(keys[0], (4, 3)), "target": jax.random.normal(keys[1], (4, 4))}
    return model, batch


def conv_case():
    model = ConvNet(jax.random.key(2))
    keys = jax.random.split(jax.random.key(3))
    batch = {"x": jax.random.normal(keys[0], (4, 8)), "target": jax.random.normal(keys[1], (4, 10))}
    return model, batch


CASES = {"mlp": mlp_case, "conv": conv_case}


def predict(model, sample):
    return simulate(model(sample["x"]))


def partitioned(model):
    """The user's partition: (arrays, the functions closing over the rest)."""
    arrays, static = eqx.partition(model, eqx.is_inexact_array)

    def predict_arrays(p, sample):
        return predict(eqx.combine(p, static), sample)

    def network_arrays(p, sample):
        return eqx.combine(p, static)(sample["x"])

    return arrays, static, predict_arrays, network_arrays


def assert_same_tree(got, want, rtol=1e-6):
    """Same structure (None where the model has no array) and values to rtol."""
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=rtol, atol=1e-12)


def estimators(predict_fn, network_fn):
    """Every top-level estimator on the case's functions."""
    return {
        "dp": physgrad.dp(predict_fn, loss),
        "hig": physgrad.hig(predict_fn, loss),
        "gauss_newton": physgrad.gauss_newton(predict_fn, loss),
        "hig_svd": physgrad.hig(predict_fn, loss, route=physgrad.routes.SVD()),
        "newton": physgrad.newton(predict_fn, loss, damping=1e-3),
        "sip": physgrad.sip(network_fn, lambda u, s: simulate(u), lambda s: s["target"], loss=loss),
    }


@pytest.mark.parametrize("case", ["mlp", pytest.param("conv", marks=pytest.mark.slow)])
def test_estimators_take_a_whole_module(case):
    model, batch = CASES[case]()
    arrays, _, predict_arrays, network_arrays = partitioned(model)
    whole = estimators(predict, lambda m, s: m(s["x"]))
    reference = estimators(predict_arrays, network_arrays)
    for name, estimate in whole.items():
        direction, stats = eqx.filter_jit(estimate)(model, batch)  # a module: filter_jit, as Equinox users do
        want, want_stats = jax.jit(reference[name])(arrays, batch)
        assert_same_tree(direction, want)
        assert_same_tree(stats, want_stats)
        # the structure of eqx.filter_grad: None where the model holds no array
        assert jax.tree.structure(direction) == jax.tree.structure(arrays), name


@pytest.mark.parametrize("case", CASES)
def test_a_users_optax_loop_on_a_whole_module(case):
    """The Equinox + optax idiom: ``opt.init(eqx.filter(model, eqx.is_inexact_array))``,
    ``opt.update(d, state, eqx.filter(...))``, ``eqx.apply_updates(model, updates)``."""
    model, batch = CASES[case]()
    estimate, optimizer = physgrad.hig(predict, loss), optax.adam(1e-2)

    @eqx.filter_jit
    def step(model, state, batch):
        d, stats = estimate(model, batch)
        params = eqx.filter(model, eqx.is_inexact_array)
        updates, state = optimizer.update(d, state, params)
        return eqx.apply_updates(model, updates), state, stats

    state = optimizer.init(eqx.filter(model, eqx.is_inexact_array))
    new, state, stats = step(model, state, batch)
    arrays, static, predict_arrays, _ = partitioned(model)

    @jax.jit
    def reference(arrays, batch):
        d, _ = physgrad.hig(predict_arrays, loss)(arrays, batch)
        updates, _ = optimizer.update(d, optimizer.init(arrays), arrays)
        return optax.apply_updates(arrays, updates)

    assert_same_tree(eqx.filter(new, eqx.is_inexact_array), reference(arrays, batch))
    assert new.activation is model.activation  # the non-array leaves are the model's own
    assert float(eqx.filter_jit(physgrad.dp(predict, loss))(new, batch)[1]["loss"]) < float(stats["loss"])


def methods():
    return {
        "method_hig": Method(JacobianPower(-0.5), optax.sgd(0.5)),
        "method_gn_adam": Method(JacobianPower(-1.0), optax.adam(1e-2)),
        "lm": LevenbergMarquardt(),
        "kfac": physgrad.methods.kfac.kfac(inverse_every=1),
    }


# K-FAC (the costliest to compile, through kfac-jax) in the slow tier
@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "kfac" else n for n in methods()])
def test_methods_step_a_whole_module(case, name):
    """``method.init(model)`` and ``method.step(objective, model, …)`` return the model with
    its non-array leaves untouched and the arrays of the partitioned path's step."""
    model, batch = CASES[case]()
    method = methods()[name]
    arrays, static, predict_arrays, _ = partitioned(model)

    def run(params, objective):
        return eqx.filter_jit(lambda p, b: method.step(objective, p, method.init(p), b))(params, batch)

    new, state, stats = run(model, Objective(predict, loss))
    want, want_state, want_stats = run(arrays, Objective(predict_arrays, loss))
    assert_same_tree(eqx.filter(new, eqx.is_inexact_array), want)
    assert_same_tree(state, want_state)
    assert_same_tree(stats, want_stats)
    assert jax.tree.structure(eqx.combine(want, static)) == jax.tree.structure(new)
    assert new.activation is model.activation


def test_a_rollout_estimator_takes_a_whole_module():
    """bptt on a closed loop whose controller is an eqx.nn.MLP."""
    model = eqx.nn.MLP(2, 1, 8, 1, activation=jax.nn.tanh, key=jax.random.key(4))
    s0 = jax.random.normal(jax.random.key(5), (4, 2))

    def system(control):
        return physgrad.closed_loop(
            control,
            lambda s, c: jnp.stack([s[0] + 0.1 * s[1], s[1] + 0.1 * c[0]]),
            lambda s, c, k: jnp.sum(s**2),
            num_steps=5,
            weights=jnp.ones(5),
        )

    arrays, static = eqx.partition(model, eqx.is_inexact_array)
    got, _ = eqx.filter_jit(physgrad.bptt(system(lambda m, s: m(s))))(model, s0)
    want, _ = eqx.filter_jit(physgrad.bptt(system(lambda p, s: eqx.combine(p, static)(s))))(arrays, s0)
    assert_same_tree(got, want)
