"""The Method contract and what a method sees of a problem."""

from __future__ import annotations

import abc
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree


class Objective(NamedTuple):
    """The per-sample pieces of a problem, as pure functions of the trainable parameters.

    ``predict(params, sample) -> y`` runs network and simulator for one sample;
    ``loss(y, sample) -> L_i`` is the per-sample loss. Methods use the batch mean
    ``L = (1/b) Σ_i L_i``, as the HIG paper's code does.

    Methods that treat network and physics separately (SIP) also use
    ``network_output(params, sample) -> x``, ``simulate(x, sample) -> y``,
    ``target(sample) -> y*`` (the y-space target, None if the problem has none) and
    ``inverse(x, y, y_target, sample) -> x̃`` (the problem's analytic local inverse or None).

    Rollout methods (BPTT and its variants) use ``rollout``: a
    :class:`physgrad.rollout.System` whose transition takes the trainable parameters; a
    batch of samples is then a batch of initial states. None for open-loop problems.
    Time-stepper problems also give ``unrolled(m, teacher_forcing) -> System``: the rollout
    over the first m steps of each window (None: the problem's m), teacher-forced for the
    one-step modality.
    """

    predict: Callable[[PyTree, PyTree], Array]
    loss: Callable[[Array, PyTree], Array]
    network_output: Callable[[PyTree, PyTree], Array] | None = None
    simulate: Callable[[Array, PyTree], Array] | None = None
    target: Callable[[PyTree], Array] | None = None
    inverse: Callable | None = None
    rollout: Any = None
    unrolled: Callable[[int | None, bool], Any] | None = None

    def sample_losses(self, params: PyTree, batch: PyTree) -> Array:
        return jax.vmap(lambda s: self.loss(self.predict(params, s), s))(batch)

    def batch_loss(self, params: PyTree, batch: PyTree) -> Array:
        return jnp.mean(self.sample_losses(params, batch))


class AbstractMethod(eqx.Module):
    """An update rule: ``init(params) -> state`` and a pure ``step``.

    ``step(objective, params, state, batch) -> (params, state, stats)`` does everything a
    training step needs (gradients, Jacobians, inverse solves) and is jit-compiled by the
    engine as one function. ``stats`` is a dict of scalars and must contain ``"loss"``, the
    batch-mean loss at the parameters *before* the update.
    """

    @abc.abstractmethod
    def init(self, params: PyTree) -> Any: ...

    def check(self, objective: Objective) -> None:
        """Raise ``ValueError`` if this method cannot run on ``objective`` (default: it can)."""

    def check_batch_size(self, batch_size: int) -> None:
        """Raise ``ValueError`` if this method cannot take batches of this size (default: it can)."""

    @abc.abstractmethod
    def step(
        self, objective: Objective, params: PyTree, state: Any, batch: PyTree
    ) -> tuple[PyTree, Any, dict[str, Array]]: ...
