"""Data parallelism: on 4 (forced) CPU devices every method's update equals the
single-device one; the distributed and matrix-free half-inverse routes equal the Gram
route; a two-process run over loopback matches a single-process run.

The 4 CPU devices come from ``XLA_FLAGS=--xla_force_host_platform_device_count=4``,
set in conftest.py before JAX starts (the other tests use device 0 only).
"""

import functools
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree
from jax.sharding import PartitionSpec

from physgrad import Budget, ConfigError
from physgrad.distributed import make_mesh, replicate, use_mesh
from physgrad.harness.config import make_config
from physgrad.harness.registry import METHODS
from physgrad.harness.train import build, load_network, make_step, train
from physgrad.jacobian import stacked_jacobian
from physgrad.routes import (
    Gram,
    JointJacobian,
    blockgram_half_inverse,
    half_inverse,
    lanczos_half_inverse,
    sharded_gram_route,
)

DEVICES = 4
needs_devices = pytest.mark.skipif(jax.device_count() < DEVICES, reason="needs 4 (forced host) devices")

OSC = {"n_steps": "8", "hidden": "6", "n_train": "64", "n_test": "64", "dtype": "float64", "batch_size": "16"}
CARTPOLE = {"n_train": "32", "n_test": "8", "batch_size": "8", "dt": "0.1", "n_steps": "10"}
ADVECTION = {"n_train": "4", "n_test": "2", "horizon": "20", "batch_size": "16", "iterations": "4"}
POISSON = {"resolution": "16", "n_train": "16", "n_test": "8", "batch_size": "8", "levels": "2"}


def problem_for(method):
    """A small problem each method runs on (float64 where the problem has a dtype)."""
    if method in ("bptt", "sbptt_m", "sbptt_c", "no_temporal"):
        return "cartpole", CARTPOLE
    if method in ("one", "nog", "wig"):
        return "advection_1d", ADVECTION
    if method == "sip":
        return "poisson", POISSON
    # This tiny ReLU net's J has singular values down to 1e-10 σ_max: with τ = 1e-6 the
    # filter of the smallest kept ones (σ^κ; for lm σ/(σ² + λ) on ill-determined singular
    # vectors) amplifies rounding differences beyond float64's reordered-sum level.
    extra = (
        {"truncation": "1e-3"} if method in ("gn", "hig", "lm") else {"damping": "10.0"} if method == "newton" else {}
    )
    return "oscillators", {**OSC, **extra}


def first_steps(problem, method, settings):
    """The start parameters, and the parameters and loss after the first training step on one
    device and on ``DEVICES`` devices, from one build of the problem (the data and the network
    are the same for both: building them twice only cost time)."""
    setup = build(make_config(problem, method, budget=Budget(steps=1), settings=settings))
    stage = setup.stages[0]
    data = setup.data["train"]
    order = jnp.arange(jax.tree.leaves(data)[0].shape[0], dtype=jnp.int32)
    inputs = (setup.params, stage.method.init(setup.params), data, order)
    out = []
    for devices in (1, DEVICES):
        mesh = make_mesh(devices)
        with use_mesh(mesh):
            step = make_step(setup, stage.batch_size, stage.method)
            params, _, stats = step(*replicate(inputs, mesh), np.int32(0))
        out += [params, float(stats["loss"])]
    return setup.params, *out


def relative_update_difference(start, a, b):
    ua = ravel_pytree(jax.tree.map(lambda x, y: np.asarray(x) - np.asarray(y), a, start))[0]
    ub = ravel_pytree(jax.tree.map(lambda x, y: np.asarray(x) - np.asarray(y), b, start))[0]
    return float(np.linalg.norm(ua - ub) / max(np.linalg.norm(ua), 1e-300))


# make test runs one method per sharded code path (DP/optax: adam, the Jacobian rules: hig,
# SIP, the rollout policies: sbptt_c, the unrolled modalities: wig); the other methods take
# the same paths and run in the slow tier, as does kfac (kfac-jax's own curvature blocks, compiled twice: minutes).
FAST_SHARDED = {"adam", "hig", "sip", "sbptt_c", "wig"}
SHARDED_COSTLY = {
    "sip": pytest.mark.costly(
        "the fast tier's one sharded SIP step: the U-Net and its per-sample inverse solves "
        "compile for 1 and for 4 devices"
    )
}


def _tiered(method):
    """``method`` as a parameter of its tier: fast (with its reason where costly) or slow."""
    if method in SHARDED_COSTLY:
        return pytest.param(method, marks=SHARDED_COSTLY[method])
    return method if method in FAST_SHARDED else pytest.param(method, marks=pytest.mark.slow)


@needs_devices
@pytest.mark.parametrize("method", [_tiered(m) for m in sorted(METHODS)])
def test_every_method_sharded_over_4_devices_gives_the_single_device_update(method):
    problem, settings = problem_for(method)
    start, single, loss1, sharded, loss4 = first_steps(problem, method, settings)
    # float64 problems: rounding of reordered sums only; float32 ones (poisson, cartpole,
    # advection): float32 rounding.
    tol = 1e-9 if settings.get("dtype") == "float64" else 1e-4
    assert relative_update_difference(start, single, sharded) < tol
    assert loss4 == pytest.approx(loss1, rel=tol)


@needs_devices
# the matrix-free routes' sharded paths in the slow tier (each is compared with the Gram route
# on one device by test_lanczos_and_blockgram_inside_the_hig_method_match_the_gram_route)
@pytest.mark.parametrize(
    "route", ["gram", "structured", *(pytest.param(r, marks=pytest.mark.slow) for r in ("svd", "blockgram", "lanczos"))]
)
def test_hig_routes_sharded_over_4_devices(route):
    settings = {**OSC, "route": route, "blocks": "4", "lanczos_steps": "200", "truncation": "1e-3"}
    start, single, _, sharded, _ = first_steps("oscillators", "hig", settings)
    assert relative_update_difference(start, single, sharded) < 1e-8


@needs_devices
@pytest.mark.parametrize(
    "route", ["gram", pytest.param("structured", marks=pytest.mark.slow), "auto"]
)  # auto: structured here
def test_sharded_hig_step_uses_the_ring_not_a_gathered_jacobian(route):
    """The compiled 4-device step passes row blocks around (collective-permute) and never
    holds all of J: the Gram route holds its own rows of J, the structured route (which
    ``auto`` picks for this MLP) not even those."""
    setup = build(make_config("oscillators", "hig", budget=Budget(steps=1), settings={**OSC, "route": route}))
    stage = setup.stages[0]
    data = setup.data["train"]
    order = jnp.arange(64, dtype=jnp.int32)
    mesh = make_mesh(DEVICES)
    with use_mesh(mesh):
        step = make_step(setup, stage.batch_size, stage.method)
        args = (*replicate((setup.params, stage.method.init(setup.params), data, order), mesh), np.int32(0))
        hlo = step.lower(*args).compile().as_text()
    assert "collective-permute" in hlo
    rows, p = 16 * 4, ravel_pytree(setup.params)[0].size  # J: 16 samples × 4 final-state entries
    assert f"f64[{rows},{p}]" not in hlo
    assert (f"f64[{rows // DEVICES},{p}]" in hlo) == (route == "gram")


@needs_devices
@pytest.mark.parametrize("shape", [(32, 90), (96, 20)])  # wide (ring of row blocks) and tall
@pytest.mark.parametrize("exponent", [-0.5, -1.0, 1.0])
def test_sharded_gram_route_equals_numpy_svd(shape, exponent):
    rng = np.random.default_rng(1)
    m, p = shape
    # singular values spread over 4 decades, one dropped by τ = 1e-5
    u, _ = np.linalg.qr(rng.normal(size=(m, min(m, p))))
    v, _ = np.linalg.qr(rng.normal(size=(p, min(m, p))))
    s = np.logspace(0, -4, min(m, p))
    s[-1] = 1e-7
    jac = (u * s) @ v.T
    g = rng.normal(size=m)
    keep = s > 1e-5 * s.max()
    want = v[:, keep] @ (s[keep] ** exponent * (u[:, keep].T @ g))
    mesh = make_mesh(DEVICES)
    spec = PartitionSpec("data")

    def route(j, g):  # the direction (the spectrum also returned is checked elsewhere)
        return sharded_gram_route(j, g, "data", DEVICES, exponent=exponent, truncation=1e-5)[0]

    with use_mesh(mesh):
        got = jax.jit(jax.shard_map(route, in_specs=(spec, spec), out_specs=PartitionSpec()))(
            jnp.asarray(jac), jnp.asarray(g)
        )
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-7, atol=1e-9 * np.abs(want).max())


def hig_pieces(batch_size=32):
    setup = build(
        make_config("oscillators", "hig", budget=Budget(steps=1), settings={**OSC, "batch_size": str(batch_size)})
    )
    batch = jax.tree.map(lambda a: a[:batch_size], setup.data["train"])
    jac, g, _ = JointJacobian.of(setup.objective, setup.params, batch).jacobian_and_gradient()
    return setup, batch, np.asarray(jac), np.asarray(g)


@pytest.mark.slow  # block Gram against Gram: also in test_half_inverse's route comparisons
def test_blockgram_route_equals_the_gram_route_without_forming_j():
    setup, batch, jac, g = hig_pieces()
    # τ = 1e-3: this ReLU net's J has singular values down to 1e-10 σ_max, whose σ^κ
    # would amplify the rounding differences of the two summation orders.
    want = np.asarray(half_inverse(jnp.asarray(jac), jnp.asarray(g), route=Gram(), truncation=1e-3))
    for blocks in (1, 4, 32):
        route = functools.partial(blockgram_half_inverse, setup.objective.predict, blocks=blocks, truncation=1e-3)
        got = jax.jit(route)(setup.params, batch, jnp.asarray(g))
        np.testing.assert_allclose(np.asarray(got), want, rtol=1e-8, atol=1e-10 * np.abs(want).max())
    with pytest.raises(ValueError, match="must divide"):
        blockgram_half_inverse(setup.objective.predict, setup.params, batch, jnp.asarray(g), blocks=5)


def two_layer_net(seed=0, batch_size=8):
    """A tanh net with a well-conditioned Gram matrix (λ_max/λ_min ≈ 500): m = 24, P = 112."""
    rng = np.random.default_rng(seed)
    params = {"w1": jnp.asarray(rng.normal(size=(16, 4))), "w2": jnp.asarray(rng.normal(size=(3, 16)) / 4)}
    batch = jnp.asarray(rng.normal(size=(batch_size, 4)))

    def predict(p, x):
        return p["w2"] @ jnp.tanh(p["w1"] @ x)

    jac = np.asarray(jax.jit(lambda p, b: stacked_jacobian(predict, p, b)[0])(params, batch))  # one program
    return predict, params, batch, jac, rng.normal(size=jac.shape[0])


def test_lanczos_route_is_exact_at_full_krylov_dimension_and_within_its_bound_before():
    predict, params, batch, jac, g = two_layer_net()
    m = g.size
    lam, u = np.linalg.eigh(jac @ jac.T)
    f = lam**-0.75  # every eigenvalue is far above τ² λ_max: nothing truncated
    exact_x = u @ (f * (u.T @ g))
    want = jac.T @ exact_x
    run = jax.jit(lambda k: lanczos_half_inverse(predict, params, batch, jnp.asarray(g), steps=k), static_argnums=0)
    got, _ = run(m)
    np.testing.assert_allclose(np.asarray(ravel_pytree(got)[0]), want, rtol=1e-8, atol=1e-10 * np.abs(want).max())
    # Before: ‖f(G)g − x_k‖ ≤ 2‖g‖ max_λ |f(λ) − p(λ)| for any p of degree < k; p = the
    # Chebyshev interpolant of f on [λ_min, λ_max] (computed here in NumPy).
    errors = []
    for k in (2, 4, 8, 12):
        direction, _ = run(k)
        x_k = np.linalg.lstsq(jac.T, np.asarray(ravel_pytree(direction)[0]), rcond=None)[0]  # J has full row rank
        cheb = np.polynomial.chebyshev.Chebyshev.interpolate(lambda t: t**-0.75, k - 1, domain=[lam.min(), lam.max()])
        bound = 2 * np.linalg.norm(g) * np.abs(f - cheb(lam)).max()
        errors.append(np.linalg.norm(exact_x - x_k))
        assert errors[-1] <= bound
    assert errors == sorted(errors, reverse=True) and errors[-1] < 0.1 * errors[0]


@pytest.mark.slow  # the routes themselves are compared with the Gram route in make test
def test_lanczos_and_blockgram_inside_the_hig_method_match_the_gram_route():
    setup, batch, jac, g = hig_pieces(batch_size=8)
    m = g.size
    steps = {}
    for route in ("gram", "blockgram", "lanczos"):
        method = METHODS["hig"](route=route, blocks=2, lanczos_steps=m, truncation=1e-3)
        params, _, stats = jax.jit(method.step, static_argnums=0)(
            setup.objective, setup.params, method.init(setup.params), batch
        )
        steps[route] = (ravel_pytree(params)[0], stats)
    ref = np.asarray(steps["gram"][0])
    np.testing.assert_allclose(np.asarray(steps["blockgram"][0]), ref, rtol=1e-9)
    # The Krylov space is all of R^m, but Ritz values below τ²θ_max are dropped as the Gram
    # route drops eigenvalues: equal to the rounding of the matrix-free products.
    np.testing.assert_allclose(np.asarray(steps["lanczos"][0]), ref, rtol=1e-6)
    assert "lanczos_change" in steps["lanczos"][1]


@pytest.mark.unchecked("wrong devices on purpose: make_mesh's own one-line error")
def test_devices_setting_errors_are_one_line():
    with pytest.raises(ConfigError, match="devices"):
        make_mesh(jax.device_count() + 1)
    with pytest.raises(ConfigError, match="a number or 'all'"):
        make_mesh("many")


@pytest.mark.unchecked("deprecated string devices on purpose: their warning")
def test_devices_are_a_number_a_sequence_or_none_and_strings_are_deprecated():
    everything = make_mesh(None)
    assert (1 if everything is None else everything.devices.size) == jax.device_count()
    assert make_mesh(jax.devices()[:1]) is None and make_mesh(1) is None
    with pytest.warns(DeprecationWarning, match="devices='1'"):
        assert make_mesh("1") is None
    with pytest.raises(ConfigError, match="a sequence of jax devices"):
        make_mesh([])


@needs_devices
@pytest.mark.slow
def test_training_on_4_devices_matches_one_device(tmp_path):
    settings = {**OSC, "eval_every": "5", "truncation": "1e-3"}  # τ: see problem_for
    config = make_config("oscillators", "hig", budget=Budget(steps=5), settings=settings)
    one = train(config, tmp_path / "one")
    four = train(config, tmp_path / "four", devices=DEVICES)
    assert four["devices"] == DEVICES and one["devices"] == 1
    assert four["final_test_loss"] == pytest.approx(one["final_test_loss"], rel=1e-9)
    with pytest.raises(ConfigError, match="does not split over 4 devices"):
        train(make_config("oscillators", "adam", budget=Budget(steps=1), settings={**OSC, "batch_size": "6"}),
              tmp_path / "odd", devices=DEVICES)  # fmt: skip


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_process_loopback_run_matches_a_single_process_run(tmp_path):
    """The README's example: two `physgrad train` processes (1 CPU device each) over
    127.0.0.1 train one run; process 0 writes it; it equals the single-process run."""
    args = ["oscillators", "--method", "hig", "--steps", "4", "--quiet",
            *[f"--set={k}={v}" for k, v in OSC.items()], "--set=eval_every=4", "--set=truncation=1e-3"]  # fmt: skip
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=1", "JAX_PLATFORMS": "cpu"}
    run = [sys.executable, "-m", "physgrad", "train", *args]
    single = subprocess.run(
        [*run, "--out", str(tmp_path / "single")], env=env, capture_output=True, text=True, timeout=300
    )
    assert single.returncode == 0, single.stderr
    port = free_port()
    procs = [
        subprocess.Popen(
            [
                *run,
                "--out",
                str(tmp_path / "pair"),
                "--coordinator",
                f"127.0.0.1:{port}",
                "--num-processes",
                "2",
                "--process-id",
                str(i),
            ],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )  # fmt: skip
        for i in range(2)
    ]
    outs = [p.communicate(timeout=300) for p in procs]
    assert [p.returncode for p in procs] == [0, 0], [o[1][-2000:] for o in outs]
    assert "on all devices of 2 processes" in outs[0][0] and "finished" in outs[0][0]
    assert "oscillators" not in outs[1][0]  # process 1 reports nothing (gloo's own lines aside)
    a = json.loads(Path(tmp_path / "single" / "summary.json").read_text())
    b = json.loads(Path(tmp_path / "pair" / "summary.json").read_text())
    assert b["devices"] == 2 and a["devices"] == 1
    assert b["final_test_loss"] == pytest.approx(a["final_test_loss"], rel=1e-9)
    cases_a, cases_b = (json.loads((tmp_path / d / "test_cases.json").read_text()) for d in ("single", "pair"))
    assert len(cases_b["loss"]) == len(cases_a["loss"]) == int(OSC["n_test"])  # every case, not one process's share
    np.testing.assert_allclose(cases_b["loss"], cases_a["loss"], rtol=1e-9)
    theta_a, theta_b = (
        ravel_pytree(eqx.filter(load_network(tmp_path / d), eqx.is_inexact_array))[0] for d in ("single", "pair")
    )
    np.testing.assert_allclose(np.asarray(theta_b), np.asarray(theta_a), rtol=1e-6, atol=1e-9)


def test_cli_device_errors_are_one_line_with_exit_2(capsys, tmp_path):
    from physgrad.harness.cli import main

    base = ["train", "oscillators", "--method", "adam", "--steps", "1", "--out", str(tmp_path / "r")]
    assert main([*base, "--devices", "many"]) == 2
    assert main([*base, "--coordinator", "127.0.0.1:1"]) == 2
    assert main([*base, "--devices", "99"]) == 2
    assert main(
        [*base, "--set", "batch_size=6", "--set", "n_train=64", "--devices", str(min(jax.device_count(), 4))]
    ) == (2 if jax.device_count() >= 4 else 0)
    err = capsys.readouterr().err.strip().splitlines()
    assert all(line.startswith("physgrad: error: ") for line in err) and len(err) == (
        4 if jax.device_count() >= 4 else 3
    )
    assert "needs all of --coordinator, --num-processes and --process-id" in err[1]


@needs_devices
@pytest.mark.parametrize("n", [64, 30])  # 30: padded to 32 and cut again
def test_evaluation_split_over_devices_equals_one_device(n):
    from physgrad.harness.train import make_evaluate

    setup = build(make_config("oscillators", "adam", budget=Budget(steps=1), settings=OSC))
    data = jax.tree.map(lambda a: a[:n], setup.data["test"])
    evaluate = make_evaluate(setup, chunk=8, per_sample=True)
    want = evaluate(setup.params, data)
    mesh = make_mesh(DEVICES)
    with use_mesh(mesh):
        got = make_evaluate(setup, chunk=8, per_sample=True)(*replicate((setup.params, data), mesh))
    for k in want:
        assert got[k].shape == (n,)
        np.testing.assert_allclose(np.asarray(got[k]), np.asarray(want[k]), rtol=1e-12)


def test_settings_added_later_keep_earlier_run_names_and_resume(tmp_path):
    """A config written before `blocks`/`lanczos_steps` (hig) and `dtype` (poisson)
    existed has the same digest as today's default config, and resumes."""
    from physgrad.harness.config import RunConfig

    for problem, method, added in [("oscillators", "hig", ("blocks", "lanczos_steps")), ("poisson", "sip", ())]:
        config = make_config(problem, method, budget=Budget(steps=1))
        old = config.to_dict()
        for phase in old["phases"]:
            for name in added:
                del phase["hyperparameters"][name]
        if problem == "poisson":
            del old["problem_settings"]["dtype"]
        assert RunConfig.from_dict(old).digest() == config.digest()
    changed = make_config("oscillators", "hig", budget=Budget(steps=1), settings={"blocks": "4"})
    assert changed.digest() != make_config("oscillators", "hig", budget=Budget(steps=1)).digest()
    # resume of a run directory whose config.json predates the new hyperparameters
    config = make_config("oscillators", "hig", budget=Budget(steps=2), settings={**OSC, "truncation": "1e-3"})
    train(config, tmp_path / "run")
    path = tmp_path / "run" / "config.json"
    old = json.loads(path.read_text())
    for name in ("blocks", "lanczos_steps"):
        del old["phases"][0]["hyperparameters"][name]
    path.write_text(json.dumps(old))
    longer = make_config("oscillators", "hig", budget=Budget(steps=3), settings={**OSC, "truncation": "1e-3"})
    assert train(longer, tmp_path / "run", resume=True)["steps"] == 3
