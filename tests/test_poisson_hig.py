"""The HIG Poisson problem: the operator against a dense Laplacian, the noise, sizes."""

import jax
import jax.numpy as jnp
import numpy as np

from physgrad.nets import parameter_count
from physgrad.problems import PoissonHig
from physgrad.problems.poisson_hig import laplace_zero_boundary, phiflow_noise


def dense_laplacian(n):
    """The 5-point Laplacian with zero Dirichlet values outside, as a dense (n², n²) matrix."""
    second = -2 * np.eye(n) + np.eye(n, k=1) + np.eye(n, k=-1)
    return np.kron(second, np.eye(n)) + np.kron(np.eye(n), second)


def test_laplace_equals_a_dense_matrix():
    x = np.random.default_rng(0).normal(size=(8, 8))
    got = np.asarray(laplace_zero_boundary(jnp.asarray(x)))
    np.testing.assert_allclose(got.ravel(), dense_laplacian(8) @ x.ravel(), rtol=1e-12, atol=1e-12)


def test_noise_is_normalised_smooth_and_mean_free():
    field = np.asarray(phiflow_noise(jax.random.key(0), (256, 8, 8), dtype=jnp.float64))
    np.testing.assert_allclose(field.mean(axis=(1, 2)), 0.0, atol=1e-12)
    np.testing.assert_allclose(field.std(axis=(1, 2)), 1.0, rtol=1e-12)
    power = np.mean(np.abs(np.fft.fft2(field)) ** 2, axis=0)
    assert power[1, 0] > 10 * power[4, 4]  # the 1/|k|² weighting: low frequencies dominate


def test_sizes_data_and_metric():
    problem = PoissonHig(n_train=128, n_test=32, dtype="float64")
    data = problem.make_data(jax.random.key(0))
    x_gt, rhs = np.asarray(data["train"]["x_gt"]), np.asarray(data["train"]["rhs"])
    np.testing.assert_allclose(rhs.reshape(128, -1), x_gt.reshape(128, -1) @ dense_laplacian(8).T, atol=1e-12)
    net = problem.make_network(jax.random.key(1))
    assert parameter_count(net) == 24896
    sample = jax.tree.map(lambda a: a[0], data["train"])
    # the exact solution has zero loss and zero ground-truth error
    assert float(problem.loss(problem.simulate(sample["x_gt"], sample), sample)) < 1e-20
    assert float(problem.metrics(sample["x_gt"], None, sample)["x_l1"]) == 0.0
