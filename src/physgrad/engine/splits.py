"""Which data a run trains on and evaluates as its ``test`` split: a strategy object of
:func:`physgrad.fit` (``split=``), applied to the problem's ``make_data`` output in one
place (:func:`physgrad.engine.setup.run_data`), so the problem a run is given stays the
caller's own.

- :class:`TestSplit` (the default): the problem's ``train`` and ``test`` as it makes them.
- :class:`HoldOut`: validation data in place of the test split, what a tuning trial
  (:func:`physgrad.tune`) trains on. Hyperparameters chosen on the test split overfit the
  test split, so a trial's run never evaluates it:

  - the problem's own ``val`` split where ``make_data`` returns one (the time-steppers: ks,
    kolmogorov, advection_1d), the training split unchanged; it stays the run's ``val``
    too (the same object, evaluated once), where PRDP reads its validation error;
  - a problem that optimises its test samples directly, with no map to generalise (its
    ``make_data`` returns one split object as both train and test: toy2d's x optimised
    from (3, 3)), has no unseen data to estimate; its validation loss is the training
    objective itself, which is what tuning an optimiser on such a problem selects on;
  - otherwise the last ``fraction`` of the training split (:func:`held_out_count`
    samples), which the run then does not train on. The last samples, because windowed
    problems store their windows trajectory by trajectory: the held-out windows come from
    other trajectories than the trained ones, as a validation set should.

  With ``fresh_samples`` every later epoch trains on the first part of a new draw (same
  size), never on the held-out samples: the split applies to every draw. The protocol is
  the usual one of model selection (Hastie, Tibshirani & Friedman, *The Elements of
  Statistical Learning*, 2009, §7.2: "the validation set is used to estimate prediction
  error for model selection; the test set ... for assessment of the generalization error
  of the final chosen model").

``make_data(key)`` still builds its test split (it is one function), but the run drops it
before anything is placed on a device, trained or evaluated.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import abc
from typing import Any

import equinox as eqx
import jax


def held_out_count(n: int, fraction: float) -> int:
    """How many of ``n`` training samples a hold-out ``fraction`` keeps for validation:
    round(fraction·n), at least 1 and at most n − 1."""
    if not 0.0 < fraction < 1.0:
        raise ValueError(f"holdout must be a fraction in (0, 1), got {fraction!r}")
    if n < 2:
        raise ValueError(f"cannot hold out validation samples from a training split of {n} sample(s)")
    return min(n - 1, max(1, round(fraction * n)))


class AbstractSplit(eqx.Module):
    """Which data a run trains on (``train``) and evaluates as ``test``."""

    @abc.abstractmethod
    def __call__(self, data: dict[str, Any]) -> dict[str, Any]:
        """The run's data from ``make_data``'s (``{"train", "test"}``, ``"val"`` optional)."""

    @property
    @abc.abstractmethod
    def note(self) -> str | None:
        """What a run's record (``config.json``, key ``"validation"``) says about its test
        split; None: the problem's own, and the record has no such key."""


class TestSplit(AbstractSplit):
    """The problem's own splits, unchanged: train on ``train``, evaluate on ``test`` (and
    ``val`` where the problem makes one)."""

    __test__ = False  # not a pytest test class, whatever its name

    def __call__(self, data: dict[str, Any]) -> dict[str, Any]:
        return data

    @property
    def note(self) -> None:
        return None


class HoldOut(AbstractSplit):
    """Validation data as the test split (the module docstring): the problem's ``val``,
    the directly optimised samples themselves, or the last ``fraction`` of ``train``
    (not trained on). The problem's test split never reaches the run."""

    fraction: float = 0.2

    def __check_init__(self):
        if not 0.0 < self.fraction < 1.0:
            raise ValueError(f"HoldOut(fraction=...) must be a fraction in (0, 1), got {self.fraction!r}")

    def __call__(self, data: dict[str, Any]) -> dict[str, Any]:
        if data.get("val") is not None:
            return {"train": data["train"], "test": data["val"], "val": data["val"]}
        train = data["train"]
        if data.get("test") is train:  # direct optimisation of the test samples (module docstring)
            return {"train": train, "test": train}
        n = jax.tree.leaves(train)[0].shape[0]
        k = held_out_count(n, self.fraction)
        return {"train": jax.tree.map(lambda a: a[: n - k], train), "test": jax.tree.map(lambda a: a[n - k :], train)}

    @property
    def note(self) -> str:
        # Worded as the tuning trials of an older physgrad recorded it (a problem wrapper then):
        # the same words keep those trials' records the same runs.
        return (f"test split = the problem's val split, or else the last {self.fraction:g} of train (held out, not "
                "trained on); the real test split is never built")  # fmt: skip


TEST_SPLIT = TestSplit()  # frozen: one shared default of every ``split=`` argument
