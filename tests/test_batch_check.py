"""A batch given as a Python list of samples (issue 53, item 5): one line saying how to
stack it, raised before the user's simulator sees a list of slices; the stacked batch and a
list of batched arrays (a valid pytree batch) go through."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad
from physgrad.engine.types import Steps
from physgrad.errors import ConfigError
from physgrad.methods import Gradient, Method
from physgrad.methods.base import STACK_SAMPLES, check_batch

W = jnp.array([[0.5, -1.0], [2.0, 0.25]])


def simulate(x):
    if not isinstance(x, jax.Array):  # what a list of samples would hand the simulator
        raise AssertionError(f"the simulator was entered with {type(x).__name__}")
    return jnp.tanh(x)


def predict(params, sample):
    return simulate(params @ sample["x"])


def loss(y, sample):
    return 0.5 * jnp.sum((y - sample["y"]) ** 2)


SAMPLES = [{"x": jnp.array([1.0, float(i)]), "y": jnp.array([0.1 * i, -0.2])} for i in range(4)]


@pytest.mark.parametrize("make", [physgrad.dp, physgrad.hig, physgrad.gauss_newton])
def test_a_list_of_samples_is_one_line_before_the_simulator(make):
    estimate = make(predict, loss)
    with pytest.raises(ConfigError) as info:
        estimate(W, SAMPLES)
    line = str(info.value)
    assert "\n" not in line and line.startswith("the batch is a list of 4 samples") and STACK_SAMPLES in line
    with pytest.raises(ConfigError, match="list of 4 samples"):
        jax.jit(estimate)(W, SAMPLES)  # under a trace too
    # the line's own fix works: the direction of the stacked batch, against the DP gradient
    # of the batch-mean loss by an explicit loop over the samples (dp only: the others differ)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *SAMPLES)
    direction, stats = estimate(W, stacked)
    if make is physgrad.dp:
        per_sample = [jax.grad(lambda w, s=s: loss(predict(w, s), s))(W) for s in SAMPLES]
        np.testing.assert_allclose(direction, np.mean(per_sample, axis=0), rtol=1e-5)
    assert np.isfinite(stats["loss"])


def test_a_stepper_refuses_it_too():
    stepper = physgrad.levenberg_marquardt(predict, loss, optimizer=optax.sgd(1.0))
    with pytest.raises(ConfigError, match="list of 4 samples"):
        stepper.step(W, stepper.init(W), SAMPLES)


def test_what_passes_and_what_does_not():
    x, y = jnp.ones((4, 2)), jnp.zeros((4, 3))
    check_batch([x, y])  # a batch whose pytree is a list of batched arrays
    check_batch([x])
    check_batch({"x": x})
    check_batch([])
    with pytest.raises(ConfigError, match="list of 3 samples"):
        check_batch([0.1, 0.2, 0.3])  # numbers have no sample axis
    with pytest.raises(ConfigError, match="list of 2 samples"):
        check_batch([(jnp.ones(2), 1.0), (jnp.ones(2), 2.0)])


def test_fit_refuses_make_data_returning_lists():
    class Listed(physgrad.AbstractProblem):
        name = "listed"
        source = "a test"

        def make_data(self, key):
            return {"train": SAMPLES, "test": SAMPLES}

        def make_network(self, key):
            return W

        def network_output(self, network, sample):
            return network @ sample["x"]

        def simulate(self, x, sample):
            return simulate(x)

        def loss(self, y, sample):
            return loss(y, sample)

    method = Method(Gradient(), optax.sgd(0.1))
    with pytest.raises(ConfigError, match=r"listed: make_data's 'train' split is a list of 4 samples; stack"):
        physgrad.fit(Listed(), method, budget=Steps(1), batch_size=2)
