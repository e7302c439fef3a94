"""Neural time-steppers' data: batches (a fresh permutation every epoch, KS one domain size
per batch), the problems' reference solvers and generated data against NumPy and their
convergence orders, PRDP's controller, paired statistics and one-line errors."""

import dataclasses
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import physgrad  # noqa: F401
from physgrad.engine import Placement, Steps, TrainSettings, grouped_order, prdp
from physgrad.harness.cli import main
from physgrad.harness.config import Budget, ConfigError, make_config
from physgrad.harness.objects import make_problem
from physgrad.harness.registry import PROBLEMS
from physgrad.harness.train import settings_of, train
from physgrad.problems import Advection1d, Kolmogorov, KuramotoSivashinsky
from physgrad.problems.advection_1d import ImplicitUpwind, fou_distance
from physgrad.problems.ks import ks_stepper
from physgrad.problems.sim.steppers import Prediction
from physgrad.problems.time_stepper import windows
from small_advection import SMALL_ADV, adv_config, data_cache  # noqa: F401 — data_cache: an autouse fixture

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


@pytest.mark.unchecked("a stand-in setup (problem, data, batch sizes): the sample order reads nothing else")
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


@pytest.mark.unchecked("a stand-in setup (problem, data, batch sizes): the sample order reads nothing else")
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


@pytest.mark.unchecked("a stand-in setup (problem, data, batch sizes): the sample order reads nothing else")
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


@pytest.mark.costly("the fast tier's one generation of KS data through exponax: two seeds, six domain sizes each")
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


@pytest.mark.slow  # trains through the engine
def test_prdp_on_a_tuning_trial_reads_the_val_split_it_evaluates_as_test(tmp_path):
    """A tuning trial (split=HoldOut) of a problem with a val split evaluates that split as
    its test, once, and PRDP reads it as the run's val (the older Validation wrapper dropped
    the val split, and PRDP then failed on the first evaluation)."""
    from physgrad.engine import HoldOut

    config = adv_config("wig", steps=12, setup="correction", prdp=True, eval_every=2, iterations=10)
    summary = train(config, tmp_path / "trial", split=HoldOut(0.2))
    assert summary["status"] == "finished" and summary["prdp"]["K"] >= 1
    rows = list(csv_rows(tmp_path / "trial" / "metrics.csv"))
    test = {(r["step"], r["metric"]): r["value"] for r in rows if r["split"] == "test"}
    assert test and test == {(r["step"], r["metric"]): r["value"] for r in rows if r["split"] == "val"}


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
