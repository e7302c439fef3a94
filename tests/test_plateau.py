"""The unrolling methods' reduce-on-plateau schedule (issue 54): against a hand-written copy of
PyTorch's ReduceLROnPlateau, off by default (the steps and run names of before), and its
settings from the command line."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from physgrad.harness.config import ConfigError
from physgrad.harness.registry import METHODS
from physgrad.harness.train import build, train
from physgrad.methods.base import with_extra_args
from physgrad.methods.unrolling import Plateau, schedule
from small_advection import adv_config, data_cache  # noqa: F401 — data_cache: an autouse fixture


def torch_reduce_on_plateau(epoch_losses, lr, factor, patience, cooldown, threshold=1e-4):
    """The learning rate after each epoch: ``torch.optim.lr_scheduler.ReduceLROnPlateau.step``
    (mode min, threshold_mode rel, eps ignored) written out by hand."""
    best, bad, cooldown_left, out = float("inf"), 0, 0, []
    for current in epoch_losses:
        if current < best * (1 - threshold):
            best, bad = current, 0
        else:
            bad += 1
        if cooldown_left > 0:
            cooldown_left -= 1
            bad = 0
        if bad > patience:
            lr *= factor
            cooldown_left, bad = cooldown, 0
        out.append(lr)
    return out


# epoch means: two improvements, a plateau (cut after the third bad epoch), a cooldown epoch,
# another plateau (cut again), an improvement
EPOCH_MEANS = [1.0, 0.9, 0.8, 0.8, 0.8, 0.8, 0.8, 0.8, 0.8, 0.8, 0.7, 0.7]


def test_plateau_schedule_equals_pytorch_reduce_on_plateau():
    every, lr = 4, 1e-2
    method = METHODS["nog"](lr=lr, plateau_factor=0.5, plateau_patience=2, plateau_cooldown=1, plateau_every=every)
    assert method.plateau == Plateau(every, 0.5, 2, 1)
    reference = torch_reduce_on_plateau(EPOCH_MEANS, lr, 0.5, 2, 1)
    # the lr it must produce: 1e-2 through the first plateau's two bad epochs, halved after the third
    # (epoch 5), held through the cooldown, halved again after epoch 9
    assert reference[4] == 1e-2 and reference[5] == 5e-3 and reference[8] == 5e-3 and reference[9] == 2.5e-3
    optimizer = with_extra_args(method.optimizer)
    params = {"w": jnp.zeros(())}
    state = optimizer.init(params)
    update = jax.jit(lambda s, v: optimizer.update({"w": jnp.ones(())}, s, params, value=v))
    rng = np.random.default_rng(0)
    rates = []
    for mean in EPOCH_MEANS:  # batch losses scattered around the epoch's mean
        spread = rng.uniform(-0.05, 0.05, every)
        for value in mean + spread - spread.mean():
            updates, state = update(state, jnp.float32(value))
            rates.append(-float(updates["w"]))  # Adam on a constant gradient moves by lr exactly
    # optax applies a decision from the update that completes the epoch, PyTorch from the next one
    expected = [lr] + [reference[(i + 1) // every - 1] if (i + 1) >= every else lr for i in range(1, len(rates))]
    np.testing.assert_allclose(rates, expected, rtol=1e-6)
    assert float(state[-1].scale) == pytest.approx(0.25)


def test_plateau_composes_with_the_decay_schedule_and_starts_afresh_per_stage():
    method = METHODS["wig"](lr=1e-2, decay=0.5, decay_every=3, plateau_factor=0.1, plateau_patience=0,
                            plateau_every=2, curriculum="1,2")  # fmt: skip
    stages = method.stages()
    assert all(stage.plateau == Plateau(2, 0.1, 0) for stage, _ in stages)
    optimizer = with_extra_args(stages[0][0].optimizer)
    params = {"w": jnp.zeros(())}
    state, rates = optimizer.init(params), []
    for _ in range(6):  # a constant loss: no improvement after the first decision, patience 0
        updates, state = optimizer.update({"w": jnp.ones(())}, state, params, value=jnp.float32(1.0))
        rates.append(-float(updates["w"]))
    decay = [schedule(1e-2, 0, 0.5, 3)(t) for t in range(6)]
    np.testing.assert_allclose(rates, np.asarray(decay) * [1, 1, 1, 0.1, 0.1, 0.01], rtol=1e-6)


def old_optimizer(method):
    """Unrolled's chain as it was before the plateau schedule (commit d7ed7d9)."""
    chain = [optax.clip_by_global_norm(method.clip)] if method.clip > 0 else []
    return optax.chain(*chain, optax.adam(schedule(method.lr, method.lr_warmup, method.decay, method.decay_every)))


@pytest.mark.parametrize("name", ["one", "wig"])
def test_off_by_default_leaves_a_step_bit_identical(name):
    setup = build(adv_config(name, m=4, lr=1e-2, decay=0.5, decay_every=1, clip=1.0))
    stage = setup.stages[0].method
    assert stage.plateau is None
    old = dataclasses.replace(stage.method, optimizer=old_optimizer(stage))
    batch = jax.tree.map(lambda a: a[:3], setup.data["train"])
    new_out = old_out = None
    for method in (stage, old):
        params, state = setup.params, method.init(setup.params)
        step = jax.jit(lambda p, s, b, method=method: method.step(setup.objective, p, s, b))
        for _ in range(3):
            params, state, stats = step(params, state, batch)
        out = (params, state)
        new_out, old_out = (out, old_out) if method is stage else (new_out, out)
    for a, b in zip(jax.tree.leaves(new_out), jax.tree.leaves(old_out), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(b))


def test_off_by_default_keeps_run_names_and_records():
    default = adv_config("wig", m=4)
    assert all("plateau_factor" not in p["hyperparameters"] for p in default.canonical_dict()["phases"])
    explicit = adv_config("wig", m=4, plateau_patience=10, plateau_every=0)  # the defaults, spelled out
    assert explicit.digest() == default.digest()
    on = adv_config("wig", m=4, plateau_factor=0.5, plateau_every=13)
    assert on.digest() != default.digest()


def test_plateau_runs_in_training_and_reports_its_scale(tmp_path):
    config = adv_config("nog", steps=8, m=4, batch_size=4, plateau_factor=0.5, plateau_patience=0, plateau_every=2)
    setup = build(config)
    method = setup.stages[0].method
    assert method.plateau == Plateau(2, 0.5, 0)
    batch = jax.tree.map(lambda a: a[:4], setup.data["train"])
    step = jax.jit(lambda p, s: method.step(setup.objective, p, s, batch))
    params, state = setup.params, method.init(setup.params)
    scales = []
    for _ in range(4):  # the same batch: the loss falls, so the scale stays 1
        params, state, stats = step(params, state)
        scales.append(float(stats["lr_scale"]))
    assert scales == [1.0] * 4
    train(config, tmp_path / "run")  # the engine records the scale's mean over the logged steps
    rows = [r.split(",") for r in (tmp_path / "run" / "metrics.csv").read_text().splitlines()]
    logged = [float(r[4]) for r in rows if r[3] == "step_lr_scale"]
    assert logged and all(0.0 < v <= 1.0 for v in logged)


@pytest.mark.parametrize(
    "settings,words",
    [
        ({"plateau_factor": 1.5, "plateau_every": 10}, "plateau_factor must lie in (0, 1)"),
        ({"plateau_factor": 0.5}, "plateau_every"),
        ({"plateau_factor": 0.5, "plateau_every": 10, "plateau_patience": -1}, ">= 0"),
    ],
)
def test_plateau_settings_are_checked_in_one_line(settings, words):
    with pytest.raises(ConfigError) as info:
        adv_config("one", **settings)
    assert words in str(info.value) and "\n" not in str(info.value)
