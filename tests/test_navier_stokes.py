"""The navier_stokes problem (SIP paper Fig. 7) on a small grid: data, loss, the authors'
local inverse, and training with adam and sip from the command line."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from physgrad.harness.cli import main
from physgrad.problems import NavierStokes
from physgrad.problems.navier_stokes import frequency_loss, threshold_top
from physgrad.problems.sim import fluid

# a quarter of the paper's grid: lengths and the loss's falloff (in cycles per cell) scaled by 1/4
SMALL = dict(
    resolution=16, size=32.0, box=14.0, swirl_sigma=5.0, falloff=20.0, levels=3, filters=4, n_train=8, n_test=4
)


@pytest.fixture(scope="module")
def problem():
    return NavierStokes(**SMALL)


@pytest.fixture(scope="module")
def samples(problem):
    return problem.examples(jax.random.key(0), 4)


@pytest.fixture(scope="module")
def simulate(problem):
    """The problem's simulation as one jitted function for the module (a new jit of the bound
    method compiles again)."""
    return jax.jit(problem.simulate)


@pytest.fixture(scope="module")
def inverse(problem):
    """The authors' local inverse, jitted once for the module."""
    return jax.jit(problem.inverse)


def one(samples, i=0):
    return {k: jnp.asarray(v[i]) for k, v in samples.items()}


def test_frequency_loss_equals_numpy_formula():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(16, 16)).astype(np.float32)
    k = np.fft.fftfreq(16)
    weight = np.exp(-0.5 * (k[:, None] ** 2 + k[None, :] ** 2) * 20.0**2)  # 80 on 64² = 20 on 16²
    amplitude = np.abs(np.fft.fft2(d - d.mean()) * weight)
    expected = np.sum(np.maximum(amplitude, np.sqrt(1e-5))) - 256 * np.sqrt(1e-5)  # PhiFlow's, minus its floor
    assert expected > 1.0  # several modes above the threshold
    assert float(frequency_loss(jnp.asarray(d), 20.0)) == pytest.approx(expected, rel=1e-5)
    assert float(frequency_loss(jnp.asarray(d) + 3.0, 20.0)) == pytest.approx(expected, rel=1e-5)  # mean ignored


def test_threshold_keeps_the_top_fraction():
    values = jnp.arange(100.0).reshape(10, 10)[::-1]
    marked = threshold_top(values, 0.07)
    assert int(marked.sum()) == 7 and float(values[marked == 1].min()) == 93.0


@pytest.mark.costly("the module fixtures' first user: it generates the fluid samples, compiles the simulation")
def test_data_are_consistent(problem, samples, simulate):
    s = one(samples)
    m0 = np.asarray(s["m0"])
    assert m0.min() >= 0 and m0.max() <= 1  # 1 inside the box, the covered fraction on its edge cells
    assert 1 <= int((m0 > 0).sum()) <= round(0.15 * 256)  # at most the top 15 % of the cells
    # m_T is the simulation of the true v₀: the loss there is 0 (PhiFlow's floor √1e-5 per mode removed)
    y = simulate(s["v0"], s)
    np.testing.assert_allclose(np.asarray(y), np.asarray(s["mT"]), atol=1e-5)
    assert abs(float(problem.loss(y, s))) < 1e-4
    # the drift part of v₀ carries the marker's centre of mass to the centre of the domain
    drift = (problem.centre - fluid.centre_of_mass(s["m0"], problem.dx)) / problem.time
    mean_v = jnp.mean(s["v0"], axis=(1, 2))
    np.testing.assert_allclose(np.asarray(mean_v), np.asarray(drift), atol=0.05)  # swirl and noise average ~0
    assert float(problem.loss(simulate(jnp.zeros_like(s["v0"]), s), s)) > 0.1


def test_vorticity_recovers_a_swirl_exactly(problem):
    for strength in (-1.3, 0.4):
        assert float(problem.vorticity(problem.swirl(strength))) == pytest.approx(strength, rel=1e-5)
    uniform = jnp.ones((2, 16, 16)) * jnp.array([1.5, -2.0])[:, None, None]
    assert abs(float(problem.vorticity(uniform))) < 1e-6  # a uniform flow carries no swirl


def test_paper_swirl_normaliser():
    """At the paper's sizes the computed N_σ is the authors' hard-coded 120.5."""
    assert float(NavierStokes().swirl_norm()) == pytest.approx(120.5, abs=0.05)


def test_inverse_lies_in_the_prior_family_and_improves_a_bad_guess(problem, samples, simulate, inverse):
    for i in range(3):
        s = one(samples, i)
        guess = jnp.zeros_like(s["v0"])
        x_tilde = inverse(guess, simulate(guess, s), s["mT"], s)
        drift = (problem.centre - fluid.centre_of_mass(s["m0"], problem.dx)) / problem.time
        swirl = x_tilde - drift[:, None, None]
        strength = problem.vorticity(swirl)
        np.testing.assert_allclose(np.asarray(swirl), np.asarray(problem.swirl(strength)), atol=1e-5)
        err = lambda x: float(problem.metrics(x, None, s)["v0_l1"])  # noqa: E731
        assert err(x_tilde) < 0.5 * err(guess)


def test_inverse_at_the_truth_stays_near_it(inverse):
    """From the true v₀ the forward and reversed centres of mass agree, so x̃ is the true
    drift + swirl: what remains is the 0.1 noise the prior cannot express."""
    no_noise = NavierStokes(**{**SMALL, "fluctuations": 0.0})
    data = no_noise.examples(jax.random.key(1), 2)
    # the module's compiled inverse: the fluctuations only shape the data (example), not the inverse
    for i in range(2):
        s = one(data, i)
        x_tilde = inverse(s["v0"], s["mT"], s["mT"], s)
        rel = float(jnp.abs(x_tilde - s["v0"]).max() / jnp.abs(s["v0"]).max())
        assert rel < 0.02, rel


@pytest.mark.slow
def test_compare_adam_and_sip_from_the_command_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "cache"))
    settings = [f"--set={k}={v}" for k, v in SMALL.items()] + ["--set=batch_size=4", "--set=eval_every=2"]
    code = main(["compare", "navier_stokes", "--methods", "adam,sip", "--seeds", "1", "--steps", "2",
                 "--out", str(tmp_path / "study"), "--quiet", *settings])  # fmt: skip
    assert code == 0
    out = capsys.readouterr().out
    assert "adam" in out and "sip" in out
    assert main(["train", "navier_stokes", "--method", "sip", "--set", "projection=spectral", "--steps", "1"]) == 2
    assert "valid choices: fft, cg" in capsys.readouterr().err


@pytest.mark.slow
def test_phiflow_simulator_trains_the_same_problem(tmp_path, monkeypatch, capsys):
    """The README's command on a small grid: adam back-propagates through PhiFlow's step and
    sip runs the authors' inverse with it (data from the JAX fluid with PhiFlow's limiter)."""
    import importlib.util

    if importlib.util.find_spec("phi") is None:
        pytest.skip("PhiFlow is not installed (pip install physgrad[phiflow])")
    import jax

    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "cache"))
    small = {**SMALL, "resolution": 8, "size": 16.0, "box": 6.0, "swirl_sigma": 2.5, "falloff": 10.0, "levels": 2,
             "steps": 2, "time": 0.5, "n_train": 4, "n_test": 2}  # fmt: skip
    settings = [f"--set={k}={v}" for k, v in small.items()] + ["--set=simulator=phiflow", "--set=limiter=cells",
                                                                "--set=batch_size=2", "--set=eval_every=1"]  # fmt: skip
    x64 = jax.config.jax_enable_x64
    code = main(["compare", "navier_stokes", "--methods", "adam,sip", "--seeds", "1", "--steps", "1",
                 "--out", str(tmp_path / "study"), "--quiet", *settings])  # fmt: skip
    assert code == 0
    assert jax.config.jax_enable_x64 == x64 or x64 is False  # the CLI's own setting, not PhiFlow's
    rows = (tmp_path / "study" / "summary.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 and all(",finished," in row for row in rows)


def test_weight_standardisation_equals_numpy_and_is_scale_invariant():
    from physgrad.nets import UNet, standardised_weight

    w = np.random.default_rng(0).normal(size=(4, 3, 3, 3)).astype(np.float32)
    flat = w.reshape(4, -1)
    expected = (flat - flat.mean(1, keepdims=True)) / (flat.std(1, keepdims=True) + 1e-5) * np.sqrt(2 / 27)
    np.testing.assert_allclose(np.asarray(standardised_weight(jnp.asarray(w))), expected.reshape(w.shape), atol=1e-6)
    # as under batch norm, a standardised conv's output does not depend on its kernel's scale
    # built eagerly (as one jitted program its initialisation cost ~1 s more of CPU); the function,
    # not the deprecated "leaky_relu" string
    net = UNet(2, 2, levels=3, filters=4, key=jax.random.key(0), activation=jax.nn.leaky_relu,
               weight_standardisation=True)  # fmt: skip
    scaled = eqx.tree_at(lambda n: n.down[1].first.weight, net, 7.0 * net.down[1].first.weight)
    x = jax.random.uniform(jax.random.key(1), (2, 16, 16))
    apply = eqx.filter_jit(lambda n, x: n(x))  # one program, not hundreds of eager ops
    np.testing.assert_allclose(np.asarray(apply(scaled, x)), np.asarray(apply(net, x)), rtol=1e-4, atol=1e-5)


@pytest.mark.slow  # five SIP steps through the fluid: a training behaviour, not a formula
def test_default_network_keeps_its_channels_alive_under_sip(problem, samples):
    """The default U-Net (leaky ReLU, weight-standardised convs) keeps every last-layer
    channel active and its output input-dependent over a few SIP steps at the authors' lr;
    ``activation=relu, weight_standardisation=false`` is the plain (BN-less PyTorch) U-Net."""
    import optax

    from physgrad.methods.sip import ScaleInvariantPhysics
    from physgrad.nets import UNet

    plain = NavierStokes(**SMALL, activation="relu", weight_standardisation=False).make_network(jax.random.key(0))
    reference = UNet(2, 2, levels=3, filters=4, key=jax.random.key(0))
    x = jnp.stack([jnp.asarray(samples["m0"][0]), jnp.asarray(samples["mT"][0])])
    np.testing.assert_array_equal(np.asarray(plain(x)), np.asarray(reference(x)))

    net = problem.make_network(jax.random.key(0))
    params, static = eqx.partition(net, eqx.is_inexact_array)
    objective, rule, opt = problem.objective(static), ScaleInvariantPhysics(), optax.adam(5e-3)
    batch = {k: jnp.asarray(v) for k, v in samples.items()}
    inputs = jnp.stack([batch["m0"], batch["mT"]], axis=1)

    @jax.jit
    def step(params, state):
        d, _ = rule(objective, params, batch)
        updates, state = opt.update(d, state, params)
        return optax.apply_updates(params, updates), state

    state = opt.init(params)
    for _ in range(5):
        params, state = step(params, state)
        network = eqx.combine(params, static)
        features = jax.vmap(network.features)(inputs)
        assert bool(jnp.all(jnp.any(features > 0, axis=(0, 2, 3)))), "a last-layer channel died"
        means = jax.vmap(network)(inputs).mean(axis=(2, 3))
        assert float(jnp.std(means, axis=0).max()) > 1e-3  # not collapsed to a constant output


def test_strategies_are_objects_and_the_command_line_keeps_its_names():
    """projection, limiter, simulator and activation are objects; the command line (and so
    config.json) spells them as before, the old strings still build the same problem (with a
    DeprecationWarning), and the data cache is keyed by the old words."""
    import warnings

    from physgrad.harness.objects import make_problem, problem_defaults
    from physgrad.problems.navier_stokes import _cache_word
    from physgrad.problems.sim.phiflow import PhiFlowFluid

    defaults = problem_defaults(NavierStokes)
    spelt = {k: defaults[k] for k in ("projection", "limiter", "simulator", "activation")}
    assert spelt == {"projection": "fft", "limiter": "faces", "simulator": "jax", "activation": "leaky_relu"}
    built = make_problem(
        NavierStokes, {"projection": "cg", "limiter": "cells", "simulator": "phiflow", "activation": "relu"}
    )
    objects = NavierStokes(projection=fluid.CGProjection(), limiter=fluid.CellLimiter(), simulator=PhiFlowFluid(),
                           activation=jax.nn.relu)  # fmt: skip
    assert built == objects
    with pytest.raises(ValueError, match="valid choices: fft, cg"):
        make_problem(NavierStokes, {"projection": "spectral"})
    with pytest.warns(DeprecationWarning, match="is deprecated; pass the object") as warned:
        assert NavierStokes(projection="cg", limiter="cells", simulator="phiflow", activation="relu") == objects
    assert {w.filename for w in warned} == {__file__}  # each names this line, with or without --jaxtyping
    with pytest.raises(ValueError, match=r"FFTProjection\(\) or CGProjection\(\)"):
        NavierStokes(projection=fluid.CellLimiter())  # pyright: ignore[reportArgumentType]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the defaults are objects: no deprecated spelling inside
        problem = NavierStokes()
    words = {k: _cache_word(k, getattr(problem, k)) for k in ("projection", "limiter", "simulator", "resolution")}
    assert words == {"projection": "fft", "limiter": "faces", "simulator": "jax", "resolution": 64}
    assert _cache_word("projection", fluid.CGProjection(atol=1e-6)) == repr(fluid.CGProjection(atol=1e-6))


def test_the_simulator_object_runs_the_jax_fluid_with_the_problems_solver_and_limiter(samples):
    p = NavierStokes(**{**SMALL, "steps": 2}, limiter=fluid.CellLimiter())
    sample = one(samples)
    velocity = p.initial_velocity(sample["v0"])
    expected = fluid.rollout(sample["m0"], velocity, 2, p.dt, p.dx, fluid.FFTProjection(), fluid.CellLimiter())
    np.testing.assert_array_equal(np.asarray(p.rollout(sample["m0"], velocity)[0]), np.asarray(expected[0]))


def test_unet_takes_its_activation_as_a_function():
    from physgrad.nets import UNet

    key, x = jax.random.key(0), jax.random.uniform(jax.random.key(1), (2, 8, 8))
    leaky = UNet(2, 2, levels=2, filters=4, key=key, activation=jax.nn.leaky_relu)
    with pytest.warns(DeprecationWarning, match="jax.nn.leaky_relu") as warned:
        named = UNet(2, 2, levels=2, filters=4, key=key, activation="leaky_relu")
    assert warned[0].filename == __file__  # the warning names the user's line, not Equinox's
    np.testing.assert_array_equal(np.asarray(leaky(x)), np.asarray(named(x)))
    assert not np.array_equal(np.asarray(leaky(x)), np.asarray(UNet(2, 2, levels=2, filters=4, key=key)(x)))
