"""The jitted training step and evaluation, and :class:`Steps`: the training data on the
devices, each epoch's batch order and each stage's steps compiled (and checked by the
memory guard, :mod:`physgrad.engine.memory`) ahead of time.

The run takes its steps in chunks (:func:`make_steps`): up to :data:`CHUNK` steps in one
dispatch, their statistics read back once, so a step of a fraction of a millisecond is not
dominated by a host round trip and Python work per step.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import distributed
from ..acceptance import SKIPPED
from ..errors import ConfigError
from ..methods import AbstractMethod
from ..precision import x64_enabled
from . import memory, programs
from .setup import mesh_devices, method_refusals, run_data, scalar_loss
from .strategies import Placement
from .types import Setup, Stage, TrainSettings, TrainState

# The most steps one dispatch of :func:`make_steps` takes: the length of its statistics
# buffers (a few kB). The loop sizes each chunk by time (:class:`physgrad.engine.run.Chunks`).
CHUNK = 1024


def make_step(setup: Setup, batch_size: int, method: AbstractMethod | None = None):
    """The training step as one jitted function of (params, state, data, order, index).

    The mini-batch is gathered inside the jit (``order`` is the epoch's sample order,
    ``index`` the batch number), so a step is a single dispatch with no host work.
    Traced under a mesh (``jax.set_mesh``, :mod:`physgrad.distributed`) the batch is split
    over the mesh's ``"data"`` axis while parameters and state stay replicated."""
    return jax.jit(_step(setup, batch_size, method))


def make_steps(setup: Setup, batch_size: int, method: AbstractMethod | None = None, chunk: int = CHUNK):
    """Up to ``chunk`` training steps as one jitted function of
    ``(params, state, data, order, start, count)`` (what the run dispatches).

    Takes the steps of batches ``start, start + 1, ...`` of ``order`` (as :func:`make_step`
    does one; after the epoch's last batch the first again, for a run whose every epoch
    has the same order) in a ``lax.while_loop``, ``count`` of them (``1 <= count <=
    chunk``; a traced argument, so every count runs one compiled program), and stops early at a step whose
    loss is not finite unless the method's acceptance skipped it (``stats["skipped"]``):
    that step is not applied, so the parameters and state returned are those before it,
    as a run that diverges reports them. Returns ``(params, state, taken, diverged,
    stats)``: ``taken`` the steps applied (int32), ``diverged`` whether the loop stopped at
    a divergent step, and ``stats`` the per-step statistics, each of shape ``(chunk,
    *shape)``, valid in rows ``[0, taken)`` (row ``taken`` is the divergent step's when
    ``diverged``).

    With ``chunk == 1`` the program is the step alone, with no loop around it (``count``
    is then ignored and one step taken): what the run compiles where a loop would slow the
    step down (:func:`loop_chunk`).

    Why: a step of a small problem takes a fraction of a millisecond, less than a host
    round trip plus the Python work of the loop around it; one dispatch per chunk and one
    read-back of its statistics cost the same per chunk however many steps it holds."""
    step = _step(setup, batch_size, method)

    def applied(stats, params, state, new_params, new_state):
        """Whether the step is not applied (its loss not finite, unless the acceptance skipped
        it), and the parameters and state after it."""
        bad = ~jnp.isfinite(stats["loss"])
        if SKIPPED in stats:  # a step the acceptance refused left everything as it was
            bad = bad & (stats[SKIPPED] == 0)
        params, state = jax.lax.cond(bad, lambda: (params, state), lambda: (new_params, new_state))
        return bad, params, state

    def one_step(params, state, data, order, start, count):
        del count  # always one step: the run never asks this program for more (its chunk is 1)
        new_params, new_state, stats = step(params, state, data, order, start % (order.shape[0] // batch_size))
        bad, params, state = applied(stats, params, state, new_params, new_state)
        buffers = jax.tree.map(lambda v: v[None], stats)
        taken = jnp.where(bad, 0, 1).astype(jnp.int32)
        return tuple(distributed.replicated(x) for x in (params, state, taken, bad, buffers))

    def steps(params, state, data, order, start, count):
        per_epoch = order.shape[0] // batch_size
        shapes = jax.eval_shape(step, params, state, data, order, start)[2]
        buffers = jax.tree.map(lambda s: jnp.zeros((chunk, *s.shape), s.dtype), shapes)

        def go_on(carry):
            i, _, _, _, stop = carry
            return (i < count) & ~stop

        def body(carry):
            i, params, state, buffers, _ = carry
            new_params, new_state, stats = step(params, state, data, order, (start + i) % per_epoch)
            buffers = jax.tree.map(lambda b, v: b.at[i].set(v), buffers, stats)
            bad, params, state = applied(stats, params, state, new_params, new_state)
            return i + jnp.where(bad, 0, 1).astype(i.dtype), params, state, buffers, bad

        carry = (jnp.zeros((), jnp.int32), params, state, buffers, jnp.zeros((), bool))
        taken, params, state, buffers, diverged = jax.lax.while_loop(go_on, body, carry)
        return tuple(distributed.replicated(x) for x in (params, state, taken, diverged, buffers))

    return jax.jit(one_step if chunk == 1 else steps)


def loop_chunk(lowered, backend: str | None = None) -> int:
    """The most steps one dispatch should take for the program ``lowered`` (a chunk of
    :func:`make_steps`, lowered): :data:`CHUNK`, or 1 where the step convolves and runs on
    a CPU.

    Why: XLA's CPU backend runs a convolution inside a loop body 5–70× slower than the same
    convolution outside one (measured with jax 0.10.2 on one core: a 2-D NCHW convolution
    and its gradient 47 ms alone against 657 ms in a one-iteration ``while_loop``, NHWC
    43 against 2,920 ms, 1-D 1.2 against 6.4 ms; FFTs and matrix products are not
    affected; jax-ml/jax issue 12868). A chunked loop made the heat U-Net's Adam step ~10×
    slower (5.6 s → 57 s), so convolutional steps on a CPU are dispatched one at a time:
    their steps take milliseconds or more, where a dispatch costs a fraction of one."""
    backend = backend or jax.default_backend()
    if backend == "cpu" and "stablehlo.convolution" in lowered.as_text():
        return 1
    return CHUNK


class Program(NamedTuple):
    """A stage's compiled steps (:func:`make_steps`) and the most steps one call of it takes
    (``chunk``: :data:`CHUNK`, or 1 for a step without a loop, :func:`loop_chunk`). Called as
    the compiled function is: ``(params, state, data, order, start, count)``."""

    compiled: Any
    chunk: int

    def __call__(self, *args):
        return self.compiled(*args)


def _step(setup: Setup, batch_size: int, method: AbstractMethod | None = None):
    """One training step of batch ``index`` of ``order``, not jitted (:func:`make_step`)."""
    method = method or setup.method

    def step(params, state, data, order, index):
        rows = jax.lax.dynamic_slice_in_dim(order, index * batch_size, batch_size)
        batch = distributed.shard_batch(jax.tree.map(lambda a: a[rows], data))
        objective = setup.objective
        if objective.loss is not None:
            objective = objective._replace(loss=scalar_loss(objective.loss))
        params, state, stats = method.step(objective, params, state, batch)
        return distributed.replicated(params), distributed.replicated(state), stats

    return step


def make_evaluate(setup: Setup, chunk: int = 1024, per_sample: bool = False):
    """Mean per-sample loss and the problem's extra metrics over a data split (jitted, in
    chunks of ``chunk``): ``{"loss": ..., **problem.metrics}``; with ``per_sample`` every
    sample's values (for paired tests). Under a mesh the samples are split over its devices.

    Runs of the same problem and network structure share one jitted function (and so its
    compilations, :mod:`physgrad.engine.programs`): the seeds differ in arguments only."""
    key = programs.key("evaluate", setup.problem, chunk, per_sample, static=setup.static)
    return programs.EVALUATIONS.get(key, lambda: _make_evaluate(setup, chunk, per_sample))[0]


def _make_evaluate(setup: Setup, chunk: int, per_sample: bool):
    problem = setup.problem

    def one(params, sample):
        x = problem.network_output(setup.network(params), sample)
        y = problem.simulate(x, sample)
        return {"loss": scalar_loss(problem.loss)(y, sample), **problem.evaluate_metrics(x, y, sample)}

    def split_evaluate(params, data):
        n = jax.tree.leaves(data)[0].shape[0]
        devices = distributed.data_axis_size()
        if devices == 1:
            values = jax.lax.map(lambda s: one(params, s), data, batch_size=min(chunk, n))
        else:  # each device evaluates its share: (devices, n/devices) with the first axis split
            pad = -n % devices  # repeats of the last sample, cut off again below
            data = jax.tree.map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], pad, axis=0)]), data)
            data = jax.tree.map(lambda a: a.reshape(devices, (n + pad) // devices, *a.shape[1:]), data)
            data = distributed.shard_batch(data)
            per_device = min(chunk, (n + pad) // devices)
            values = jax.vmap(lambda d: jax.lax.map(lambda s: one(params, s), d, batch_size=per_device))(data)
            values = jax.tree.map(lambda v: v.reshape(n + pad, *v.shape[2:])[:n], values)
        return values if per_sample else jax.tree.map(jnp.mean, values)

    return jax.jit(lambda params, data: distributed.replicated(split_evaluate(params, data)))


class Steps:
    """The training data on the devices, each epoch's sample order, and each stage's steps
    compiled ahead of time (:func:`make_steps`; compilation is counted in ``compile_seconds``).

    With ``settings.memory_guard`` a stage's step is checked before it first runs
    (:mod:`physgrad.engine.memory`): the method's footprint before compiling, XLA's memory
    analysis of the compiled steps after; a step that cannot fit raises ConfigError."""

    def __init__(self, setup: Setup, placement: Placement, settings: TrainSettings, seed: int):
        self.placement, self.settings = placement, settings
        self.n_train = jax.tree.leaves(setup.data["train"])[0].shape[0]
        self.data = placement.put(setup.data["train"])
        self.shuffle_key = jax.random.fold_in(jax.random.key(seed), 2)
        self.shuffle = setup.problem.default_shuffle if settings.shuffle is None else settings.shuffle
        fresh = settings.fresh_samples
        self.fresh = setup.problem.default_fresh_samples if fresh is None else fresh
        if self.fresh and setup.problem.fixed_samples:
            raise ConfigError(f"{setup.problem.name}: fresh_samples cannot be on: its samples are what is trained")
        self.fresh_key = jax.random.fold_in(jax.random.key(seed), 3)
        self.first = self.data
        groups = setup.problem.batch_groups(setup.data["train"]) if self.shuffle else None
        self.groups = None if groups is None else np.asarray(groups)
        self.batch_sizes = [stage.batch_size for stage in setup.stages]

    @property
    def same_every_epoch(self) -> bool:
        """Whether every epoch trains on the same data in the same order (neither shuffled
        nor fresh), so that a chunk of steps may run on past an epoch's end."""
        return not self.shuffle and not self.fresh

    def draw(self, setup: Setup, stage: int, epoch: int) -> None:
        """The training data of a stage's epoch in ``self.data``: the first epoch of the first
        stage trains on ``setup.data``; with ``fresh_samples`` every later epoch on a new
        train split from ``make_data`` with a key of the seed, stage and epoch (so a resumed
        run draws the same samples), of the same shapes, so the compiled step is reused; the
        run's split applies to each draw (:func:`~physgrad.engine.setup.run_data`: a
        :class:`~physgrad.engine.splits.HoldOut` run never trains on the held-out part)."""
        if not self.fresh:
            return
        if stage == 0 and epoch == 0:
            self.data = self.first
            return
        key = jax.random.fold_in(jax.random.fold_in(self.fresh_key, stage), epoch)
        try:
            train = run_data(setup.problem, setup.split, key, check=False)["train"]
        except ValueError as e:
            raise ConfigError(f"{setup.problem.name}: fresh_samples: {e}") from None
        self.data = self.placement.put(train)

    def order(self, stage: int, epoch: int):
        """The sample order of a stage's epoch: fixed, or with ``shuffle`` a permutation
        drawn from the seed, the stage and the epoch (so a resumed run takes the same
        batches). Where the problem labels its samples (``batch_groups``) the permutation
        keeps each of the stage's batches within one label (:func:`grouped_order`)."""
        if not self.shuffle:
            return self.placement.put(jnp.arange(self.n_train, dtype=jnp.int32))
        key = jax.random.fold_in(jax.random.fold_in(self.shuffle_key, stage), epoch)
        if self.groups is None:
            return self.placement.put(jax.random.permutation(key, self.n_train).astype(jnp.int32))
        rng = np.random.default_rng(np.asarray(jax.random.key_data(key)))
        return self.placement.put(jnp.asarray(grouped_order(self.groups, self.batch_sizes[stage], rng)))

    def compile(self, state: TrainState, setup: Setup) -> tuple[Program, TrainState]:
        """The current stage's steps, compiled (and checked by the memory guard) with the
        chunk :func:`loop_chunk` chooses, or the
        same program compiled earlier in this process by a run that differs only in its
        seed (:mod:`physgrad.engine.programs`)."""
        stage = setup.stages[state.stage]
        t0 = time.perf_counter()
        lower = lambda size, chunk: self._lower(state, setup=setup, stage=stage, batch_size=size, chunk=chunk)  # noqa: E731
        guard = self.settings.memory_guard

        def build():
            if guard:  # the footprint alone, before spending time on compilation
                self._check(setup, stage)
            lowered = lower(stage.batch_size, CHUNK)
            chunk = loop_chunk(lowered)
            compiled = (lowered if chunk == CHUNK else lower(stage.batch_size, chunk)).compile()
            if guard:
                measure = lambda size: memory.compiled_bytes(lower(size, chunk).compile(), arguments=False)  # noqa: E731
                self._check(setup, stage, compiled=compiled, measure=measure)
            return Program(compiled, chunk)

        compiled, _ = programs.STEPS.get(self._key(state, setup, stage), build)
        return compiled, state._replace(compile_seconds=state.compile_seconds + time.perf_counter() - t0)

    def _key(self, state: TrainState, setup: Setup, stage: Stage):
        """What the compiled step depends on (None: something unhashable, compile afresh).
        The epoch's sample order is not in it: its shape is the data's length, its placement
        the mesh's."""
        return programs.key("steps", setup.problem, stage.method, stage.batch_size, self.placement.mesh,
                            self.settings.memory_guard, x64_enabled(), CHUNK, static=setup.static,
                            arguments=(state.params, state.opt_state, self.data))  # fmt: skip

    def _lower(self, state: TrainState, *, setup: Setup, stage: Stage, batch_size: int, chunk: int):
        with self.placement.scope():
            fn = make_steps(setup, batch_size, stage.method, chunk)
            order = self.order(state.stage, 0)
            return fn.lower(state.params, state.opt_state, self.data, order, np.int32(0), np.int32(1))

    def _check(self, setup: Setup, stage: Stage, *, compiled=None, measure=None):
        batch = memory.stand_in(setup.data["train"], stage.batch_size)
        devices = mesh_devices(self.placement.mesh)
        with method_refusals(stage.label, setup.problem):
            memory.check_step_fits(stage.method, setup.objective, setup.params, batch, devices=devices,
                                   compiled=compiled, measure=measure, label=stage.label)  # fmt: skip


def grouped_order(groups: np.ndarray, batch_size: int, rng: np.random.Generator) -> np.ndarray:
    """A permutation of ``range(len(groups))`` whose consecutive blocks of ``batch_size``
    each hold samples of one group: every group's samples in random order cut into full
    batches, those batches in random order (the groups interleaved at random). A group's
    remainder (fewer than ``batch_size`` samples) goes to the end, where the epoch's last
    batches may mix groups; every sample appears once."""
    batches, rest = [], []
    for label in np.unique(groups):
        members = rng.permutation(np.flatnonzero(groups == label))
        full = len(members) // batch_size * batch_size
        batches.extend(members[:full].reshape(-1, batch_size))
        rest.append(members[full:])
    ordered = [batches[i] for i in rng.permutation(len(batches))]
    tail = np.concatenate(rest)
    return np.concatenate([*ordered, rng.permutation(tail)]).astype(np.int32)
