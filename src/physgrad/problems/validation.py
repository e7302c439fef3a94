"""A problem whose test split is its validation data: what a tuning trial trains on.

Hyperparameters chosen on the test split overfit the test split, so a tuning trial
(:func:`physgrad.tune`) never builds it. :class:`Validation` wraps a problem so that its
``test`` split *is* the validation data:

- the problem's own ``val`` split where ``make_data`` returns one (the time-steppers: ks,
  kolmogorov, advection_1d), the training split unchanged;
- a problem that optimises its test samples directly, with no map to generalise (its
  ``make_data`` returns one split object as both train and test: toy2d's x optimised from
  (3, 3)), has no unseen data to estimate; its validation loss is the training objective
  itself, which is what tuning an optimiser on such a problem selects on;
- otherwise the last ``holdout`` fraction of the training split (at least one sample),
  which the trial then does not train on. The last samples, because windowed problems
  store their windows trajectory by trajectory: the held-out windows come from other
  trajectories than the trained ones, as a validation set should.

Everything else is the wrapped problem's (network, physics, loss, metrics, batch order,
precision). With ``fresh_samples`` every later epoch trains on the first part of a new draw
(same size), never on the held-out samples. The protocol is the usual one of model
selection (e.g. Hastie, Tibshirani & Friedman, *The Elements of Statistical Learning*,
§7.2: "the validation set is used to estimate prediction error for model selection; the
test set ... for assessment of the generalization error of the final chosen model").
"""

from __future__ import annotations

import dataclasses
from typing import Any, ClassVar

import jax

from .base import AbstractProblem


def held_out_count(n: int, holdout: float) -> int:
    """How many of ``n`` training samples a ``holdout`` fraction keeps for validation:
    round(holdout·n), at least 1 and at most n − 1."""
    if not 0.0 < holdout < 1.0:
        raise ValueError(f"holdout must be a fraction in (0, 1), got {holdout!r}")
    if n < 2:
        raise ValueError(f"cannot hold out validation samples from a training split of {n} sample(s)")
    return min(n - 1, max(1, round(holdout * n)))


class Validation(AbstractProblem):
    """``problem`` with its validation data as the test split (see the module docstring)."""

    problem: AbstractProblem
    holdout: float = 0.2

    description: ClassVar[str] = "a problem with its validation data in place of the test split (tuning trials)"
    source: ClassVar[str] = "hold-out validation (Hastie, Tibshirani & Friedman 2009, §7.2)"

    def make_data(self, key):
        data = self.problem.make_data(key)
        if data.get("val") is not None:
            return {"train": data["train"], "test": data["val"]}
        train = data["train"]
        if data.get("test") is train:  # direct optimisation of the test samples (module docstring)
            return {"train": train, "test": train}
        n = jax.tree.leaves(train)[0].shape[0]
        k = held_out_count(n, self.holdout)
        return {"train": jax.tree.map(lambda a: a[: n - k], train), "test": jax.tree.map(lambda a: a[n - k :], train)}

    # --- the rest is the wrapped problem's -------------------------------------------------
    @property
    def name(self) -> str:  # type: ignore[override]
        return self.problem.name

    @property
    def extra(self):  # type: ignore[override]
        return self.problem.extra

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        return self.problem.needs_float64

    @property
    def default_batch_size(self) -> int:  # type: ignore[override]
        return self.problem.default_batch_size

    @property
    def default_shuffle(self) -> bool:  # type: ignore[override]
        return self.problem.default_shuffle

    @property
    def default_fresh_samples(self) -> bool:  # type: ignore[override]
        return self.problem.default_fresh_samples

    @property
    def fixed_samples(self) -> bool:  # type: ignore[override]
        return self.problem.fixed_samples

    @property
    def default_eval_samples(self) -> int:  # type: ignore[override]
        return self.problem.default_eval_samples

    def make_network(self, key):
        return self.problem.make_network(key)

    def initial_network(self, key, data):
        return self.problem.initial_network(key, data)

    def network_output(self, network, sample):
        return self.problem.network_output(network, sample)

    def simulate(self, x, sample):
        return self.problem.simulate(x, sample)

    def loss(self, y, sample):
        return self.problem.loss(y, sample)

    def metrics(self, x, y, sample) -> dict[str, Any]:
        return self.problem.metrics(x, y, sample)

    def initial_guess(self, sample):
        return self.problem.initial_guess(sample)

    def predict(self, network, sample):
        return self.problem.predict(network, sample)

    @property
    def target(self):  # type: ignore[override]
        return self.problem.target

    @property
    def inverse(self):  # type: ignore[override]
        return self.problem.inverse

    def objective(self, static):
        return self.problem.objective(static)

    @property
    def batch_group_key(self) -> str | None:  # type: ignore[override]
        return self.problem.batch_group_key

    # PRDP on a tuning trial refines the wrapped problem's solver (``--set prdp=true``)
    def refinable_problem(self) -> AbstractProblem:
        return self.problem.refinable_problem()

    def with_refined(self, k: int) -> Validation:
        return dataclasses.replace(self, problem=self.problem.with_refined(k))
