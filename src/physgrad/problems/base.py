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
      the error against a ground truth), averaged over each split at evaluation (read them
      with :meth:`evaluate_metrics`, ``{}`` where a problem has none);
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
      so the engine refuses fresh samples for it;
    - optionally ``rollout_pieces(static) -> {field: value}``: the
      :class:`~physgrad.methods.Objective`'s rollout fields, where the problem is a closed
      loop or a time-stepper (the bases :class:`~physgrad.problems.AbstractClosedLoop` and
      :class:`~physgrad.problems.AbstractTimeStepper` define it);
    - ``zero_output_layer``: True where :meth:`initial_network` zeroes the network's output
      layer (a declared flag; the time-steppers' ``zero_init``).

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

    def initial_guess(self, sample: Sample) -> PyTree:
        """Start of direct optimisation of x for one sample (zeros shaped like the output)."""
        # Only the output's shape is needed: trace the network abstractly, build no weights.
        shape = jax.eval_shape(lambda s: self.network_output(self.make_network(jax.random.key(0)), s), sample)
        return jnp.zeros(shape.shape, shape.dtype)

    # Optional pieces: None where a problem has none; a problem that has one defines it as a
    # method of the same name (no default is written here for a subclass to replace).
    metrics = None  # optional: (x, y, sample) -> {name: per-sample scalar}, besides the loss
    target = None  # optional: (sample) -> y*
    inverse = None  # optional: (x, y, y_target, sample) -> x̃
    # optional: (static) -> the Objective's rollout fields ("rollout", and for time-steppers
    # "unrolled" and "differentiable"), where the problem runs a closed loop or a rollout
    rollout_pieces = None

    def evaluate_metrics(self, x: PyTree, y: PyTree, sample: Sample) -> dict[str, jax.Array]:
        """The problem's :attr:`metrics` for one sample, ``{}`` where it declares none."""
        return {} if self.metrics is None else self.metrics(x, y, sample)

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

    # True where the network's output layer starts at zero (a declared flag, a property
    # where a setting decides it: the time-steppers' ``zero_init``, so a corrector starts as
    # the bare solver). Closed-loop problems that zero a kernel do it in make_network.
    zero_output_layer: ClassVar[bool] = False

    def initial_network(self, key: PRNGKeyArray, data: dict[str, Sample]) -> PyTree:
        """The network a run starts from: :meth:`make_network`, with its output layer
        zeroed (weights and bias) where the problem declares ``zero_output_layer``
        (:func:`zeroed_output_layer`). Direct optimisation starts from the data's initial
        guesses instead."""
        net = self.make_network(key)
        return zeroed_output_layer(net) if self.zero_output_layer else net

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
            **({} if self.rollout_pieces is None else self.rollout_pieces(static)),
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


def _output_layer(net):
    """``net -> its output layer``: the ResNets' ``conv_out``, the last layer with
    parameters of a network with ``layers`` (``eqx.nn.Sequential``, ``eqx.nn.MLP``,
    :class:`physgrad.MLP`), or a single-layer network itself."""
    if hasattr(net, "conv_out"):
        return lambda n: n.conv_out
    layers = getattr(net, "layers", None)
    if isinstance(layers, tuple | list):
        with_params = [i for i, layer in enumerate(layers) if jax.tree.leaves(eqx.filter(layer, eqx.is_inexact_array))]
        if with_params:
            index = with_params[-1]
            return lambda n: n.layers[index]
    return lambda n: n


def zeroed_output_layer(net: PyTree) -> PyTree:
    """``net`` with its output layer's weights and bias at zero (:func:`_output_layer`).
    Only the output layer: zeroing every layer of a deeper network would leave only the
    last bias with a gradient."""
    last = _output_layer(net)
    zeroed = jax.tree.map(jnp.zeros_like, eqx.filter(last(net), eqx.is_inexact_array))
    return eqx.tree_at(last, net, eqx.combine(zeroed, last(net)))
