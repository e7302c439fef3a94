"""half_inverse against a NumPy float64 SVD formula written here, and its two routes."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad import half_inverse
from physgrad.routes import SVD, Gram, by_shape


def reference(j, g, exponent, truncation):
    """V diag(s^κ) Uᵀ g over s > τ s_max, in NumPy float64."""
    u, s, vt = np.linalg.svd(np.asarray(j, np.float64), full_matrices=False)
    keep = s > truncation * s.max()
    return vt[keep].T @ (s[keep] ** exponent * (u[:, keep].T @ np.asarray(g, np.float64)))


def matrix_with_spectrum(rng, m, p, singular_values):
    u, _ = np.linalg.qr(rng.standard_normal((m, len(singular_values))))
    v, _ = np.linalg.qr(rng.standard_normal((p, len(singular_values))))
    return (u * singular_values) @ v.T


@pytest.mark.parametrize("shape", [(12, 40), (40, 12), (30, 30)])
@pytest.mark.parametrize("exponent", [-1.0, -0.5, 0.5, 1.0])
@pytest.mark.parametrize("truncation", [1e-6, 1e-2, 0.3])
@pytest.mark.parametrize("route", [SVD(), Gram()])
def test_matches_numpy_formula(shape, exponent, truncation, route):
    rng = np.random.default_rng(0)
    m, p = shape
    k = min(m, p)
    j = matrix_with_spectrum(rng, m, p, np.logspace(0, -3, k))  # spans the truncations
    g = rng.standard_normal(m)
    got = half_inverse(jnp.asarray(j), jnp.asarray(g), exponent=exponent, truncation=truncation, route=route)
    want = reference(j, g, exponent, truncation)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-7, atol=1e-9 * np.abs(want).max())


@pytest.mark.parametrize("shape", [(64, 300), (300, 64), (50, 60)])
def test_routes_agree_in_float32(shape):
    rng = np.random.default_rng(1)
    m, p = shape
    j = matrix_with_spectrum(rng, m, p, np.linspace(1.0, 0.2, min(m, p))).astype(np.float32)
    g = rng.standard_normal(m).astype(np.float32)
    # each route compiled as one program (eagerly, each operation compiles on its own)
    svd = jax.jit(lambda j, g: half_inverse(j, g, route=SVD()))(jnp.asarray(j), jnp.asarray(g))
    gram = jax.jit(lambda j, g: half_inverse(j, g, route=Gram()))(jnp.asarray(j), jnp.asarray(g))
    assert svd.dtype == gram.dtype == jnp.float32
    rel = np.linalg.norm(np.asarray(svd) - np.asarray(gram)) / np.linalg.norm(np.asarray(gram))
    assert rel < 1e-5


def test_exponent_plus_one_is_transpose_product():
    rng = np.random.default_rng(2)
    j, g = rng.standard_normal((20, 50)), rng.standard_normal(20)
    for route in (SVD(), Gram()):
        got = half_inverse(jnp.asarray(j), jnp.asarray(g), exponent=1.0, truncation=0.0, route=route)
        np.testing.assert_allclose(np.asarray(got), j.T @ g, rtol=1e-9, atol=1e-10)


def test_exponent_minus_one_solves_least_squares():
    rng = np.random.default_rng(3)
    j, g = rng.standard_normal((60, 15)), rng.standard_normal(60)  # tall, full column rank
    want = np.linalg.lstsq(j, g, rcond=None)[0]
    for route in (SVD(), Gram()):
        got = half_inverse(jnp.asarray(j), jnp.asarray(g), exponent=-1.0, truncation=1e-10, route=route)
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-8, atol=1e-10)


def test_truncated_directions_are_dropped_not_clamped():
    rng = np.random.default_rng(4)
    j = matrix_with_spectrum(rng, 5, 9, np.array([1.0, 0.5, 0.1, 1e-4, 1e-5]))
    u, s, vt = np.linalg.svd(j, full_matrices=False)
    g = u[:, 3]  # lies entirely in a direction below the cut-off
    for route in (SVD(), Gram()):
        got = half_inverse(jnp.asarray(j), jnp.asarray(g), truncation=1e-3, route=route)
        assert np.linalg.norm(np.asarray(got)) < 1e-8


def test_rank_deficient_gives_finite_result():
    rng = np.random.default_rng(5)
    j = matrix_with_spectrum(rng, 20, 40, np.array([2.0, 1.0, 0.5]))  # rank 3
    g = rng.standard_normal(20)
    for route in (SVD(), Gram()):
        got = half_inverse(jnp.asarray(j), jnp.asarray(g), truncation=1e-6, route=route)
        np.testing.assert_allclose(np.asarray(got), reference(j, g, -0.5, 1e-6), rtol=1e-6, atol=1e-9)


@pytest.mark.unchecked("route='qr' on purpose: half_inverse's own one-line error")
def test_auto_route_and_errors():
    assert isinstance(by_shape((512, 2956)), Gram)
    assert isinstance(by_shape((2956, 512)), Gram)
    assert isinstance(by_shape((100, 120)), SVD)
    with pytest.raises(ValueError, match="route SVD\\(\\), Gram\\(\\) or None"):
        half_inverse(jnp.ones((3, 4)), jnp.ones(3), route="qr")
    with pytest.raises(ValueError, match="jacobian"):
        half_inverse(jnp.ones((3, 4)), jnp.ones(4))


def float32_network_float64_simulator():
    """A float32 MLP whose outputs a float64 "simulator" maps nonlinearly (as heat: a float32
    network in front of float64 physics), a float64 loss, and a batch of 6 samples."""
    import equinox as eqx

    from physgrad.methods import Objective

    net = eqx.nn.MLP(3, 4, 8, 1, activation=jnp.tanh, key=jax.random.key(0), dtype=jnp.float32)
    params, static = eqx.partition(net, eqx.is_inexact_array)

    def predict(p, s):
        x = eqx.combine(p, static)(s["x"])
        return jnp.sin(x.astype(jnp.float64) * s["c"])

    rng = np.random.default_rng(0)
    batch = {"x": jnp.asarray(rng.normal(size=(6, 3)), jnp.float32), "c": jnp.asarray(rng.uniform(1, 2, (6, 1))),
             "t": jnp.asarray(rng.normal(size=(6, 4)))}  # fmt: skip
    objective = Objective(predict=predict, loss=lambda y, s: 0.5 * jnp.sum((y - s["t"]) ** 2))
    return objective, params, batch


def _direction(name):
    from physgrad.harness.registry import make_route

    objective, params, batch = float32_network_float64_simulator()
    r = make_route(name, blocks=3, lanczos_steps=24)  # 24 = m: Lanczos exact up to rounding
    d, loss, _ = jax.jit(lambda p, b: r(objective, p, b, -0.5, 1e-3))(params, batch)
    assert d.dtype == jnp.float32 and loss.dtype == jnp.float64
    return np.asarray(d)


@pytest.fixture(scope="module")
def gram_direction():
    return _direction("gram")


@pytest.mark.parametrize("route", ["svd", "structured", "blockgram", "lanczos"])
def test_every_route_takes_a_simulator_whose_outputs_are_float64_behind_a_float32_network(route, gram_direction):
    """Issue 29: the Lanczos route failed with 'cotangent type does not match function
    output' when the simulator's dtype differs from the parameters'."""
    ref = gram_direction
    np.testing.assert_allclose(_direction(route), ref, rtol=0, atol=1e-4 * np.abs(ref).max())


# --- what a step reports: the route, the rank kept, the singular-value range (issue 33) ---
def _spectrum_case(tall: bool):
    """An eqx.nn.MLP (float64) through a small nonlinear map; J wide (8 × 122) or tall
    (80 × 38: a narrow net and long outputs)."""
    import equinox as eqx

    width, depth, out, b = (2, 1, 10, 8) if tall else (8, 2, 2, 4)
    model = eqx.nn.MLP(3, out, width, depth, activation=jax.nn.tanh, dtype=jnp.float64, key=jax.random.key(0))
    batch = {"x": jax.random.normal(jax.random.key(1), (b, 3), jnp.float64)}
    batch["target"] = jnp.zeros((b, out), jnp.float64)

    def predict(m, s):
        u = m(s["x"])
        return u + 0.1 * u**2

    def loss(y, s):
        return 0.5 * jnp.sum((y - s["target"]) ** 2)

    return model, batch, predict, loss


@functools.cache
def _spectrum_reference(tall: bool):
    """The stacked Jacobian's shape and NumPy's singular values of it, once per case for all six
    routes (the Jacobian compiled as one program: eagerly, each operation compiles on its own)."""
    import equinox as eqx

    from physgrad.jacobian import stacked_jacobian

    model, batch, predict, _ = _spectrum_case(tall)
    arrays, static = eqx.partition(model, eqx.is_inexact_array)
    jac, _ = jax.jit(lambda a, b: stacked_jacobian(lambda p, s: predict(eqx.combine(p, static), s), a, b))(
        arrays, batch
    )
    return jac.shape, np.linalg.svd(np.asarray(jac), compute_uv=False)


@pytest.mark.parametrize("tall", [False, True])
@pytest.mark.parametrize("route_name", ["auto", "svd", "gram", "structured", "blockgram", "lanczos"])
def test_stats_report_the_route_rank_and_kept_singular_values(route_name, tall):
    """Against NumPy's SVD of the same stacked Jacobian; ``describe`` names the route
    before the step, and the step's ``route`` code agrees."""
    import equinox as eqx

    import physgrad
    from physgrad import routes

    model, batch, predict, loss = _spectrum_case(tall)
    shape, s = _spectrum_reference(tall)
    truncation = float(0.5 * (s[-2] + s[-3]) / s.max())  # drops the two smallest singular values
    keep = s > truncation * s.max()
    objects = {"auto": routes.Auto(), "svd": routes.SVD(), "gram": routes.Gram(), "structured": routes.Structured(),
               "blockgram": routes.BlockGram(2), "lanczos": routes.Lanczos(steps=shape[0])}  # fmt: skip
    estimate = physgrad.hig(predict, loss, truncation=truncation, route=objects[route_name])
    described = estimate.describe(model, batch)
    _, stats = eqx.filter_jit(estimate)(model, batch)

    assert described["jacobian"] == shape
    ran = routes.ROUTE_NAMES[int(stats["route"])]
    assert ran == described["route"]
    if route_name == "auto":
        assert ran == ("gram" if tall else "structured")  # tall J: Gram; wide with dense layers: structured
    elif route_name == "structured" and tall:
        assert ran == "gram"
    else:
        assert ran == route_name
    assert int(stats["rank"]) == keep.sum() == len(s) - 2
    rtol = 1e-4 if route_name == "lanczos" else 1e-8  # Lanczos: Ritz values, exact only up to rounding at k = rows
    np.testing.assert_allclose(float(stats["sigma_max"]), s.max(), rtol=rtol)
    np.testing.assert_allclose(float(stats["sigma_min_kept"]), s[keep].min(), rtol=rtol)


def test_gauss_newton_and_lm_report_the_spectrum_too():
    import equinox as eqx

    import physgrad
    from physgrad.methods.lm import LevenbergMarquardt

    model, batch, predict, loss = _spectrum_case(False)
    _, stats = eqx.filter_jit(physgrad.gauss_newton(predict, loss))(model, batch)
    assert {"route", "rank", "sigma_max", "sigma_min_kept"} <= set(stats)
    lm = LevenbergMarquardt()
    _, _, lm_stats = eqx.filter_jit(lambda m, b: lm.step(physgrad.Objective(predict, loss), m, lm.init(m), b))(
        model, batch
    )
    for name in ("route", "rank", "sigma_max", "sigma_min_kept"):
        np.testing.assert_allclose(np.asarray(lm_stats[name]), np.asarray(stats[name]), rtol=1e-8)
