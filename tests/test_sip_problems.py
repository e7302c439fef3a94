"""The SIP paper's problems: operators against independent references, data, networks."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.inverse import GaussNewton
from physgrad.nets import UNet, parameter_count
from physgrad.problems import LinearOscillators, Sine, Toy2d
from physgrad.problems.heat import box_parameters, damped_deconvolution, diffuse, random_boxes, soft_box
from physgrad.problems.poisson import solve_poisson
from physgrad.problems.poisson_hig import laplace_zero_boundary
from test_poisson_hig import dense_laplacian


def test_poisson_solve_equals_a_dense_solve():
    x = np.random.default_rng(0).normal(size=(16, 16))
    got = np.asarray(solve_poisson(jnp.asarray(x)))
    np.testing.assert_allclose(got.ravel(), np.linalg.solve(dense_laplacian(16), x.ravel()), rtol=1e-10, atol=1e-10)


def test_poisson_solve_inverts_the_laplacian_at_paper_size():
    x = np.random.default_rng(1).normal(size=(64, 64))
    np.testing.assert_allclose(laplace_zero_boundary(solve_poisson(jnp.asarray(x))), x, atol=1e-9)


def periodic_gaussian_convolution(x, variance):
    """Direct periodic convolution with the sampled, periodised Gaussian of this variance."""
    n = x.shape[0]
    d = np.arange(n)
    images = np.arange(-3, 4)[:, None] * n
    g = np.exp(-((d[None, :] + images) ** 2) / (2 * variance)).sum(0) / np.sqrt(2 * np.pi * variance)
    kernel = np.outer(g, g)
    out = np.zeros_like(x)
    for i in range(n):
        for j in range(n):
            out += x[i, j] * np.roll(np.roll(kernel, i, axis=0), j, axis=1)
    return out


def test_heat_forward_equals_a_direct_gaussian_convolution():
    """exp(−(2π)²|k|² ν t) is the DFT of the periodised Gaussian of variance 2 ν t (aliasing
    ≈ e^{−79} at ν t = 8), so the spectral solver equals a direct convolution."""
    x = np.random.default_rng(2).uniform(size=(32, 32))
    np.testing.assert_allclose(diffuse(jnp.asarray(x), 8.0), periodic_gaussian_convolution(x, 16.0), atol=1e-12)


def test_heat_forward_conserves_the_mean_in_float64():
    x = jnp.asarray(np.random.default_rng(3).uniform(size=(64, 64)), jnp.float32)
    y = diffuse(x, 8.0)
    assert y.dtype == jnp.float64
    np.testing.assert_allclose(jnp.mean(y), jnp.mean(x.astype(jnp.float64)), rtol=1e-12)


def test_damped_deconvolution_inverts_signal_and_damps_noise():
    n = 64
    i = np.arange(n)
    smooth = np.sin(2 * np.pi * i / n)[:, None] * np.cos(4 * np.pi * i / n)[None, :]  # low modes only
    recovered = damped_deconvolution(diffuse(jnp.asarray(smooth), 8.0), 8.0)
    np.testing.assert_allclose(recovered, smooth, atol=1e-9)  # signal: full inversion
    # A checkerboard residual (|k|² = ½) cannot come from diffused data: its expected signal
    # amplitude 64·e^{−158} is far below it, so it is diffused further, not amplified by e^{158}.
    checker = 1e-3 * (-1.0) ** (i[:, None] + i[None, :])
    damped = np.asarray(damped_deconvolution(jnp.asarray(checker), 8.0))
    assert np.abs(damped).max() < 1e-60
    mixed = np.asarray(damped_deconvolution(diffuse(jnp.asarray(smooth), 8.0) + jnp.asarray(checker), 8.0))
    np.testing.assert_allclose(mixed, smooth, atol=1e-9)  # signal kept, noise removed


def test_soft_boxes_cover_their_exact_area():
    box = soft_box(64, jnp.array([20.3, 31.7]), jnp.array([3.25, 5.5]))
    np.testing.assert_allclose(jnp.sum(box), 4 * 3.25 * 5.5, rtol=1e-12)
    assert float(box.max()) == 1.0 and float(box.min()) == 0.0


def test_heat_examples_follow_the_authors_generator():
    keys = jax.random.split(jax.random.key(0), 256)
    centres, halves, strengths = jax.vmap(lambda k: box_parameters(k, 64))(keys)
    counts = np.asarray(jnp.sum(strengths > 0, axis=1))
    assert counts.min() >= 4 and counts.max() <= 10 and len(set(counts.tolist())) == 7  # ⌊4 + 7u⌋
    assert float(halves.min()) >= 0 and float(halves.max()) < 10
    assert bool(jnp.all(centres - halves >= 0)) and bool(jnp.all(centres + halves <= 64))  # inside
    fields = jax.vmap(lambda k: random_boxes(k, 64))(keys)
    # every box lies inside, so the field's total heat is Σ strength × exact area
    np.testing.assert_allclose(
        jnp.sum(fields, axis=(1, 2)), jnp.sum(strengths * 4 * halves[..., 0] * halves[..., 1], axis=1), rtol=1e-10
    )


@pytest.fixture(scope="module")
def unet():
    """The default U-Net, built once for the module's two tests (eagerly: 1.5 s of CPU, its
    initialisation compiled as one program 2.6 s)."""
    return UNet(1, 1, key=jax.random.key(0))


def test_unet_matches_the_phiflow_layout(unet):
    net = unet
    assert parameter_count(net) == 37697 - 448  # PhiFlow u_net(1, 1) minus batch norm
    x = jax.random.normal(jax.random.key(1), (1, 64, 64), jnp.float32)
    out = eqx.filter_jit(lambda n, x: n(x))(net, x)  # one program (eagerly, every layer's ops compile one by one)
    assert out.shape == (1, 64, 64)
    assert bool(jnp.all(jnp.isfinite(out)))
    with pytest.raises(ValueError, match="divisible by 8"):
        net(jnp.zeros((1, 60, 64)))


def test_unet_convolutions_pad_circularly(unet):
    """A 3×3 layer equals a periodic cross-correlation written with np.roll."""
    from physgrad.nets import _circular_conv

    conv = unet.down[0].first
    x = np.random.default_rng(6).normal(size=(1, 16, 16)).astype(np.float32)
    got = np.asarray(_circular_conv(conv, jnp.asarray(x)))
    w, b = np.asarray(conv.weight), np.asarray(conv.bias)
    expected = np.zeros((w.shape[0], 16, 16))
    for o in range(w.shape[0]):
        for di in range(3):
            for dj in range(3):
                expected[o] += w[o, 0, di, dj] * np.roll(x[0], (1 - di, 1 - dj), axis=(0, 1))
    np.testing.assert_allclose(got, expected + b, atol=1e-5)


@pytest.mark.parametrize("xi,phi", [(1.0, 0.0), (32.0, 45.0), (10.0, 30.0)])
def test_sine_closest_solution_solves_the_physics_and_is_nearest(xi, phi):
    problem = Sine(xi=xi, phi=phi)
    rng = np.random.default_rng(5)
    draws = [(rng.normal(size=2) * 2, rng.uniform(-1, 1, size=2)) for _ in range(20)]
    xs, ys = (jnp.asarray(np.stack(d)) for d in zip(*draws))
    # the 20 points as one batch: eagerly, point by point, ~900 operations dispatched one by one
    sols = jax.vmap(problem.closest_solution)(xs, {"y": ys})
    np.testing.assert_allclose(jax.vmap(problem.simulate)(sols, {"y": ys}), ys, atol=1e-9)
    for x, y, sol in zip(np.asarray(xs), np.asarray(ys), np.asarray(sols)):
        # brute force over both arcsin branches and ±5 turns, in NumPy
        a = np.deg2rad(phi)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        scale = np.array([10 / xi, 10 * xi])
        asin = np.arcsin(y[0])
        cands = [rot.T @ (np.array([b + 2 * np.pi * k, y[1]]) / scale)
                 for b in (asin, np.pi - asin) for k in range(-50, 51)]  # fmt: skip
        best = min(np.linalg.norm(x - c) for c in cands)
        np.testing.assert_allclose(np.linalg.norm(x - sol), best, rtol=1e-9)


def test_toy_inverse_picks_the_root_closest_to_the_prediction():
    toy = Toy2d()
    np.testing.assert_allclose(toy.inverse(jnp.array([0.0, -2.0]), None, jnp.array([1.0, 4.0]), None), [1.0, -2.0])
    np.testing.assert_allclose(toy.inverse(jnp.array([0.0, 2.0]), None, jnp.array([1.0, 4.0]), None), [1.0, 2.0])


def test_gauss_newton_inverts_the_linear_oscillator_chain_exactly():
    problem = LinearOscillators()
    data = problem.make_data(jax.random.key(0))
    sample = jax.tree.map(lambda a: a[0].astype(jnp.float64), data["train"])
    u = jax.random.normal(jax.random.key(1), (problem.n_steps,), jnp.float64)
    y = problem.simulate(u, sample)
    result = GaussNewton(1e-5)(problem.simulate, u, y, problem.target(sample), sample)
    assert bool(result.converged)
    np.testing.assert_allclose(problem.simulate(result.x, sample), sample["x0"], atol=1e-9)
