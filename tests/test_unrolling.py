"""Neural time-steppers: modalities against hand-written loops and a NumPy float64 adjoint,
compositions against their formulas, solver differentiability, stabilisers, schedules and
curricula (the batches, problems' data and PRDP: tests/test_time_stepper_data.py)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad  # noqa: F401
from physgrad.harness.cli import main
from physgrad.harness.config import Budget, ConfigError, make_config
from physgrad.harness.registry import METHODS
from physgrad.harness.train import build, make_step, train
from physgrad.problems import Advection1d, KuramotoSivashinsky
from physgrad.problems.sim.steppers import (
    Bypass,
    NonDifferentiable,
    NotDifferentiableError,
    Parallel,
    Prediction,
    Residual,
    Sequential,
    Solver,
)
from physgrad.rollout import value_and_grad
from small_advection import adv_config, data_cache  # noqa: F401 — data_cache: an autouse fixture

# --- the modalities against independent references ------------------------------------------


def numpy_sweeps(u, cfl, iterations):
    """Implicit upwind by Jacobi sweeps, written independently in float64 NumPy."""
    a, v = abs(cfl), u.copy()
    for _ in range(iterations):
        neighbour = np.roll(v, -1) if cfl < 0 else np.roll(v, 1)
        v = (u + a * neighbour) / (1 + a)
    return v


def numpy_loss_and_grad(w, traj, cfl, iterations, mode):
    """L = (1/m) Σ_k mean((u_k − ũ_k)²) and dL/dw for u_{k+1} = P u_k + w₀u_k + w₁ shift(u_k),
    by forward sensitivities in float64: WIG carries du/dw through P and the stencil, NOG
    only the local term at the detached state, ONE the local term at the reference state."""
    n, m = traj.shape[1], traj.shape[0] - 1
    eye = np.eye(n)
    P = np.stack([numpy_sweeps(eye[:, j], cfl, iterations) for j in range(n)], axis=1)
    shift = np.roll(eye, -1, axis=0)  # (shift u)_i = u_{i+1}
    A = P + w[0] * eye + w[1] * shift
    u, du = traj[0].copy(), np.zeros((2, n))
    loss, grad = 0.0, np.zeros(2)
    for k in range(m):
        base = traj[k] if mode == "one" else u
        local = np.stack([base, shift @ base])  # ∂(stencil)/∂w at the input
        du = (A @ du.T).T + local if mode == "wig" else local
        u = A @ base
        r = u - traj[k + 1]
        loss += np.mean(r**2) / m
        grad += (2 / (n * m)) * du @ r
    return loss, grad


@pytest.mark.parametrize("method", ["one", "nog", "wig"])
def test_modality_loss_and_gradient_match_a_numpy_adjoint(method):
    config = adv_config(method, m=4)
    setup = build(config)
    w = jnp.array([0.3, 0.5], jnp.float32)
    params = eqx.tree_at(lambda p: p.weight, setup.params, w.reshape(1, 1, 2))
    batch = jax.tree.map(lambda a: a[:3], setup.data["train"])
    stage = setup.stages[0].method
    system = setup.objective.unrolled(None, stage.teacher_forcing)
    loss, grads = jax.jit(lambda p: value_and_grad(system, p, system.initial_state(batch), stage.policy))(params)
    ref_loss, ref_grad = 0.0, np.zeros(2)
    for traj in np.asarray(batch["u"], np.float64)[:, :, 0]:
        l, g = numpy_loss_and_grad(np.array([0.3, 0.5]), traj, -0.75, 6, method)
        ref_loss, ref_grad = ref_loss + l / 3, ref_grad + g / 3
    assert float(loss) == pytest.approx(ref_loss, rel=1e-5)
    np.testing.assert_allclose(np.asarray(grads.weight).reshape(2), ref_grad, rtol=1e-4, atol=1e-7)


def hand_loop(problem, net_fn, batch, m, mode):
    """The three modalities as plain Python loops over steps with explicit stop_gradients."""
    u = batch["u"][:, 0]
    total = 0.0
    for k in range(m):
        if mode == "one":
            u = batch["u"][:, k]
        elif mode == "nog":
            u = jax.lax.stop_gradient(u)
        step = jax.vmap(lambda v, c, i: problem.step(net_fn, v, v, c, i)[0])
        u = step(u, batch["cond"], batch["index"])
        total = total + jnp.mean((u - batch["u"][:, k + 1]) ** 2) / m
    return total


def travelling_cosines(self, factors, n_per, frames, split_seed):
    """A stand-in for KS's exponax reference in ``_simulate``'s layout, ``(len(factors)·n_per,
    frames+1, 1, N)`` float32: four travelling cosine modes of amplitude < 1 (as the initial
    conditions), seeded per split. The modalities' equality with the hand-written loops holds
    for any trajectories; generating the real ones costs ~18 s of CPU in XLA compiles (the
    data's own tests: tests/test_time_stepper_data.py)."""
    rng = np.random.default_rng(split_seed)
    amp, phase, speed = (a[:, None, :, None] for a in rng.uniform(-1, 1, (3, len(factors) * n_per, 4)))
    k = np.arange(1, 5)[:, None]  # broadcast to (trajectory, frame, mode, point), summed over the modes
    x, t = np.arange(self.n) / self.n * 2 * np.pi, np.arange(frames + 1)[:, None, None]
    u = np.sum(amp * np.cos(k * x + 2 * np.pi * phase + speed * t), axis=2)
    return u[:, :, None].astype(np.float32)


# make test checks every modality in the prediction setup and WIG (the full adjoint) in the
# correction setup; ONE and NOG with the solver in the loop run in the slow tier.
@pytest.mark.parametrize(
    "setup_name,method",
    [
        ("prediction", "one"),
        ("prediction", "nog"),
        ("prediction", "wig"),
        ("correction", "wig"),
        pytest.param("correction", "one", marks=pytest.mark.slow),
        pytest.param("correction", "nog", marks=pytest.mark.slow),
    ],
)
@pytest.mark.costly("each case compiles a KS rollout's gradient and the hand-written loop's")
def test_modalities_on_ks_equal_hand_written_loops(setup_name, method, monkeypatch, tmp_path_factory):
    monkeypatch.setattr(KuramotoSivashinsky, "_simulate", travelling_cosines)
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path_factory.getbasetemp() / "stand-in-ks-cache"))
    settings = {"frames": 40, "warmup_frames": 20, "n_ics": 1, "n_test": 1, "long_horizon": 12, "width": 4,
                "blocks": 1, "dataset_fraction": 1.0, "setup": setup_name}  # fmt: skip
    setup = build(make_config("ks", method, budget=Budget(steps=1), settings=settings))
    problem, static = setup.problem, setup.static
    batch = jax.tree.map(lambda a: a[::37][:4], setup.data["train"])
    stage = setup.stages[0].method
    system = setup.objective.unrolled(None, stage.teacher_forcing)
    loss, grads = jax.jit(lambda p: value_and_grad(system, p, system.initial_state(batch), stage.policy))(setup.params)

    def reference(p):
        net = eqx.combine(p, static)
        return hand_loop(problem, lambda u, c: problem.apply(net, u, c), batch, problem.m, method)

    ref_loss, ref_grads = jax.jit(jax.value_and_grad(reference))(setup.params)
    assert float(loss) == pytest.approx(float(ref_loss), rel=1e-5)
    for a, b in zip(jax.tree.leaves(grads), jax.tree.leaves(ref_grads)):
        np.testing.assert_allclose(a, b, rtol=2e-4, atol=1e-7)


def numpy_conv_resnet(net, x, lift_activation):
    """List et al.'s KS ResNet forward in float64 NumPy: circular kernel-3 cross-correlations,
    LeakyReLU(0.01), residual blocks; the lifting convolution activated only when asked."""

    def conv(layer, h):
        w, b = np.asarray(layer.weight, np.float64), np.asarray(layer.bias, np.float64).reshape(-1)
        shifted = np.stack([np.roll(h, 1 - j, axis=-1) for j in range(w.shape[-1])], axis=-1)  # h[c, i + j - 1]
        return np.einsum("ocj,cij->oi", w, shifted) + b[:, None]

    def act(h):
        return np.where(h > 0, h, 0.01 * h)

    h = conv(net.conv_in, x)
    h = act(h) if lift_activation else h
    for first, second in net.blocks:
        h = act(h + conv(second, act(conv(first, h))))
    return conv(net.conv_out, h)


@pytest.mark.parametrize("lift_activation", [False, True])
def test_conv_resnet_matches_a_numpy_float64_forward(lift_activation):
    from physgrad.nets import ConvResNet

    net = ConvResNet(1, 2, 1, 5, 2, key=jax.random.key(3), lift_activation=lift_activation)
    x = np.random.default_rng(0).normal(size=(2, 12))
    np.testing.assert_allclose(
        net(jnp.asarray(x, jnp.float32)), numpy_conv_resnet(net, x, lift_activation), rtol=1e-4, atol=1e-5
    )
    assert physgrad.parameter_count(ConvResNet(1, 2, 1, 26, 8, key=jax.random.key(0))) == 33_125


def numpy_etd1_frame(u, size, dt=0.5, substeps=2):
    """The authors' ETD1 for u_t = −u_xx − u_xxxx − ½(u²)_x, L = 2π·size, in float64 NumPy."""
    n = u.shape[-1]
    k = 1j * np.fft.fftfreq(n, size / n)
    lin = -(k**2) - k**4
    e = np.exp(lin * dt)
    c1 = np.where(lin == 0, dt, (e - 1) / np.where(lin == 0, 1, lin))
    for _ in range(substeps):
        u = np.real(np.fft.ifft(e * np.fft.fft(u) - 0.5 * k * np.fft.fft(u**2) * c1))
    return u


def test_ks_correction_is_etd1_plus_the_substep_times_the_network():
    """u⁺ = ETD1(u) + Δt·f_θ(u, f) with the substep Δt = 0.5 (the authors' ``diff_ks.dt * net``)."""
    problem = KuramotoSivashinsky(composition=Parallel(scale=0.5))
    net = problem.make_network(jax.random.key(1))
    x = np.arange(48) / 48 * 2 * np.pi
    u = (np.cos(x) + 0.3 * np.sin(3 * x))[None]
    f, index = 1.1, 3  # the fourth training size
    out, ok = problem.step(lambda v, c: problem.apply(net, v, c), jnp.asarray(u, jnp.float32),
                           jnp.asarray(u, jnp.float32), jnp.float32(f), index)  # fmt: skip
    net_out = np.asarray(problem.apply(net, jnp.asarray(u, jnp.float32), jnp.float32(f)), np.float64)
    np.testing.assert_allclose(out, numpy_etd1_frame(u, 8 * f) + 0.5 * net_out, rtol=1e-4, atol=2e-5)
    assert bool(ok)


def test_one_nog_wig_differ_and_wig_truncate_m_equals_nog_plus_local():
    """With truncate=1 every state is cut, so WIG's gradient equals NOG's."""
    setup = build(adv_config("wig", m=4, **{"wig.truncate": 1}))
    nog = build(adv_config("nog", m=4)).stages[0].method
    batch = jax.tree.map(lambda a: a[:5], setup.data["train"])
    params = eqx.tree_at(lambda p: p.weight, setup.params, jnp.array([[[0.2, 0.6]]], jnp.float32))
    system = setup.objective.unrolled(None, False)
    s0 = system.initial_state(batch)

    @jax.jit  # one program for the three gradients (eagerly, each rollout's scans compile on their own)
    def gradients(p):
        policies = (setup.stages[0].method.policy, nog.policy, METHODS["wig"]().policy)
        return [value_and_grad(system, p, s0, policy)[1] for policy in policies]

    g_trunc, g_nog, g_full = gradients(params)
    np.testing.assert_allclose(g_trunc.weight, g_nog.weight, rtol=1e-5)
    assert not np.allclose(g_full.weight, g_nog.weight, rtol=1e-3)


# --- compositions and solver differentiability -------------------------------------------------


class Affine(Solver):
    def __call__(self, u, cond):
        return 2.0 * u + 1.0


@pytest.mark.parametrize(
    "composition, expected",
    [
        (Prediction(), lambda u, c: u**2 + c),
        (Residual(), lambda u, c: u + u**2 + c),
        (Parallel(scale=0.5), lambda u, c: 2 * u + 1 + 0.5 * (u**2 + c)),
        (Sequential(), lambda u, c: (2 * u + 1) ** 2 + c),
        (Bypass(scale=0.5), lambda u, c: 2 * u + 1 + 0.5 * ((2 * u + 1) ** 2 + c)),
    ],
)
def test_compositions_match_their_formulas(composition, expected):
    u = jnp.linspace(-1.0, 2.0, 7)[None]
    out, ok = composition(Affine(), lambda v, c: v**2 + c, u, u, 0.3)
    np.testing.assert_allclose(out, expected(u, 0.3), rtol=1e-6)
    assert bool(ok)


def test_nondifferentiable_solver_raises_only_when_differentiated():
    solver = NonDifferentiable(Affine())
    u = jnp.ones((1, 4))
    np.testing.assert_allclose(solver(u, 0.0), 3.0)
    with pytest.raises(NotDifferentiableError):
        jax.grad(lambda v: jnp.sum(solver(v, 0.0)))(u)


@pytest.mark.slow  # trains through the engine
def test_nondifferentiable_solver_trains_under_nog_and_one_and_is_refused_by_wig(tmp_path):
    for method in ("nog", "one"):
        opaque = train(adv_config(method, steps=30, differentiable_solver=False), tmp_path / method)
        clear = train(adv_config(method, steps=30), tmp_path / f"{method}-clear")
        assert opaque["status"] == "finished"
        assert opaque["final_test_loss"] == pytest.approx(clear["final_test_loss"], rel=1e-6)  # same gradients
    for method in ("wig", "adam", "bptt"):
        with pytest.raises(ConfigError, match="not differentiable"):
            build(adv_config(method, differentiable_solver=False))
    assert main(["train", "advection_1d", "--method", "wig", "--steps", "2", "--set", "differentiable_solver=false",
                 "--out", str(tmp_path / "cli")]) == 2  # fmt: skip


# --- stabilisers ------------------------------------------------------------------------------


def stepper(method_name, **hyper):
    """``one_step(batch_transform, state_transform)``: one update of the method from the
    initial parameters on four windows, the setup built and the step compiled once for all
    the calls (a test's cases differ in values, not shapes)."""
    setup = build(adv_config(method_name, **hyper))
    method = setup.stages[0].method
    step = jax.jit(lambda p, s, b: method.step(setup.objective, p, s, b))

    def one_step(batch_transform=None, state_transform=None):
        batch = jax.tree.map(lambda a: a[:4], setup.data["train"])
        if batch_transform:
            batch = batch_transform(batch)
        state = method.init(setup.params)
        if state_transform:
            state = state_transform(state)
        params, state, stats = step(setup.params, state, batch)
        return setup.params, params, state, stats

    return one_step


def one_step(method_name, batch_transform=None, state_transform=None, **hyper):
    return stepper(method_name, **hyper)(batch_transform, state_transform)


def test_nan_gradient_skips_the_update():
    poison = lambda b: {**b, "u": b["u"].at[0, 2, 0, 3].set(jnp.nan)}  # noqa: E731
    nog = stepper("nog")
    before, after, _, stats = nog(poison)
    assert float(stats["skipped"]) == 1.0 and float(stats["skip_nan"]) == 1.0
    np.testing.assert_array_equal(before.weight, after.weight)
    _, after, _, stats = nog()
    assert float(stats["skipped"]) == 0.0 and not np.array_equal(before.weight, after.weight)


def test_norm_guard_skips_an_outlier_and_tracks_the_running_bound():
    bound = lambda s: float(optax.tree_utils.tree_get(s, "bound"))  # noqa: E731  (norm_guard's state)
    set_bound = lambda c: lambda s: optax.tree_utils.tree_set(s, bound=jnp.asarray(c, jnp.float32))  # noqa: E731
    wig = stepper("wig", norm_guard=True)
    _, _, state, stats = wig()
    norm = float(stats["grad_norm"])
    assert bound(state) == pytest.approx(100 * norm, rel=1e-5)  # the first update sets c = 100‖g‖
    before, after, state, stats = wig(state_transform=set_bound(0.5 * norm))
    assert float(stats["skip_norm"]) == 1.0 and bound(state) == pytest.approx(0.5 * norm, rel=1e-6)
    np.testing.assert_array_equal(before.weight, after.weight)
    _, _, state, stats = wig(state_transform=set_bound(2.0 * norm))
    assert float(stats["skipped"]) == 0.0
    assert bound(state) == pytest.approx(0.9 * 2.0 * norm + 10 * norm, rel=1e-5)


class Failing(Solver):
    def __call__(self, u, cond):
        return u

    def step(self, u, cond):
        return u, jnp.asarray(False)


def test_solver_failure_skips_the_update(monkeypatch):
    monkeypatch.setattr(Advection1d, "solvers", lambda self: Failing())
    before, after, _, stats = one_step("nog")
    assert float(stats["skip_solver"]) == 1.0
    np.testing.assert_array_equal(before.weight, after.weight)
    _, after, _, stats = one_step("nog", skip_solver_failure=False)
    assert float(stats["skipped"]) == 0.0 and not np.array_equal(before.weight, after.weight)


def test_learning_rate_warmup_and_decay_schedule():
    method = METHODS["nog"](lr=1e-2, lr_warmup=4, decay=0.5, decay_every=10)
    params = {"w": jnp.zeros(())}
    state = method.optimizer.init(params)
    sizes = []
    for _ in range(12):  # Adam's first steps move by ≈ lr · sign(g)
        updates, state = method.optimizer.update({"w": jnp.ones(())}, state, params)
        sizes.append(-float(updates["w"]))
    np.testing.assert_allclose(sizes[:4], [2.5e-3, 5e-3, 7.5e-3, 1e-2], rtol=1e-3)
    np.testing.assert_allclose(sizes[9], 1e-2, rtol=1e-3)
    np.testing.assert_allclose(sizes[10:], 5e-3, rtol=1e-3)


@pytest.mark.costly("the fast tier's one curriculum run: three stages, each its own compiled step")
def test_curriculum_expands_into_stages_with_their_rollout_and_learning_rate(tmp_path):
    config = adv_config("wig", steps=40, m=4, curriculum="1,2,4", stage_epochs=1.0, stage_lr="1e-2,1e-3,1e-4",
                        batch_size=4)  # fmt: skip
    setup = build(config)
    per_epoch = setup.stages[0].steps_per_epoch
    assert per_epoch == 4 * 13 // 4  # 4 trajectories x 13 windows of 5 frames, batch 4
    assert [(s.method.m, s.method.lr) for s in setup.stages] == [(1, 1e-2), (2, 1e-3), (4, 1e-4)]
    assert [s.steps for s in setup.stages] == [per_epoch, per_epoch, None]
    summary = train(config, tmp_path / "run")
    assert summary["stage_steps"] == {"0:wig[m=1]": 13, "1:wig[m=2]": 13, "2:wig[m=4]": 14}
    with pytest.raises(ConfigError, match="does not fit"):
        build(adv_config("wig", m=4, curriculum="1,8"))
    with pytest.raises(ConfigError, match="stage_lr"):
        adv_config("wig", curriculum="1,2", stage_lr="1e-3")
    # '/' separates too (compare sweeps on commas)
    slashed = build(adv_config("wig", steps=40, m=4, curriculum="1/2/4", stage_lr="1e-2/1e-3/1e-4", batch_size=4))
    assert [(s.method.m, s.method.lr) for s in slashed.stages] == [(1, 1e-2), (2, 1e-3), (4, 1e-4)]


def test_nondifferentiable_wrapper_keeps_the_solver_failure_flag():
    u_next, ok = NonDifferentiable(Failing()).step(jnp.ones((1, 4)), 0.0)
    assert not bool(ok)


@pytest.mark.slow  # trains through the engine
def test_prdp_rebuild_trains_with_the_new_iteration_count(tmp_path):
    """After a refinement the compiled step uses the new K: its loss equals a fresh setup's at K."""

    config = adv_config("wig", setup="correction", iterations=10)
    low, high = build(config, {"iterations": 1}), build(config, {"iterations": 10})
    refined = low.with_problem(dataclasses.replace(low.problem, iterations=4))
    reference = build(config, {"iterations": 4})
    args = lambda s: (s.params, s.method.init(s.params), s.data["train"], jnp.arange(52, dtype=jnp.int32), jnp.int32(0))  # noqa: E731
    loss = lambda s: float(make_step(s, 32)(*args(s))[2]["loss"])  # noqa: E731
    assert loss(refined) == pytest.approx(loss(reference), rel=1e-6)
    assert loss(refined) != pytest.approx(loss(low), rel=1e-3) and loss(refined) != pytest.approx(loss(high), rel=1e-3)
    with pytest.raises(ConfigError, match="setup=correction"):
        train(adv_config("wig", setup="prediction", prdp=True), tmp_path / "p")
