"""The Problem contract: what every benchmark problem provides to the methods."""

from __future__ import annotations

import abc
import dataclasses
from typing import TYPE_CHECKING, Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray, PyTree

if TYPE_CHECKING:
    from ..methods import Objective  # for the annotation; objective() imports it when called

Sample = PyTree  # one data sample (unbatched); a batch is the same pytree with a leading axis


class AbstractProblem(eqx.Module):
    """A network coupled to a differentiable simulator (open-loop data flow).

        sample ──► network(θ) ──► x ──► simulate ──► y ──► loss(y, sample)

    Subclasses are Equinox modules whose fields are the problem's *settings* (sizes,
    physical constants), each with the paper's value as default. They define:

    - ``name`` and ``source`` (paper and section); ``default_batch_size``, the batch a run
      takes when none is given (the command line's per-method paper settings and
      comparisons are its own table, :mod:`physgrad.harness.papers`);
    - ``make_data(key) -> {"train": batch, "test": batch}``: deterministic per key;
    - ``make_network(key)``: the paper's default network;
    - ``network_output(network, sample) -> x``: per sample (unbatched);
    - ``simulate(x, sample) -> y``: per sample, differentiable;
    - ``loss(y, sample) -> scalar``: per-sample loss L_i; methods use the batch mean;
    - optionally ``metrics(x, y, sample) -> {name: scalar}``: extra per-sample metrics (e.g.
      the error against a ground truth), averaged over each split at evaluation;
    - optionally ``target(sample) -> y*``: the y-space target, when the loss measures the
      distance to one (needed by SIP);
    - optionally ``inverse(x, y, y_target, sample) -> x̃``: the analytic local inverse of
      ``simulate`` near the prediction x (SIP's ``analytic`` solver);
    - optionally ``initial_guess(sample) -> x``: where direct optimisation without a
      network (``--no-network``) starts (zeros by default);
    - ``default_shuffle``: the paper's batch order, fixed (False, the default) or a fresh
      permutation of the training samples every epoch (True); optionally
      ``batch_group_key``, a key of the data whose values label the samples: when shuffled,
      every batch holds samples of one label, the labels' batches interleaved at random (KS:
      one domain size per batch, ``batch_groups(train)`` reads the labels);
    - ``default_fresh_samples``: whether the paper trains on a stream of fresh samples
      (True: every epoch after the first draws a new train split from ``make_data``);
    - ``fixed_samples``: True where the samples are what is trained (direct optimisation),
      so the engine refuses fresh samples for it.

    All per-sample functions must be pure and traceable (vmap, jit, jacrev).
    """

    name: ClassVar[str]
    source: ClassVar[str]
    default_batch_size: ClassVar[int] = 128
    extra: ClassVar[str | None] = None  # the optional extra it needs (physgrad.extras), e.g. "pde"

    @abc.abstractmethod
    def make_data(self, key: PRNGKeyArray) -> dict[str, Sample]: ...

    @abc.abstractmethod
    def make_network(self, key: PRNGKeyArray) -> PyTree: ...  # an Equinox module, or any pytree of arrays and functions

    @abc.abstractmethod
    def network_output(self, network: PyTree, sample: Sample) -> PyTree: ...

    @abc.abstractmethod
    def simulate(self, x: PyTree, sample: Sample) -> PyTree: ...  # an array; a closed loop's (states, controls)

    @abc.abstractmethod
    def loss(self, y: PyTree, sample: Sample) -> jax.Array: ...

    def metrics(self, x: PyTree, y: PyTree, sample: Sample) -> dict[str, jax.Array]:
        """Extra per-sample metrics besides the loss (none by default)."""
        return {}

    def initial_guess(self, sample: Sample) -> PyTree:
        """Start of direct optimisation of x for one sample (zeros shaped like the output)."""
        # Only the output's shape is needed: trace the network abstractly, build no weights.
        shape = jax.eval_shape(lambda s: self.network_output(self.make_network(jax.random.key(0)), s), sample)
        return jnp.zeros(shape.shape, shape.dtype)

    target = None  # optional: (sample) -> y*
    inverse = None  # optional: (x, y, y_target, sample) -> x̃

    def predict(self, network: PyTree, sample: Sample) -> PyTree:
        """Simulator output ``y = P(network(sample))`` for one sample."""
        return self.simulate(self.network_output(network, sample), sample)

    # --- what the training engine asks of a problem (declared, never type-tested) -------
    # True when the problem's own arrays or physics are float64: the engine then runs the
    # whole training under ``jax.enable_x64(True)``. A declared flag (a class variable, or a
    # property where a setting decides it, e.g. ``dtype``). False by default: importing
    # physgrad leaves JAX's configuration alone, and float32 problems neither need nor get
    # x64 (their few float64 parts, such as reference solvers for data, scope it themselves).
    needs_float64: ClassVar[bool] = False

    def initial_network(self, key: PRNGKeyArray, data: dict[str, Sample]) -> PyTree:
        """The network a run starts from (default: :meth:`make_network`; direct
        optimisation starts from the data's initial guesses)."""
        return self.make_network(key)

    def objective(self, static: PyTree) -> Objective:
        """The pieces the update rules use, as functions of the trainable parameters
        (the network's inexact arrays; ``static`` is the rest, ``eqx.partition``)."""
        from ..methods import Objective

        return Objective(
            predict=lambda p, s: self.predict(eqx.combine(p, static), s),
            loss=self.loss,
            network_output=lambda p, s: self.network_output(eqx.combine(p, static), s),
            simulate=self.simulate,
            target=self.target,
            inverse=self.inverse,
        )

    refinable_setting: ClassVar[str | None] = None  # an iterative solver's count, refined by PRDP

    def check_refinable(self) -> None:
        """Raise ``ValueError`` if this instance's solver cannot be refined (PRDP)."""

    def with_refined(self, k: int) -> AbstractProblem:
        """This problem with its ``refinable_setting`` at ``k`` (what PRDP trains on next)."""
        name = self.refinable_setting
        assert name is not None, "only for a problem that declares refinable_setting"
        return dataclasses.replace(self, **{name: k})

    default_eval_samples: ClassVar[int] = 0  # evaluate the train split on a strided subset of this size
    # The paper's batch order, the default of the ``shuffle`` training setting: fixed (every
    # epoch takes the same batches in the same order) or a fresh permutation every epoch.
    default_shuffle: ClassVar[bool] = False
    # Whether the paper draws fresh training samples as it trains (an endless stream; the SIP
    # paper's experiments generate every batch on the fly) rather than cycling over a fixed
    # set: the default of the ``fresh_samples`` training setting. With it, every epoch after
    # the first trains on a new ``make_data`` train split (same size, new key), so no sample
    # is seen twice; ``make_data`` must then be cheap next to an epoch of training.
    default_fresh_samples: ClassVar[bool] = False
    # True where the samples are what is being trained (direct optimisation: one free x per
    # sample): a fresh draw would swap the targets under their variables, so the engine refuses
    # ``fresh_samples=True`` on such a problem.
    fixed_samples: ClassVar[bool] = False

    # The data's key whose values label the training samples' groups, or None: when the order
    # is shuffled, every batch then holds samples of one label only, and the labels' batches
    # follow each other at random (the KS code batches each domain size by itself). None (the
    # default): batches are cut from one permutation of all samples.
    batch_group_key: ClassVar[str | None] = None

    def batch_groups(self, train: Sample) -> np.ndarray | None:
        """One label per training sample (``train`` is the data's train split): its
        :attr:`batch_group_key` entry, or None where the problem declares none."""
        key = self.batch_group_key
        return None if key is None else np.asarray(train[key])

    @classmethod
    def settings(cls) -> dict[str, Any]:
        """The problem's settings (dataclass fields) and their defaults."""
        return {f.name: f.default for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}
