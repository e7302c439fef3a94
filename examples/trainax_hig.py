"""A physgrad rule inside a trainax training setup.

trainax (F. Koehler, ``pip install trainax``) trains autoregressive neural emulators: it cuts
trajectories into windows, shuffles minibatches and runs the loop; its trainers compute the
update from ``eqx.filter_value_and_grad`` of a loss configuration in ``step_fn``. Here
``step_fn`` asks a physgrad rule for the direction instead, and everything else stays
trainax's: its data, windows, mixer, loop and optax chain.

The problem is trainax's quick start: learn a linear 3-tap stencil that advects a periodic
1-D signal at CFL 0.75 (trainax's exact Fourier-spectral reference), trained on 5-step
rollouts. The rule is the half-inverse gradient (``physgrad.hig``) of the rollout, with
plain SGD, against trainax's own Adam on the same windows and number of updates.

    python examples/trainax_hig.py        # prints both runs' final training losses
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
import trainax as tx

import physgrad

ROLLOUT = 5  # unrolled steps per window (trainax's num_rollout_steps)


def make_stepper(key):
    """The emulator: one linear circular convolution (3 taps, no bias)."""
    return eqx.nn.Conv1d(1, 1, 3, padding="SAME", padding_mode="CIRCULAR", use_bias=False, dtype=jnp.float32, key=key)


def predict(stepper, window):
    """A window (ROLLOUT + 1, 1, N) -> the stepper's rollout of ROLLOUT steps from its first frame."""

    def body(u, _):
        u = stepper(u)
        return u, u

    return jax.lax.scan(body, window[0], None, length=ROLLOUT)[1]


def loss(y, window):  # the MSE over the rollout, as trainax's Supervised configuration
    return jnp.mean((y - window[1:]) ** 2)


class PhysgradTrainer(tx.trainer.SupervisedTrainer):
    """trainax's supervised rollout trainer whose update direction is a physgrad estimator's
    (``estimate(stepper, batch) -> (direction, stats)``), applied by the trainer's optax chain."""

    estimate: physgrad.Estimator

    def __init__(self, data, *, estimate, **kwargs):
        super().__init__(data, num_rollout_steps=ROLLOUT, **kwargs)
        self.estimate = estimate

    def step_fn(self, stepper, opt_state, data):
        direction, stats = self.estimate(stepper, data)
        updates, opt_state = self.optimizer.update(direction, opt_state, eqx.filter(stepper, eqx.is_array))
        return eqx.apply_updates(stepper, updates), opt_state, stats["loss"]


def main(steps: int = 200, verbose: bool = True) -> dict[str, float]:
    """Train trainax's Adam and physgrad's HIG for ``steps`` updates; the final mean loss of each
    (over the last 10 updates) and the test error of the learned stencil's 20-step rollout."""
    data = tx.sample_data.advection_1d_periodic(num_points=30, num_samples=20, temporal_horizon=50,
                                                key=jax.random.key(0)).astype(jnp.float32)  # fmt: skip
    test = tx.sample_data.advection_1d_periodic(num_points=30, num_samples=5, temporal_horizon=21,
                                                key=jax.random.key(1)).astype(jnp.float32)  # fmt: skip
    common = dict(num_training_steps=steps, batch_size=8)
    trainers = {
        "trainax adam": tx.trainer.SupervisedTrainer(
            data, num_rollout_steps=ROLLOUT, optimizer=optax.adam(1e-2), **common
        ),
        "physgrad hig": PhysgradTrainer(data, estimate=physgrad.hig(predict, loss), optimizer=optax.sgd(1.0), **common),
    }
    results = {}
    for name, trainer in trainers.items():
        stepper, history = trainer(make_stepper(jax.random.key(2)), jax.random.key(3), spawn_tqdm=False)
        rollout = jax.vmap(lambda u0, s=stepper: jax.lax.scan(lambda u, _: (s(u),) * 2, u0, None, length=20)[1])(
            test[:, 0]
        )
        error = float(jnp.mean((rollout - test[:, 1:]) ** 2) / jnp.mean(test[:, 1:] ** 2))
        results[name] = {"train_loss": float(jnp.mean(history[-10:])), "test_rel_mse_20": error}
        if verbose:
            stencil = jnp.ravel(stepper.weight)
            print(f"{name}: training loss {results[name]['train_loss']:.2e}, 20-step relative test MSE {error:.2e}, "
                  f"stencil {jnp.round(stencil, 3)}")  # fmt: skip
    return results


if __name__ == "__main__":
    main()
