"""Each local inverse solver against an independent reference (NumPy, SciPy, closed forms)."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
import scipy.optimize

from physgrad.harness import objects
from physgrad.harness.registry import make_solver
from physgrad.inverse import LBFGS, Analytic, GaussNewton, LinearSolve, SaddleFreeNewton

RNG = np.random.default_rng(0)
A = RNG.normal(size=(3, 3))


def simulate(x, sample):
    """A smooth nonlinear map R³ → R³ with an invertible Jacobian near the test points."""
    return jnp.asarray(A) @ x + 0.1 * jnp.sin(x) + sample["shift"]


def fd_jacobian(f, x, h=1e-6):
    """Central finite differences, float64 NumPy."""
    cols = [(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(x.size)]
    return np.stack(cols, axis=1)


def np_simulate(x):
    return A @ x + 0.1 * np.sin(x) + 0.5


SAMPLE = {"shift": jnp.float64(0.5)}
X = RNG.normal(size=3)
Y = np_simulate(X)
Y_TARGET = Y + RNG.normal(size=3) * 0.1


def test_analytic_applies_the_problem_inverse_and_flags_non_finite():
    solver = Analytic(lambda x, y, yt, s: jnp.log(yt))
    result = solver(None, jnp.zeros(2), jnp.ones(2), jnp.array([2.0, 3.0]), {})
    np.testing.assert_allclose(result.x, np.log([2.0, 3.0]), rtol=1e-15)
    assert bool(result.converged)
    assert not bool(solver(None, jnp.zeros(2), jnp.ones(2), jnp.array([-1.0, 3.0]), {}).converged)


@pytest.mark.parametrize("rcond", [1e-5, 0.5])
def test_gauss_newton_equals_numpy_pinv_of_a_finite_difference_jacobian(rcond):
    result = GaussNewton(rcond)(simulate, jnp.asarray(X), jnp.asarray(Y), jnp.asarray(Y_TARGET), SAMPLE)
    jac = fd_jacobian(np_simulate, X)
    expected = X + np.linalg.pinv(jac, rcond=rcond) @ (Y_TARGET - Y)
    np.testing.assert_allclose(result.x, expected, rtol=1e-7, atol=1e-8)
    assert bool(result.converged)


def test_gauss_newton_is_the_minimum_norm_step_for_an_underdetermined_map():
    B = RNG.normal(size=(2, 5))
    sim = lambda x, s: jnp.asarray(B) @ x  # noqa: E731
    x = RNG.normal(size=5)
    yt = RNG.normal(size=2)
    result = GaussNewton(1e-10)(sim, jnp.asarray(x), jnp.asarray(B @ x), jnp.asarray(yt), {})
    step = np.asarray(result.x) - x
    np.testing.assert_allclose(B @ np.asarray(result.x), yt, atol=1e-12)  # exact for linear P
    np.testing.assert_allclose(step, np.linalg.lstsq(B, yt - B @ x, rcond=None)[0], atol=1e-12)


def sfn_reference(grad, hess, max_loss_change):
    """The SIP authors' limited saddle-free Newton step, written out in NumPy."""
    s, v = np.linalg.eigh(hess)
    g = v.T @ grad
    newton = np.abs(g / s)
    if max_loss_change is not None:
        s_mean = np.abs(np.prod(s)) ** (1 / len(s))
        newton = np.where(s > s_mean, newton, np.minimum(newton, np.abs(max_loss_change / g)))
    return v @ (-np.sign(g) * newton)


@pytest.mark.parametrize("max_loss_change", [None, 0.2, 1e-3])
def test_saddle_free_newton_equals_the_numpy_formula_with_finite_difference_derivatives(max_loss_change):
    def loss(x):
        return 0.5 * np.sum((np_simulate(x) - Y_TARGET) ** 2)

    grad = fd_jacobian(lambda x: np.array([loss(x)]), X)[0]
    hess = fd_jacobian(lambda x: fd_jacobian(lambda z: np.array([loss(z)]), x, 1e-5)[0], X, 1e-4)
    hess = 0.5 * (hess + hess.T)
    result = SaddleFreeNewton(max_loss_change)(simulate, jnp.asarray(X), jnp.asarray(Y), jnp.asarray(Y_TARGET), SAMPLE)
    np.testing.assert_allclose(
        np.asarray(result.x) - X, sfn_reference(grad, hess, max_loss_change), rtol=1e-4, atol=1e-7
    )


def test_saddle_free_newton_is_newton_on_a_convex_quadratic():
    from physgrad.inverse.saddle_free_newton import saddle_free_newton_step

    G = RNG.normal(size=(4, 4))
    H, g = G @ G.T + np.eye(4), RNG.normal(size=4)
    np.testing.assert_allclose(
        saddle_free_newton_step(jnp.asarray(g), jnp.asarray(H)), -np.linalg.solve(H, g), rtol=1e-10
    )


def test_saddle_free_newton_caps_zero_curvature_steps():
    from physgrad.inverse.saddle_free_newton import saddle_free_newton_step

    step = saddle_free_newton_step(jnp.array([1.0, 1.0]), jnp.diag(jnp.array([4.0, 0.0])), 0.2)
    np.testing.assert_allclose(step, [-0.25, -0.2])  # s = 0: the cap 0.2/|g| sets the step


def test_saddle_free_newton_descends_at_a_saddle():
    # ℓ = ½ (x₀² − x₁²): Newton would step *to* the saddle along x₁; |H| steps away from it.
    from physgrad.inverse.saddle_free_newton import saddle_free_newton_step

    x = np.array([1.0, 0.5])
    grad, hess = np.array([x[0], -x[1]]), np.diag([1.0, -1.0])
    step = np.asarray(saddle_free_newton_step(jnp.asarray(grad), jnp.asarray(hess)))
    np.testing.assert_allclose(step, [-1.0, 0.5], atol=1e-12)  # x₁ moves away from 0: ℓ decreases


def test_lbfgs_finds_the_scipy_minimiser_from_the_prediction():
    result = LBFGS(max_steps=500, tol=1e-12)(simulate, jnp.asarray(X), jnp.asarray(Y), jnp.asarray(Y_TARGET), SAMPLE)
    reference = scipy.optimize.minimize(
        lambda x: 0.5 * np.sum((np_simulate(x) - Y_TARGET) ** 2), X, method="L-BFGS-B",
        options={"ftol": 1e-20, "gtol": 1e-12, "maxiter": 1000},
    )  # fmt: skip
    assert bool(result.converged)
    np.testing.assert_allclose(result.x, reference.x, atol=1e-6)
    np.testing.assert_allclose(np_simulate(np.asarray(result.x)), Y_TARGET, atol=1e-8)


def test_lbfgs_reports_running_out_of_steps():
    result = LBFGS(max_steps=1, tol=1e-12)(simulate, jnp.asarray(X), jnp.asarray(Y), jnp.asarray(Y_TARGET), SAMPLE)
    assert not bool(result.converged)


def test_lbfgs_accept_last_keeps_an_unconverged_iterate_that_helped():
    """The SIP authors' 16-iteration L-BFGS inverse: the budget's last iterate is used."""
    args = (simulate, jnp.asarray(X), jnp.asarray(Y), jnp.asarray(Y_TARGET), SAMPLE)
    plain = LBFGS(max_steps=3, tol=1e-12)(*args)
    last = LBFGS(max_steps=3, tol=1e-12, accept_last=True)(*args)
    assert not bool(plain.converged) and bool(last.converged)
    np.testing.assert_array_equal(np.asarray(last.x), np.asarray(plain.x))
    misfit = lambda x: 0.5 * np.sum((np_simulate(np.asarray(x)) - Y_TARGET) ** 2)  # noqa: E731
    assert misfit(last.x) < misfit(X)


# CG on a symmetric positive (semi)definite operator
SPD_CG = {"solver": lx.CG(rtol=0.0, atol=0.0, max_steps=1000), "tags": (lx.symmetric_tag, lx.positive_semidefinite_tag)}


@pytest.mark.parametrize("krylov", ["gmres", "bicgstab", "normal_cg"])
def test_linear_solve_equals_numpy_solve_for_a_general_matrix(krylov):
    M = RNG.normal(size=(6, 6)) + 6 * np.eye(6)
    sim = lambda x, s: jnp.asarray(M) @ x + 1.0  # noqa: E731  affine
    x, yt = RNG.normal(size=6), RNG.normal(size=6)
    result = LinearSolve(**objects.krylov(krylov), rtol=1e-12, atol=1e-14)(
        sim, jnp.asarray(x), jnp.asarray(M @ x + 1.0), jnp.asarray(yt), {}
    )
    assert bool(result.converged)
    np.testing.assert_allclose(result.x, np.linalg.solve(M, yt - 1.0), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("krylov,sign", [("cg", 1.0), ("cg_negative", -1.0)])
def test_linear_solve_cg_on_definite_operators(krylov, sign):
    G = RNG.normal(size=(6, 6))
    M = sign * (G @ G.T + np.eye(6))
    sim = lambda x, s: jnp.asarray(M) @ x  # noqa: E731
    x, yt = RNG.normal(size=6), RNG.normal(size=6)
    result = LinearSolve(**objects.krylov(krylov), rtol=1e-12, atol=1e-14)(
        sim, jnp.asarray(x), jnp.asarray(M @ x), jnp.asarray(yt), {}
    )
    assert bool(result.converged)
    np.testing.assert_allclose(result.x, np.linalg.solve(M, yt), rtol=1e-8, atol=1e-10)


def test_linear_solve_reports_non_convergence():
    M = np.diag(np.logspace(0, 6, 20))
    sim = lambda x, s: jnp.asarray(M) @ x  # noqa: E731
    result = LinearSolve(**SPD_CG, rtol=1e-12, atol=0.0, max_steps=2)(
        sim, jnp.zeros(20), jnp.zeros(20), jnp.ones(20), {}
    )
    assert not bool(result.converged)


def test_linear_solve_krylov_names_are_deprecated_spellings_of_solver_objects():
    with pytest.warns(DeprecationWarning, match="LinearSolve") as warned:
        old = LinearSolve("cg", rtol=1e-3)
    assert warned[0].filename == __file__  # the user's line, not Equinox's __init__ wrapper
    assert old == LinearSolve(**objects.krylov("cg"), rtol=1e-3)
    with pytest.warns(DeprecationWarning):
        assert LinearSolve(krylov="gmres") == LinearSolve()


def test_make_solver_names_and_errors():
    assert isinstance(make_solver("auto", analytic=None), GaussNewton)
    assert isinstance(make_solver("auto", analytic=lambda *a: a[0]), Analytic)
    assert make_solver("saddle_free_newton", max_loss_change=0).max_loss_change is None
    with pytest.raises(ValueError, match="valid choices: auto, analytic"):
        make_solver("magic")
    with pytest.raises(ValueError, match="unknown krylov 'qr'"):
        make_solver("linear_solve", krylov="qr")


def test_lbfgs_accepts_float32_predictions():
    result = LBFGS(max_steps=500, tol=1e-10)(
        simulate, jnp.asarray(X, jnp.float32), jnp.asarray(Y, jnp.float32), jnp.asarray(Y_TARGET, jnp.float32), SAMPLE
    )
    assert result.x.dtype == jnp.float32 and bool(result.converged)
    np.testing.assert_allclose(np_simulate(np.asarray(result.x, np.float64)), Y_TARGET, atol=1e-5)


def test_linear_solve_with_a_float64_simulator_on_float32_predictions():
    M = RNG.normal(size=(5, 5)) + 5 * np.eye(5)
    sim = lambda x, s: jnp.asarray(M) @ x.astype(jnp.float64)  # noqa: E731  (float64 physics)
    x, yt = jnp.zeros(5, jnp.float32), RNG.normal(size=5)
    result = LinearSolve(rtol=1e-6, atol=1e-8)(sim, x, sim(x, None), jnp.asarray(yt), None)
    assert result.x.dtype == jnp.float32 and bool(result.converged)
    np.testing.assert_allclose(result.x, np.linalg.solve(M, yt), rtol=1e-4, atol=1e-5)


def spd(condition, n=32, seed=0):
    """A symmetric positive definite matrix with eigenvalues log-spaced in [1, condition]."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(n, n)))
    return (q * np.logspace(0, np.log10(condition), n)) @ q.T


def test_linear_solve_cg_default_tolerance_converges_in_float32():
    """Issue 33: at the old default (rtol 1e-6, atol 1e-10 on the unscaled system) CG failed
    on every sample of a condition-170 SPD operator in float32."""
    M = spd(170.0)
    matrix = jnp.asarray(M, jnp.float32)
    sim = lambda x, s: matrix @ x  # noqa: E731
    rng = np.random.default_rng(1)
    x, y_target = rng.normal(size=(64, 32)), rng.normal(size=(64, 32))
    solve = jax.jit(jax.vmap(lambda x, yt: LinearSolve(**SPD_CG)(sim, x, sim(x, None), yt, None)))
    result = solve(jnp.asarray(x, jnp.float32), jnp.asarray(y_target, jnp.float32))
    assert result.x.dtype == jnp.float32 and bool(jnp.all(result.converged))
    want = np.linalg.solve(M, y_target.T).T
    # error ≲ condition × tolerance (ε^{3/4} ≈ 6e-6)
    np.testing.assert_allclose(result.x, want, atol=2e-3 * np.abs(want).max())
    assert LinearSolve(**SPD_CG).tolerances(jnp.float32) == (np.finfo(np.float32).eps ** 0.75,) * 2
    assert LinearSolve(**SPD_CG, rtol=1e-3).tolerances(jnp.float64) == (1e-3, np.finfo(np.float64).eps ** 0.75)


def test_linear_solve_tolerance_is_relative_to_the_residual_scale():
    """The same solve at residuals 1e-6 and 1e6 times as large: the same verdict and x̃ − x
    scaled by the same factor (atol is relative to ‖y_t − y‖_∞)."""
    M = spd(50.0, n=8)
    sim = lambda x, s: jnp.asarray(M) @ x  # noqa: E731
    r = np.random.default_rng(2).normal(size=8)
    solve = jax.jit(lambda yt: LinearSolve(**SPD_CG)(sim, jnp.zeros(8), jnp.zeros(8), yt, None))
    steps = []
    for scale in (1e-6, 1.0, 1e6):
        result = solve(jnp.asarray(scale * r))
        assert bool(result.converged)
        steps.append(np.asarray(result.x) / scale)
    np.testing.assert_allclose(steps[0], steps[1], rtol=1e-9)
    np.testing.assert_allclose(steps[2], steps[1], rtol=1e-9)
