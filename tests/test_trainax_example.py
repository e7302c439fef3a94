"""examples/trainax_hig.py: a physgrad rule (HIG) as the update of a trainax trainer.

Skipped where trainax is not installed (it is in the test extra)."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import pytest

pytest.importorskip("trainax", reason="the example trains with trainax (pip install trainax)")

# an end-to-end example (two trainers, 15 steps each, ~22 s): the slow tier
pytestmark = pytest.mark.slow

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "trainax_hig.py"


def load():
    spec = importlib.util.spec_from_file_location("trainax_hig", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_hig_trains_inside_a_trainax_trainer():
    import jax
    import jax.numpy as jnp

    example = load()
    results = example.main(steps=15, verbose=False)
    assert set(results) == {"trainax adam", "physgrad hig"}
    for values in results.values():
        assert all(math.isfinite(v) for v in values.values())
        assert values["test_rel_mse_20"] < 1.0  # better than predicting zeros
    # the trainer's step is the estimator's direction applied by its optax chain
    data = jax.random.normal(jax.random.key(0), (4, example.ROLLOUT + 1, 1, 30), jnp.float32)
    stepper = example.make_stepper(jax.random.key(1))
    import optax

    import physgrad

    estimate = physgrad.hig(example.predict, example.loss)
    trainer = example.PhysgradTrainer(data, estimate=estimate, optimizer=optax.sgd(0.5), num_training_steps=1,
                                      batch_size=4)  # fmt: skip
    opt_state = trainer.optimizer.init(stepper)
    new, _, loss = trainer.step_fn(stepper, opt_state, data)
    direction, stats = estimate(stepper, data)
    assert float(loss) == pytest.approx(float(stats["loss"]))
    assert jnp.allclose(new.weight, stepper.weight - 0.5 * direction.weight, atol=1e-6)
