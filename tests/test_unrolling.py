"""Neural time-steppers: modalities against hand-written loops and a NumPy float64 adjoint,
compositions against their formulas, solver differentiability, stabilisers, the problems'
solvers and data, PRDP and paired statistics."""

import dataclasses
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import physgrad  # noqa: F401
from physgrad.engine import Placement, Steps, TrainSettings, grouped_order, prdp
from physgrad.harness.cli import main
from physgrad.harness.config import Budget, ConfigError, make_config
from physgrad.harness.objects import make_problem
from physgrad.harness.registry import METHODS, PROBLEMS
from physgrad.harness.train import build, make_step, settings_of, train
from physgrad.problems import Advection1d, Kolmogorov, KuramotoSivashinsky
from physgrad.problems.advection_1d import ImplicitUpwind, fou_distance
from physgrad.problems.ks import ks_stepper
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
from physgrad.problems.time_stepper import windows
from physgrad.rollout import value_and_grad


@pytest.fixture(autouse=True)
def data_cache(tmp_path_factory, monkeypatch):
    """Generated datasets go to a per-session directory, not the user's cache."""
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path_factory.getbasetemp() / "physgrad-cache"))


SMALL_ADV = {"n_train": 4, "n_test": 3, "horizon": 16, "iterations": 6}


def adv_config(method, steps=5, **settings):
    return make_config("advection_1d", method, budget=Budget(steps=steps), settings={**SMALL_ADV, **settings})


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
@pytest.mark.costly(
    "each case compiles a KS rollout's gradient and the hand-written loop's; the first also "
    "generates the module's KS data (exponax)"
)
def test_modalities_on_ks_equal_hand_written_loops(setup_name, method):
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
    _, g_trunc = value_and_grad(system, params, s0, setup.stages[0].method.policy)
    _, g_nog = value_and_grad(system, params, s0, nog.policy)
    _, g_full = value_and_grad(system, params, s0, METHODS["wig"]().policy)
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


def one_step(method_name, batch_transform=None, state_transform=None, **hyper):
    setup = build(adv_config(method_name, **hyper))
    method = setup.stages[0].method
    batch = jax.tree.map(lambda a: a[:4], setup.data["train"])
    if batch_transform:
        batch = batch_transform(batch)
    state = method.init(setup.params)
    if state_transform:
        state = state_transform(state)
    params, state, stats = jax.jit(lambda p, s, b: method.step(setup.objective, p, s, b))(setup.params, state, batch)
    return setup.params, params, state, stats


def test_nan_gradient_skips_the_update():
    poison = lambda b: {**b, "u": b["u"].at[0, 2, 0, 3].set(jnp.nan)}  # noqa: E731
    before, after, _, stats = one_step("nog", poison)
    assert float(stats["skipped"]) == 1.0 and float(stats["skip_nan"]) == 1.0
    np.testing.assert_array_equal(before.weight, after.weight)
    _, after, _, stats = one_step("nog")
    assert float(stats["skipped"]) == 0.0 and not np.array_equal(before.weight, after.weight)


def test_norm_guard_skips_an_outlier_and_tracks_the_running_bound():
    bound = lambda s: float(optax.tree_utils.tree_get(s, "bound"))  # noqa: E731  (norm_guard's state)
    set_bound = lambda c: lambda s: optax.tree_utils.tree_set(s, bound=jnp.asarray(c, jnp.float32))  # noqa: E731
    _, _, state, stats = one_step("wig", norm_guard=True)
    norm = float(stats["grad_norm"])
    assert bound(state) == pytest.approx(100 * norm, rel=1e-5)  # the first update sets c = 100‖g‖
    before, after, state, stats = one_step("wig", state_transform=set_bound(0.5 * norm), norm_guard=True)
    assert float(stats["skip_norm"]) == 1.0 and bound(state) == pytest.approx(0.5 * norm, rel=1e-6)
    np.testing.assert_array_equal(before.weight, after.weight)
    _, _, state, stats = one_step("wig", state_transform=set_bound(2.0 * norm), norm_guard=True)
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


# --- batches: a fresh permutation every epoch, KS one domain size per batch ------------------

SMALL_KS = {"frames": 50, "n_ics": 1, "dataset_fraction": 1.0}  # 51 frames: 48 windows of 4 per domain size
TIME_STEPPERS = ("ks", "kolmogorov", "advection_1d")


def stand_in_setup(config, train):
    """What :class:`Steps` reads of a setup (problem, training split, stages), without the
    network and solvers that ``build`` makes."""
    from types import SimpleNamespace

    problem = make_problem(PROBLEMS[config.problem], config.problem_settings)
    return SimpleNamespace(
        problem=problem, data={"train": train}, stages=[SimpleNamespace(batch_size=p.batch_size) for p in config.phases]
    )


def epoch_orders(setup, config, epochs=1, seed=0, **settings):
    """The engine's sample order of the first ``epochs`` epochs (``settings`` replace the config's)."""
    steps = Steps(setup, Placement(), dataclasses.replace(settings_of(config), **settings), seed)
    return [np.asarray(steps.order(0, e)) for e in range(epochs)]


def batches_of(order, batch_size):
    return order[: len(order) // batch_size * batch_size].reshape(-1, batch_size)


def test_time_steppers_shuffle_by_default_and_the_other_problems_keep_their_papers_fixed_order():
    for name in PROBLEMS:
        expected = name in TIME_STEPPERS
        assert PROBLEMS[name].default_shuffle is expected, name
    for name in TIME_STEPPERS:
        assert make_config(name, "one", budget=Budget(steps=1)).shuffle is True
        assert make_config(name, "one", budget=Budget(steps=1), settings={"shuffle": "false"}).shuffle is False
    assert make_config("oscillators", "hig", budget=Budget(steps=1)).shuffle is False


@pytest.fixture(scope="module")
def advection():
    """The small advection problem's config and training windows (4 trajectories x 12
    windows, as stored), without running the reference solver."""

    def trajectories(self, split):
        zeros = np.zeros(self.n_train, np.float32)
        return {"u": np.zeros((self.n_train, 17, 1, 30), np.float32), "cond": zeros, "index": zeros.astype(np.int32)}

    config = adv_config("nog", batch_size=8)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Advection1d, "trajectories", trajectories)
        return config, make_problem(PROBLEMS["advection_1d"], config.problem_settings).make_data(jax.random.key(0))[
            "train"
        ]


def test_a_time_stepper_batch_is_not_consecutive_windows_of_one_trajectory(advection):
    config, train = advection
    setup = stand_in_setup(config, train)
    (order,) = epoch_orders(setup, config)
    per_trajectory = train["u"].shape[0] // SMALL_ADV["n_train"]
    assert per_trajectory == 12

    def consecutive_in_one_trajectory(batch):
        rows = np.sort(batch)
        return rows[-1] - rows[0] == len(rows) - 1 and rows[0] // per_trajectory == rows[-1] // per_trajectory

    batches = batches_of(order, 8)
    assert len(batches) == 6 and not any(consecutive_in_one_trajectory(b) for b in batches)
    assert all(len(set(b // per_trajectory)) > 1 for b in batches)  # the trajectories mix within a batch
    # shuffle=false: the stored order, 4 of the 6 batches one trajectory's consecutive windows
    (fixed,) = epoch_orders(setup, config, shuffle=False)
    np.testing.assert_array_equal(fixed, np.arange(48))
    assert sum(consecutive_in_one_trajectory(b) for b in batches_of(fixed, 8)) == 4
    # the library's TrainSettings() (shuffle None) takes the problem's default
    library = Steps(setup, Placement(), TrainSettings(), 0)
    np.testing.assert_array_equal(np.asarray(library.order(0, 0)), order)


def test_orders_differ_between_epochs_are_reproducible_per_seed_and_see_every_sample_once(advection):
    config, train = advection
    setup = stand_in_setup(config, train)
    orders, again = epoch_orders(setup, config, epochs=3), epoch_orders(setup, config, epochs=3)
    other = epoch_orders(setup, config, epochs=3, seed=1)
    for order in orders:
        np.testing.assert_array_equal(np.sort(order), np.arange(48))
    assert not np.array_equal(orders[0], orders[1]) and not np.array_equal(orders[1], orders[2])
    for a, b in zip(orders, again):
        np.testing.assert_array_equal(a, b)
    assert all(not np.array_equal(a, b) for a, b in zip(orders, other))


def test_ks_batches_hold_one_domain_size_each_with_the_sizes_interleaved_at_random(monkeypatch):
    from physgrad.problems.ks import TRAIN_FACTORS

    def trajectories(self, split):  # the stored layout (size by size), without running the solver
        frames = 51 if split == "train" else 13
        index = np.repeat(np.arange(6), self.n_ics).astype(np.int32)
        return {"u": np.zeros((6 * self.n_ics, frames, 1, 48), np.float32), "index": index,
                "cond": np.asarray(TRAIN_FACTORS, np.float32)[index]}  # fmt: skip

    monkeypatch.setattr(KuramotoSivashinsky, "trajectories", trajectories)
    config = make_config("ks", "nog", budget=Budget(steps=1), settings=SMALL_KS)
    train = make_problem(PROBLEMS["ks"], config.problem_settings).make_data(jax.random.key(0))["train"]
    setup = stand_in_setup(config, train)
    size = np.asarray(train["index"])  # the domain size of every window
    assert np.bincount(size).tolist() == [48] * 6
    labels = []
    orders = epoch_orders(setup, config, epochs=2)
    for order in orders:
        np.testing.assert_array_equal(np.sort(order), np.arange(6 * 48))  # every window once per epoch
        batches = batches_of(order, 16)
        assert len(batches) == 18
        assert all(len(set(size[b])) == 1 for b in batches)  # one domain size per batch
        labels.append([int(size[b[0]]) for b in batches])
        assert sorted(labels[-1]) == sorted(list(range(6)) * 3)  # every size's 3 batches
        # interleaved: not the sizes one after another (5 changes of size), far more changes
        assert sum(a != b for a, b in zip(labels[-1], labels[-1][1:])) > 8
    assert labels[0] != labels[1] and not np.array_equal(orders[0], orders[1])
    np.testing.assert_array_equal(orders[0], epoch_orders(setup, config)[0])  # reproducible
    # another stage's batch size (48) is cut within the sizes too
    wide = stand_in_setup(config, train)
    wide.stages[0].batch_size = 48
    (order,) = epoch_orders(wide, config)
    assert all(len(set(size[b])) == 1 for b in batches_of(order, 48)) and len(batches_of(order, 48)) == 6
    # fixed order (shuffle=false): size by size, as stored
    (fixed,) = epoch_orders(setup, config, shuffle=False)
    np.testing.assert_array_equal(fixed, np.arange(6 * 48))


def test_grouped_order_cuts_full_batches_per_group_and_puts_the_remainders_last():
    groups = np.repeat([2, 0, 1], [10, 7, 5])  # batch 4: 2 + 1 + 1 full batches, remainders 2 + 3 + 1
    order = grouped_order(groups, 4, np.random.default_rng(0))
    np.testing.assert_array_equal(np.sort(order), np.arange(22))
    full = order[:16].reshape(4, 4)
    assert all(len(set(groups[b])) == 1 for b in full)
    assert sorted(int(groups[b[0]]) for b in full) == [0, 1, 2, 2]
    again = grouped_order(groups, 4, np.random.default_rng(0))
    np.testing.assert_array_equal(order, again)
    assert not np.array_equal(order, grouped_order(groups, 4, np.random.default_rng(1)))


# --- problems: solvers and data --------------------------------------------------------------


def test_ks_reference_converges_at_second_order_and_conserves_the_mean():
    x = np.arange(48) / 48 * 2 * np.pi
    u0 = jnp.asarray((np.cos(x) + 0.5 * np.sin(2 * x) + 0.2 * np.cos(3 * x))[None])

    def run(dt, order=2, t_end=4.0):
        stepper, u = ks_stepper(1.0, 48, dt, order), u0
        for _ in range(int(round(t_end / dt))):
            u = stepper(u)
        return np.asarray(u)

    exact = run(0.5 / 64)
    errors = [np.max(np.abs(run(dt) - exact)) for dt in (0.5, 0.25, 0.125)]
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 1.8), orders
    first = [np.max(np.abs(run(dt, order=1) - exact)) for dt in (0.25, 0.125)]
    assert 0.8 < np.log2(first[0] / first[1]) < 1.3  # the coarse ETD1 is first order
    u = u0
    stepper = ks_stepper(1.0, 48, 0.5, 2)
    for _ in range(100):
        u = stepper(u)
    assert abs(float(jnp.mean(u)) - float(jnp.mean(u0))) < 1e-12


def test_windows_are_the_overlapping_slices():
    u = np.arange(2 * 6 * 3).reshape(2, 6, 3)
    w = windows(u, 2)
    assert w.shape == (8, 3, 3)
    expected = [u[s, t : t + 3] for s in range(2) for t in range(4)]
    np.testing.assert_array_equal(w, np.stack(expected))


def test_data_generation_is_deterministic_per_seed_and_cached(tmp_path, monkeypatch):
    settings = dict(frames=20, warmup_frames=10, n_ics=1, n_test=1, long_horizon=12, dataset_fraction=1.0)
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "a"))
    a = KuramotoSivashinsky(**settings).generate("train")
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path / "b"))
    cached = KuramotoSivashinsky(**settings).trajectories("train")
    again = KuramotoSivashinsky(**settings).trajectories("train")  # from the cache file
    other = KuramotoSivashinsky(**settings, data_seed=1).generate("train")
    for key in a:
        np.testing.assert_array_equal(a[key], cached[key])
        np.testing.assert_array_equal(a[key], again[key])
    assert not np.allclose(a["u"], other["u"])
    assert len(list((tmp_path / "b").glob("ks-train-*.npz"))) == 1
    assert a["u"].shape == (6, 21, 1, 48) and a["u"].dtype == np.float32
    np.testing.assert_allclose(np.mean(a["u"], axis=-1), np.mean(a["u"][:, :1], axis=-1).repeat(21, 1), atol=1e-5)


@pytest.mark.slow  # two exponax solvers at two resolutions: most of a minute to build
def test_kolmogorov_reference_is_finer_and_the_coarse_solver_is_close_but_not_exact():
    problem = Kolmogorov(n=16, refinement=2, forcing_mode=4, frames=6, warmup_frames=10, n_test=1, long_horizon=12)
    data = problem.trajectories("train")
    assert data["u"].shape == (6, 7, 1, 16, 16)
    np.testing.assert_allclose(data["cond"], [0.3, 0.4, 0.5, 0.7, 0.8, 0.9], rtol=1e-6)
    u = jnp.asarray(data["u"])
    step = jax.vmap(lambda v, i: problem.step(lambda w, c: jnp.zeros_like(w), v, v, 0.0, i)[0])
    coarse = step(u[:, 0], jnp.asarray(data["index"]))
    rel = float(jnp.linalg.norm(coarse - u[:, 1]) / jnp.linalg.norm(u[:, 1] - u[:, 0]))
    assert 1e-3 < rel < 1.0  # a visible but bounded under-resolution error per step


def test_implicit_upwind_converges_to_the_direct_solve():
    u = jnp.asarray(np.random.default_rng(0).normal(size=(1, 30)))
    a = 0.75
    matrix = (1 + a) * np.eye(30) - a * np.roll(np.eye(30), 1, axis=1)  # row i: (1+a)u_i − a u_{i+1}
    exact = np.linalg.solve(matrix, np.asarray(u[0]))
    errors = [np.max(np.abs(np.asarray(ImplicitUpwind(-0.75, k)(u, 0.0))[0] - exact)) for k in (5, 10, 40)]
    assert errors[0] > errors[1] > errors[2] and errors[2] < 1e-9
    assert errors[1] / errors[0] == pytest.approx((a / (1 + a)) ** 5, rel=0.5)


def test_advection_reference_is_an_exact_shift_and_the_fou_metric():
    problem = Advection1d(n_train=2, n_test=1, horizon=4)
    u = problem.trajectories("train")["u"][:, :, 0].astype(np.float64)
    k = np.fft.rfftfreq(30) * 30 * 2 * np.pi
    shifted = np.fft.irfft(np.fft.rfft(u[:, 0]) * np.exp(-1j * k * (-0.75 / 30)), n=30)
    np.testing.assert_allclose(u[:, 1], shifted, atol=1e-5)
    conv = problem.make_network(jax.random.key(0))
    conv = eqx.tree_at(lambda c: c.weight, conv, jnp.array([[[0.25, 0.75]]], jnp.float32))
    assert fou_distance(conv) == pytest.approx(0.0, abs=1e-7)
    out = conv(jnp.asarray(u[:1, 0], jnp.float32))
    np.testing.assert_allclose(out[0], 0.25 * u[0, 0] + 0.75 * np.roll(u[0, 0], -1), rtol=1e-5, atol=1e-6)


def test_metrics_rel_error_and_decorrelation_on_known_rollouts():
    problem = Advection1d(n_train=2, n_test=1, horizon=20, eval_horizon=12)
    ref = jnp.asarray(np.random.default_rng(1).normal(size=(21, 1, 30)), jnp.float32)
    sample = {"u": ref}
    perfect = problem.metrics(None, ref[1:], sample)
    assert float(perfect["rel_error"]) == 0.0 and float(perfect["corr_time"]) == 20.0
    noisy = ref[1:] + 0.1
    expected = 0.01 / float(jnp.max(ref[1:13] ** 2))
    assert float(problem.metrics(None, noisy, sample)["rel_error"]) == pytest.approx(expected, rel=1e-4)
    flipped = ref[1:].at[5:].multiply(-1.0)
    assert float(problem.metrics(None, flipped, sample)["corr_time"]) == 5.0


# --- PRDP ---------------------------------------------------------------------------------------


def test_prdp_controller_refines_on_plateaus_and_stops_when_refining_stops_helping():
    def feed(state, errors, start=0):
        for step, error in enumerate(errors, start=start):
            state = prdp.update(state, error, step, increment=2, maximum=9)
        return state

    state = feed(prdp.initial_state(1), [1.0] * 3)
    assert state["K"] == 1  # too few checks for a plateau test (EMA now vs 3 checks ago)
    state = feed(state, [1.0], start=3)
    assert state["K"] == 3 and state["refinements"] == [[3, 3]]  # first plateau: refine (E_ref = 100)
    state = feed(state, [0.5] * 3, start=4)
    assert state["K"] == 3 and not state["stopped"]  # improving: no plateau
    state = feed(state, [0.5] * 30, start=7)
    # the error plateaued 50 % below the last refinement: refine; the next plateau, no better: stop
    assert state["K"] == 5 and len(state["refinements"]) == 2 and state["stopped"]
    state = feed(state, [0.1] * 30, start=37)
    assert state["K"] == 5  # stopped for good
    assert feed(prdp.initial_state(8), [1.0] * 10)["K"] == 9  # capped at full fidelity


@pytest.mark.slow  # trains through the engine
def test_prdp_training_raises_the_iteration_count_and_counts_iterations(tmp_path):
    config = adv_config("wig", steps=300, setup="correction", prdp=True, eval_every=10, iterations=10)
    summary = train(config, tmp_path / "prdp")
    assert summary["prdp"]["K"] > 1 and summary["prdp"]["refinements"]
    assert summary["solver_iterations"] < 10 * 300
    fixed = train(adv_config("wig", steps=30, setup="correction", iterations=10), tmp_path / "fixed")
    assert fixed["solver_iterations"] == 10 * 30 and fixed["prdp"] is None
    with pytest.raises(ConfigError, match="prdp needs"):
        train(make_config("ks", "nog", budget=Budget(steps=1), settings={"prdp": True}), tmp_path / "bad")


# --- command line and statistics ------------------------------------------------------------


@pytest.mark.slow
def test_compare_sweeps_setups_and_reports_paired_tests(tmp_path, capsys):
    out = tmp_path / "study"
    args = ["compare", "advection_1d", "--methods", "one,nog,wig", "--steps", "20", "--seeds", "2", "--quiet",
            "--out", str(out), "--set", "setup=prediction,correction"]  # fmt: skip
    args += [f"--set={k}={v}" for k, v in SMALL_ADV.items()]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "Wilcoxon" in text and "one vs nog" in text
    rows = list(csv_rows(out / "setupcorrection" / "paired_tests.csv"))
    assert {(r["method_a"], r["method_b"]) for r in rows} == {("one", "nog"), ("one", "wig"), ("nog", "wig")}
    assert all(int(r["pairs"]) == 2 * 3 for r in rows)  # 2 seeds x 3 test cases


def csv_rows(path):
    import csv

    with open(path) as f:
        yield from csv.DictReader(f)


def test_paired_tests_pair_by_seed(tmp_path):
    from physgrad.harness.stats import paired_tests, seed_means

    rows = ["problem,method,seed,run_dir"]
    for method, offset in (("a", 0.0), ("b", 1.0)):
        for seed in (0, 1):
            run = tmp_path / f"runs/{method}{seed}"
            run.mkdir(parents=True)
            values = [seed + i + offset for i in range(3)]
            (run / "test_cases.json").write_text(json.dumps({"rel_error": values, "loss": values}))
            rows.append(f"p,{method},{seed},runs/{method}{seed}")
    (tmp_path / "summary.csv").write_text("\n".join(rows) + "\n")
    (test,) = paired_tests(tmp_path)
    assert test["pairs"] == 6 and test["a_lower"] == 1.0
    # paired by seed: 2 seeds, both lower; no p-value (2 seeds cannot go below 2/2^2 = 0.5),
    # the ratio is the median of the per-seed ratios of the means over the cases (1/2, 2/3)
    assert test["seeds"] == 2 and test["seeds_a_lower"] == 2 and math.isnan(test["p_value"])
    assert test["ratio"] == pytest.approx(math.sqrt(1 / 2 * 2 / 3))  # two seeds: the median of the log-ratios
    means = seed_means(tmp_path)
    assert means["a"][0] == pytest.approx(1.5) and means["a"][1] == pytest.approx(math.sqrt(0.5))


def test_problem_and_setting_errors_are_one_line(capsys, tmp_path):
    assert (
        main(["train", "ks", "--method", "wig", "--steps", "1", "--set", "setup=bogus", "--out", str(tmp_path / "x")])
        == 2
    )
    assert "valid choices: prediction, correction" in capsys.readouterr().err
    assert main(["train", "ks", "--method", "wig", "--steps", "1", "--set", "composition=bypass", "--set",
                 "setup=prediction", "--out", str(tmp_path / "y")]) == 2  # fmt: skip
    assert "valid choices: full, residual" in capsys.readouterr().err


def test_cache_key_follows_the_settings_that_shape_the_splits(tmp_path, monkeypatch):
    monkeypatch.setenv("PHYSGRAD_CACHE", str(tmp_path))
    short = Advection1d(**SMALL_ADV, eval_horizon=5).trajectories("val")
    longer = Advection1d(**SMALL_ADV, eval_horizon=8).trajectories("val")
    assert short["u"].shape[1] == 6 and longer["u"].shape[1] == 9
    Advection1d(**{**SMALL_ADV, "iterations": 3}, composition=Prediction(), eval_horizon=5).trajectories(
        "val"
    )  # cached
    assert len(list(tmp_path.glob("advection_1d-val-*.npz"))) == 2


def test_nondifferentiable_wrapper_keeps_the_solver_failure_flag():
    u_next, ok = NonDifferentiable(Failing()).step(jnp.ones((1, 4)), 0.0)
    assert not bool(ok)


@pytest.mark.slow  # trains through the engine
def test_prdp_rebuild_trains_with_the_new_iteration_count(tmp_path):
    """After a refinement the compiled step uses the new K: its loss equals a fresh setup's at K."""
    import dataclasses

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


def test_too_short_trajectories_are_a_one_line_error(capsys, tmp_path):
    assert main(["train", "advection_1d", "--method", "nog", "--steps", "1", "--set", "horizon=3",
                 "--out", str(tmp_path / "x")]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert "too short for m = 5" in err and "\n" not in err


@pytest.mark.parametrize(
    "make",
    [
        pytest.param(lambda z: Kolmogorov(n=16, forcing_mode=4, zero_init=z), marks=pytest.mark.slow),
        lambda z: Advection1d(zero_init=z),
    ],
)
def test_zero_init_starts_the_corrector_at_the_bare_solver(make):
    """zero_init zeroes the output layer (weights and bias): the corrected step is the solver's;
    without it the paper's initialisation changes the step."""
    shape = (1, 16, 16) if isinstance(make(False), Kolmogorov) else (1, 30)
    u = jax.random.normal(jax.random.key(1), shape, jnp.float32)
    cond = jnp.float32(0.3)

    def step(problem, network_fn):
        return problem.step(network_fn, u, u, cond, 0)[0]

    bare = step(make(False), lambda v, c: jnp.zeros_like(v))
    for zero in (True, False):
        problem = make(zero)
        net = problem.initial_network(jax.random.key(0), {})
        out = step(problem, lambda v, c: problem.apply(net, v, c))
        assert np.allclose(out, bare, atol=1e-6) == zero
