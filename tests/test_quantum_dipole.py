"""The quantum dipole: Crank–Nicolson unitarity, stationary eigenstates, H against NumPy."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.jacobian import stacked_jacobian
from physgrad.nets import parameter_count
from physgrad.problems import QuantumDipole


def dense_hamiltonian(u, n_grid=16, length=2.0):
    """H(u) = −∂xx + u·x on the interior points, written out as a dense NumPy matrix."""
    n, dx = n_grid - 2, length / (n_grid - 1)
    x = dx * np.arange(1, n + 1)
    h = np.zeros((n, n))
    for j in range(n):
        h[j, j] = 2 / dx**2 + u * x[j]
        if j > 0:
            h[j, j - 1] = -1 / dx**2
        if j < n - 1:
            h[j, j + 1] = -1 / dx**2
    return h


def test_cn_step_matches_dense_numpy_solve():
    problem = QuantumDipole(dtype="float64")
    rng = np.random.default_rng(0)
    psi = rng.normal(size=14) + 1j * rng.normal(size=14)
    u, dt = 1.7, problem.dt
    h = dense_hamiltonian(u)
    want = np.linalg.solve(np.eye(14) + 0.5j * dt * h, (np.eye(14) - 0.5j * dt * h) @ psi)
    got = problem.cn_step(jnp.asarray(psi), u)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("scale", [0.0, 5.0])
def test_norm_is_kept_over_the_full_horizon(scale):
    problem = QuantumDipole()  # float32 / complex64, as trained
    controls = scale * jax.random.normal(jax.random.key(1), (problem.n_steps,), jnp.float32)
    sample = jax.tree.map(lambda a: a[0], problem.make_data(jax.random.key(0))["train"])
    psi = problem.simulate(controls, sample)
    assert psi.dtype == jnp.complex64 and psi.shape == (14,)
    assert abs(float(jnp.linalg.norm(psi)) - 1.0) < 1e-5


@pytest.mark.parametrize("n", [1, 2, 3])
def test_eigenstates_are_stationary_up_to_the_cn_phase(n):
    problem = QuantumDipole(dtype="float64")
    psi_n = np.asarray(problem.eigenstate(n))
    h = dense_hamiltonian(0.0)
    np.testing.assert_allclose(h @ psi_n, (psi_n @ h @ psi_n) * psi_n, atol=1e-9)  # an eigenvector of H(0)
    energy = 4 / problem.dx**2 * np.sin(np.pi * n / (2 * 15)) ** 2
    phase = ((1 - 0.5j * problem.dt * energy) / (1 + 0.5j * problem.dt * energy)) ** problem.n_steps

    def evolve(psi, _):
        return problem.cn_step(psi, 0.0), None

    psi_t, _ = jax.lax.scan(evolve, jnp.asarray(psi_n, jnp.complex128), None, length=problem.n_steps)
    np.testing.assert_allclose(np.asarray(psi_t), phase * psi_n, atol=1e-10)


def test_loss_is_the_infidelity():
    problem = QuantumDipole(dtype="float64")
    psi2, psi3 = np.asarray(problem.eigenstate(2)), np.asarray(problem.eigenstate(3))
    target = 0.6 * psi2 + 0.8 * psi3
    sample = {"target": jnp.asarray(np.stack([target, np.zeros(14)], -1))}
    psi = (np.exp(0.3j) * psi2 + 1j * psi3) / np.sqrt(2)
    want = 1 - abs(np.vdot(target, psi)) ** 2
    assert float(problem.loss(jnp.asarray(psi), sample)) == pytest.approx(want, rel=1e-12)


def test_sizes_and_data():
    problem = QuantumDipole()
    data = problem.make_data(jax.random.key(0))
    target = data["train"]["target"]
    assert target.shape == (1024, 14, 2) and data["test"]["target"].shape == (1024, 14, 2)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(target), axis=(1, 2)), 1.0, rtol=1e-5)
    # a real mix of the 2nd and 3rd eigenstates: orthogonal to the ground state
    assert float(jnp.max(jnp.abs(target[..., 0] @ problem.eigenstate(1)))) < 1e-5
    net = problem.make_network(jax.random.key(1))
    assert parameter_count(net) == 9484
    batch = jax.tree.map(lambda a: a[:2], data["train"])
    # one compiled program (eagerly, the vmapped jacrev of the 384-step rollout costs ~2 s more of CPU)
    jac, y = eqx.filter_jit(lambda n, b: stacked_jacobian(problem.predict, n, b))(net, batch)
    assert jac.shape == (2 * 28, 9484) and y.shape == (2, 28)  # (Re, Im) pairs per grid point
