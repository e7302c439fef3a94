"""The stacked Jacobian's row order against central finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from physgrad import Budget
from physgrad.harness.config import make_config
from physgrad.harness.train import build
from physgrad.jacobian import stacked_jacobian


def test_rows_are_sample_major_against_finite_differences():
    config = make_config(
        "oscillators", "hig", budget=Budget(steps=1),
        settings={"n_steps": "6", "hidden": "3", "dtype": "float64", "n_train": "4", "n_test": "4", "batch_size": "4"},
    )  # fmt: skip
    setup = build(config)
    batch = jax.tree.map(lambda a: a[:3], setup.data["train"])
    # compiled as one program, as the methods run it (eagerly, each operation of the rollout's
    # reverse pass compiles on its own: 2.2 instead of 0.9 CPU-s)
    jac, y = jax.jit(lambda p, b: stacked_jacobian(setup.objective.predict, p, b))(setup.params, batch)
    flat, unravel = ravel_pytree(setup.params)
    assert jac.shape == (3 * 4, flat.size) and y.shape == (3, 4)

    @jax.jit
    def outputs(theta):  # sample i's output k at row i*4 + k, one sample at a time
        return jnp.concatenate([setup.objective.predict(unravel(theta), {"x0": x}) for x in batch["x0"]])

    eps = 1e-6
    fd = np.stack(
        [(outputs(flat.at[j].add(eps)) - outputs(flat.at[j].add(-eps))) / (2 * eps) for j in range(flat.size)],
        axis=1,
    )
    np.testing.assert_allclose(np.asarray(jac), fd, rtol=1e-5, atol=1e-7)


def test_complex_outputs_become_real_pairs():
    def predict(params, sample):
        return params["w"] * sample * jnp.asarray([1.0, 1j])

    jac, y = stacked_jacobian(predict, {"w": jnp.asarray(2.0)}, jnp.asarray([1.0, 3.0]))
    # per sample: (Re, Im) of w·x and of i·w·x
    np.testing.assert_allclose(np.asarray(y), [[2, 0, 0, 2], [6, 0, 0, 6]])
    np.testing.assert_allclose(np.asarray(jac[:, 0]), [1, 0, 0, 1, 3, 0, 0, 3])
