"""physgrad.problems.sim.fluid against independent references: a dense NumPy Poisson solve, SciPy's
linear interpolation, exact shifts, the convergence order, conservation of energy and of
incompressibility, finite differences for both autodiff modes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from physgrad.precision import float64_scope
from physgrad.problems.sim import fluid


def random_velocity(key, n, scale=1.0):
    return scale * jax.random.normal(key, (2, n, n))


def test_fft_projection_leaves_no_divergence_float64():
    with float64_scope():
        v = random_velocity(jax.random.key(0), 32, 5.0).astype(jnp.float64)
        projected, _ = fluid.project(v, 2.0)
        assert float(jnp.abs(fluid.divergence(projected, 2.0)).max()) < 1e-6
        assert float(jnp.abs(fluid.divergence(v, 2.0)).max()) > 1.0  # the test field was far from it


def test_fft_pressure_equals_dense_numpy_solve():
    n, dx = 8, 1.5
    rng = np.random.default_rng(0)
    rhs = rng.normal(size=(n, n))
    rhs -= rhs.mean()
    # the periodic 5-point Laplacian as a dense matrix, written out index by index
    lap = np.zeros((n * n, n * n))
    for i in range(n):
        for j in range(n):
            row = i * n + j
            lap[row, row] = -4 / dx**2
            for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1)):
                lap[row, ((i + di) % n) * n + (j + dj) % n] += 1 / dx**2
    reference = (np.linalg.pinv(lap) @ rhs.ravel()).reshape(n, n)  # the zero-mean solution
    with float64_scope():
        p = fluid.FFTProjection()(jnp.asarray(rhs), dx, jnp.zeros((n, n)))
        np.testing.assert_allclose(np.asarray(p), reference, atol=1e-12)
        np.testing.assert_allclose(np.asarray(fluid.laplace(p, dx)), rhs, atol=1e-12)


def test_cg_projection_matches_fft_to_its_tolerance():
    v = random_velocity(jax.random.key(1), 32)
    exact, _ = fluid.project(v, 2.0)
    cg, _ = fluid.project(v, 2.0, fluid.CGProjection(atol=1e-4))
    # CG stops once max |∇²p − ∇·v| ≤ atol: what is left of the divergence is that residual
    assert float(jnp.abs(fluid.divergence(cg, 2.0)).max()) <= 1e-4
    # the velocity error is ∇ of the pressure error ∇⁻²r, of the order of the residual itself
    assert float(jnp.abs(cg - exact).max()) <= 1e-4
    # a tighter CG converges to the FFT answer
    tight, _ = fluid.project(v, 2.0, fluid.CGProjection(atol=1e-6))
    assert float(jnp.abs(tight - exact).max()) <= 1e-5


def test_stagger_and_centre_are_the_face_and_cell_means():
    c = random_velocity(jax.random.key(2), 6)
    s = fluid.stagger(c)
    assert np.allclose(s[0, 3, 2], 0.5 * (c[0, 2, 2] + c[0, 3, 2]))
    assert np.allclose(s[1, 3, 0], 0.5 * (c[1, 3, 5] + c[1, 3, 0]))  # periodic wrap
    back = fluid.centre(s)
    assert np.allclose(back[0, 1, 4], 0.5 * (s[0, 1, 4] + s[0, 2, 4]))


@pytest.mark.parametrize("offset", [fluid.CENTRED, fluid.FACE_X, fluid.FACE_Y])
def test_bilinear_equals_scipy_linear_interpolation(offset):
    n, dx = 12, 2.0
    rng = np.random.default_rng(3)
    values = rng.normal(size=(n, n))
    points = rng.uniform(-30, 60, size=(2, 50))  # also far outside the domain: periodic
    got, corners = fluid.bilinear(jnp.asarray(values), offset, jnp.asarray(points), dx)
    coords = [points[a] / dx - offset[a] for a in range(2)]
    ref = ndimage.map_coordinates(values, coords, order=1, mode="grid-wrap")
    np.testing.assert_allclose(np.asarray(got), ref, atol=1e-5)
    assert np.all(np.asarray(corners).min(0) <= np.asarray(got) + 1e-6)
    assert np.all(np.asarray(corners).max(0) >= np.asarray(got) - 1e-6)


def test_uniform_field_and_integer_shift_are_exact():
    n, dx, dt = 16, 2.0, 0.25
    m = jax.random.uniform(jax.random.key(4), (n, n))
    velocity = jnp.stack([jnp.full((n, n), 8.0), jnp.full((n, n), -16.0)])  # (+1, −2) cells per step
    shifted = jax.jit(fluid.mac_cormack, static_argnums=(1, 3, 4))(m, fluid.CENTRED, velocity, dt, dx)
    np.testing.assert_array_equal(np.asarray(shifted), np.asarray(jnp.roll(m, (1, -2), (0, 1))))
    # a uniform field stays uniform under any velocity (projected as one program, not op by op)
    swirling = jax.jit(fluid.project, static_argnums=1)(random_velocity(jax.random.key(5), n, 6.0), dx)[0]
    uniform = jax.jit(fluid.mac_cormack, static_argnums=(1, 3, 4))(
        jnp.full((n, n), 0.7), fluid.CENTRED, swirling, dt, dx
    )
    np.testing.assert_allclose(np.asarray(uniform), 0.7, rtol=1e-6)
    # a uniform velocity advects itself unchanged, and one full step keeps it
    assert np.array_equal(
        np.asarray(jax.jit(fluid.advect_velocity, static_argnums=(1, 2))(velocity, dt, dx)), np.asarray(velocity)
    )
    marker, v_new, _ = jax.jit(fluid.step, static_argnums=(3, 4))(m, velocity, jnp.zeros((n, n)), dt, dx)
    np.testing.assert_allclose(np.asarray(v_new), np.asarray(velocity), rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(marker), np.asarray(shifted))


@pytest.mark.parametrize("clamp", [pytest.param(True, marks=pytest.mark.slow), False])  # the clamped variant: slow tier
def test_mac_cormack_is_second_order(clamp):
    """L1 error of a smooth periodic field advected by a uniform, non-grid-aligned velocity
    for time 0.5 at a fixed CFL number: halving Δx divides it by ~4 (semi-Lagrangian: ~2)."""
    errors = []
    # 16 cells already in the asymptotic range (orders 1.96 and 1.99); 128 cost 2-3 s of CPU
    for n in (16, 32, 64):
        dx = 1.0 / n
        steps = round(0.5 / (0.37 * dx))
        dt = 0.5 / steps
        x = fluid.sample_points(n, dx, fluid.CENTRED)
        f = jnp.sin(2 * jnp.pi * x[0]) * jnp.cos(2 * jnp.pi * x[1])
        velocity = jnp.stack([jnp.full((n, n), 1.0), jnp.full((n, n), 0.5)])
        body = lambda g, _: (fluid.mac_cormack(g, fluid.CENTRED, velocity, dt, dx, clamp), None)  # noqa: E731
        g, _ = jax.jit(lambda f: jax.lax.scan(body, f, None, length=steps))(f)
        exact = jnp.sin(2 * jnp.pi * (x[0] - 0.5)) * jnp.cos(2 * jnp.pi * (x[1] - 0.25))
        errors.append(float(jnp.mean(jnp.abs(g - exact))))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 1.8), (errors, orders)


def test_step_keeps_energy_and_incompressibility():
    n, dx = 32, 2.0
    with float64_scope():
        v = fluid.project(random_velocity(jax.random.key(6), n, 4.0).astype(jnp.float64), dx)[0]
        m = jax.random.uniform(jax.random.key(7), (n, n), jnp.float64)
        e0 = fluid.energy(v)
        marker, v1, _ = fluid.step(m, v, jnp.zeros((n, n)), 0.25, dx)
        assert abs(float(fluid.energy(v1) / e0) - 1) < 1e-12  # rescaled exactly
        assert float(jnp.abs(fluid.divergence(v1, dx)).max()) < 1e-10
        # advection alone loses energy (numerical dissipation), which the rescale restores
        assert float(fluid.energy(fluid.project(fluid.advect_velocity(v, 0.25, dx), dx)[0]) / e0) < 1 - 1e-4
        # the clamp keeps the marker inside its initial range
        assert float(marker.min()) >= float(m.min()) - 1e-12 and float(marker.max()) <= float(m.max()) + 1e-12
    zero = fluid.rescale_energy(jnp.zeros((2, n, n)), 1.0)
    assert np.all(np.isfinite(np.asarray(zero))) and float(jnp.abs(zero).max()) == 0.0


@pytest.mark.parametrize(
    "solver,steps",
    [pytest.param(fluid.FFTProjection(), 3, marks=pytest.mark.slow), (fluid.CGProjection(atol=1e-10), 1)],
    ids=["fft", "cg"],
)
@pytest.mark.costly(
    "the fast tier's one derivative check through the CG projection (FFT's is slow): "
    "jvp and grad of its while loop compile"
)
def test_rollout_derivatives_match_finite_differences(solver, steps):
    """Forward (jvp) and reverse (grad) mode of a short rollout against central differences."""
    n, dx, dt = 12, 2.0, 0.25
    with float64_scope():
        k1, k2, k3 = jax.random.split(jax.random.key(8), 3)
        v = fluid.project(random_velocity(k1, n, 3.0).astype(jnp.float64), dx)[0]
        m = jax.random.uniform(k2, (n, n), jnp.float64)
        t = random_velocity(k3, n).astype(jnp.float64)
        w = jnp.cos(jnp.arange(n * n, dtype=jnp.float64)).reshape(n, n)

        def scalar(v):
            return jnp.sum(w * fluid.rollout(m, v, steps, dt, dx, solver)[0])

        # The difference quotient, jvp and grad in one compiled program, not three (about 2 of
        # this test's 11 s of CPU: compiling the CG loop is most of it).
        @jax.jit
        def derivatives(v, t):
            eps = 1e-6
            fd = (scalar(v + eps * t) - scalar(v - eps * t)) / (2 * eps)
            return fd, jax.jvp(scalar, (v,), (t,))[1], jnp.sum(jax.grad(scalar)(v) * t)

        fd, jvp, grad = derivatives(v, t)
        assert abs(float(jvp - fd)) < 1e-6 * max(1.0, abs(float(fd)))
        assert abs(float(grad - fd)) < 1e-6 * max(1.0, abs(float(fd)))


def test_centre_of_mass_and_swirl():
    n, dx = 16, 2.0
    m = jnp.zeros((n, n)).at[3, 5].set(1.0).at[7, 5].set(3.0)
    np.testing.assert_allclose(np.asarray(fluid.centre_of_mass(m, dx)), [(3.5 * 1 + 7.5 * 3) / 4 * dx, 5.5 * dx])
    swirl = fluid.gaussian_swirl(n, dx, (16.0, 16.0), 2.0, 5.0)
    x = fluid.sample_points(n, dx, fluid.CENTRED)
    d = x - 16.0
    expected = 2.0 * np.exp(-0.5 * (d[0] ** 2 + d[1] ** 2) / 25.0) * np.stack([-d[1], d[0]])
    np.testing.assert_allclose(np.asarray(swirl), expected, rtol=1e-6, atol=1e-6)
    # counter-clockwise for a positive strength: at +x of the centre the velocity points to +y
    assert float(swirl[1, 10, 7]) > 0


def test_limiters_clamp_to_their_neighbourhoods_and_the_old_names_still_work():
    """FaceLimiter takes each component's own faces, CellLimiter the cell-centred 2 × 2 values
    (PhiFlow's): an explicit mac_cormack per component is the reference; "faces"/"cells" warn."""
    rng = np.random.default_rng(3)
    v = jnp.asarray(rng.normal(size=(2, 16, 16)), jnp.float32)
    dt, dx = 0.7, 1.0
    for limiter, at in [
        (fluid.FaceLimiter(), lambda a: fluid.STAGGERED[a]),
        (fluid.CellLimiter(), lambda a: fluid.CENTRED),
    ]:
        expected = jnp.stack([fluid.mac_cormack(v[a], fluid.STAGGERED[a], v, dt, dx, True, at(a)) for a in range(2)])
        np.testing.assert_array_equal(
            np.asarray(fluid.advect_velocity(v, dt, dx, limiter=limiter)), np.asarray(expected)
        )
    faces, cells = (
        np.asarray(fluid.advect_velocity(v, dt, dx, limiter=lim)) for lim in (fluid.FaceLimiter(), fluid.CellLimiter())
    )
    assert not np.array_equal(faces, cells)  # the limiter bites somewhere at this step size
    with pytest.warns(DeprecationWarning, match="CellLimiter") as warned:
        np.testing.assert_array_equal(np.asarray(fluid.advect_velocity(v, dt, dx, limiter="cells")), cells)
    assert warned[0].filename == __file__  # the caller's line, past physgrad's own frames
    with pytest.raises(ValueError, match=r"FaceLimiter\(\) or CellLimiter\(\)"):
        fluid.limiter_of("edges")
