"""The PBDL book's linear chain: the RK4 solver against the matrix exponential."""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.linalg import expm

from physgrad.nets import parameter_count
from physgrad.problems import LinearOscillators


def system_matrices(n=2, coupling=0.2, gain=1.0):
    """ds/dt = A s + b u for the book's chain, built from its description (free ends)."""
    lap = -2 * np.eye(n) + np.eye(n, k=1) + np.eye(n, k=-1)
    lap[0, 0] = lap[-1, -1] = -1
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-np.eye(n) + coupling * lap, np.zeros((n, n))]])
    b = np.zeros(2 * n)
    b[-1] = gain
    return a, b


def exact(x0, controls, dt):
    """Piecewise-constant control: exp of the augmented matrix [[A, b], [0, 0]] per step."""
    a, b = system_matrices()
    aug = np.zeros((5, 5))
    aug[:4, :4], aug[:4, 4] = a, b
    step = expm(aug * dt)
    z = np.append(x0, 0.0)
    for u in controls:
        z[4] = u
        z = step @ z
    return z[:4]


def test_solver_converges_to_the_matrix_exponential_at_fourth_order():
    rng = np.random.default_rng(0)
    x0, controls = rng.uniform(size=4), rng.normal(size=24)
    errors = []
    for refine in (1, 8):
        problem = LinearOscillators(dtype="float64", n_steps=24 * refine, dt=0.5 / refine)
        fine = np.repeat(controls, refine)
        got = np.asarray(problem.simulate(jnp.asarray(fine), {"x0": jnp.asarray(x0)}))
        errors.append(np.abs(got - exact(x0, fine, problem.dt)).max())
    assert errors[0] < 2e-2 and errors[1] < 1e-5  # the book's dt = 0.5 is within 1.2e-2 of exact
    assert 8**3.5 < errors[0] / errors[1] < 8**4.5, errors


def test_rk4_step_is_the_taylor_polynomial_of_the_exponential():
    a, b = system_matrices()
    aug = np.zeros((5, 5))
    aug[:4, :4], aug[:4, 4] = a, b
    dt = 0.5
    taylor = sum(np.linalg.matrix_power(aug * dt, k) / float(np.prod(np.arange(1, k + 1))) for k in range(5))
    rng = np.random.default_rng(1)
    x0, u = rng.uniform(size=4), 0.7
    problem = LinearOscillators(dtype="float64", n_steps=1)
    got = np.asarray(problem.simulate(jnp.asarray([u]), {"x0": jnp.asarray(x0)}))
    np.testing.assert_allclose(got, (taylor @ np.append(x0, u))[:4], rtol=1e-13, atol=1e-13)


def test_book_sizes():
    problem = LinearOscillators()
    assert parameter_count(problem.make_network(jax.random.key(0))) == 1444
    data = problem.make_data(jax.random.key(0))
    assert data["train"]["x0"].shape == (4096, 4)
