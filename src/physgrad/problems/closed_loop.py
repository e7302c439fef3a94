"""Closed-loop control problems: a network steers a simulator step by step.

    s_{k+1} = physics(s_k, c_k),   c_k = control(network, s_k),   k = 0 … m−1,
    L = Σ_k w_k ℓ(s_{k+1}, c_k, k)

(the closed-loop data flow of physgrad's rollout engine).
A sample is an initial state s_0. The rollout methods (``bptt``, ``sbptt_m``, ``sbptt_c``,
``no_temporal``) train through :meth:`AbstractClosedLoop.system`; every other method sees
the problem through the open-loop contract as well:

- ``network_output(network, s0)`` runs the closed loop and returns the controls c_0..c_{m−1};
- ``simulate(controls, s0)`` replays them open-loop and returns y = (states s_1..s_m, controls);
- ``loss(y, s0) = Σ_k w_k ℓ(s_{k+1}, c_k, k)``;

so ``adam`` trains with plain BPTT without clipping, and ``--no-network`` optimises each
test sample's control sequence directly.

The data follow the StableBPTT protocol (§2.1): ``n_train + n_test`` initial states drawn
once from ``data_seed`` (42), the first ``n_train`` for training, independent of the run
seed (which only sets the network's initialisation); mini-batches of 8 in fixed order.
"""

# No `from __future__ import annotations`: Equinox reads `AbstractVar` fields from evaluated annotations.

import abc
import warnings
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from equinox import AbstractVar
from jaxtyping import PyTree

from ..rollout import System, closed_loop
from .base import AbstractProblem, Sample


class AbstractClosedLoop(AbstractProblem):
    """A closed-loop control problem: the rollout, the open-loop contract and the data
    protocol shared by :class:`~physgrad.problems.CartPole`,
    :class:`~physgrad.problems.Guidance` and :class:`~physgrad.problems.QuantumControl`.

    Equinox's abstract/final pattern, as :class:`~physgrad.problems.oscillators.AbstractOscillators`:
    this class holds the methods, each final class declares every setting (the protocol's
    ``n_train``, ``n_test``, ``data_seed`` first, then its own with its ``n_steps``) and
    defines the physics, the controller and the per-step loss (``initial_states``,
    ``control``, ``physics``, ``step_loss``, ``loss_weights``).
    """

    default_batch_size: ClassVar[int] = 8

    # The protocol's data (§2.1): n_train + n_test initial states from one fixed seed.
    n_train: AbstractVar[int]
    n_test: AbstractVar[int]
    data_seed: AbstractVar[int]
    n_steps: AbstractVar[int]  # the rollout length m

    @property
    def num_steps(self) -> int:
        """The rollout length m (``n_steps``)."""
        return self.n_steps

    @abc.abstractmethod
    def initial_states(self, key, n: int) -> Sample:
        """``n`` initial states stacked on a leading axis."""

    @abc.abstractmethod
    def control(self, network: PyTree, s: Sample) -> jax.Array:
        """c = N(s) for one state."""

    @abc.abstractmethod
    def physics(self, s: Sample, c: jax.Array) -> Sample:
        """One simulator step s' = P(s, c) for one state."""

    @abc.abstractmethod
    def step_loss(self, s_next: Sample, c: jax.Array, k) -> jax.Array:
        """The loss term ℓ_k of step k (before its weight)."""

    @abc.abstractmethod
    def loss_weights(self) -> jax.Array:
        """Per-step weights w, shape (num_steps,)."""

    # --- the open-loop contract and the rollout system ---------------------------------
    def make_data(self, key):
        del key  # the protocol fixes the data; the run seed only initialises the network
        n_train, n_test = self.n_train, self.n_test
        states = self.initial_states(jax.random.key(self.data_seed), n_train + n_test)
        return {
            "train": jax.tree.map(lambda a: a[:n_train], states),
            "test": jax.tree.map(lambda a: a[n_train:], states),
        }

    def closed_loop(self, network, s0):
        """(states s_1..s_m, controls c_0..c_{m−1}) of the closed loop from one s0."""

        def body(s, _):
            c = self.control(network, s)
            s_next = self.physics(s, c)
            return s_next, (s_next, c)

        _, (states, controls) = jax.lax.scan(body, s0, None, length=self.num_steps)
        return states, controls

    def network_output(self, network, sample):
        return self.closed_loop(network, sample)[1]

    def simulate(self, controls, sample):
        def body(s, c):
            s_next = self.physics(s, c)
            return s_next, s_next

        _, states = jax.lax.scan(body, sample, controls)
        return states, controls

    def predict(self, network, sample):
        return self.closed_loop(network, sample)

    def loss(self, y, sample):
        states, controls = y
        terms = jax.vmap(self.step_loss)(states, controls, jnp.arange(self.num_steps))
        return jnp.sum(self.loss_weights().astype(terms.dtype) * terms)

    def rollout_pieces(self, static):
        """The rollout system (BPTT and its variants) beside the open-loop pieces of
        :meth:`~physgrad.problems.AbstractProblem.objective`."""
        return {"rollout": self.system(lambda p, s: self.control(eqx.combine(p, static), s))}

    def system(self, control) -> System:
        """The rollout :class:`~physgrad.rollout.System` over a batch, with
        ``control(params, s) -> c`` (the network with its trainable parameters split off)."""
        return closed_loop(control, self.physics, self.step_loss, self.num_steps, self.loss_weights())


class ClosedLoopProblem(AbstractClosedLoop):
    """Deprecated spelling of :class:`AbstractClosedLoop` for one release: a base that
    fills the protocol's settings with their defaults (256 train and 256 test initial
    states from seed 42); a subclass declares ``n_steps`` and the abstract methods."""

    n_train: int = eqx.field(static=True, default=256)
    n_test: int = eqx.field(static=True, default=256)
    data_seed: int = eqx.field(static=True, default=42)

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        warnings.warn("physgrad.problems.ClosedLoopProblem is now physgrad.problems.AbstractClosedLoop, whose final "
                      "classes declare n_train, n_test, data_seed and n_steps themselves", DeprecationWarning,
                      stacklevel=2)  # fmt: skip


def zero_last_kernel(network):
    """The network with its last Dense kernel set to 0, so its initial output is 0 (the
    authors' ``--zero`` flag, on by accident of ``argparse type=bool``)."""
    last = network.layers[-1]
    return eqx.tree_at(lambda n: n.layers[-1].weight, network, jnp.zeros_like(last.weight))
