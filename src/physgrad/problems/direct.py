"""Direct optimisation without a network (``--no-network``): x itself is trained.

The PBDL book and the SIP paper compare update rules first on the bare inverse problem,
``min_x L(P(x), y*)`` per sample, before putting a network in front (the SIP paper's 2D
toy and its heat-equation optimisation plots). :class:`DirectOptimisation` wraps any problem so that the engine
does exactly that: the "network" is a table of free variables, one x per sample, started
at ``problem.initial_guess(sample)``; every method applies unchanged (Adam/SGD = gradient
descent on x, ``newton`` = Newton on x, ``sip`` with ``optimizer=sgd, lr=1`` = iterating
the inverse simulator x ← P⁻¹(y + η(y* − y); x)). The wrapped problem's *test* samples are
the ones optimised, and are both splits (there is nothing to generalise to).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from .base import AbstractProblem


class FreeVariables(eqx.Module):
    """One x per sample: ``x[i]`` is sample i's current estimate; shape (n, *x_shape)."""

    x: Array


class DirectOptimisation(AbstractProblem):
    """``problem`` with its network replaced by free per-sample variables."""

    problem: AbstractProblem

    description: ClassVar[str] = "direct optimisation of x per sample (no network)"
    source: ClassVar[str] = "Holl, Koltun, Thuerey, NeurIPS 2022 (direct optimisation of the inverse problem)"
    fixed_samples: ClassVar[bool] = True  # the samples are the variables' targets

    @property
    def name(self) -> str:  # the wrapped problem's: summaries and errors name what was run
        return self.problem.name

    @property
    def needs_float64(self) -> bool:  # pyright: ignore[reportIncompatibleVariableOverride]
        # the wrapped problem's physics keeps its precision
        return self.problem.needs_float64

    def make_data(self, key):
        samples = self.problem.make_data(key)["test"]
        n = jax.tree.leaves(samples)[0].shape[0]
        indexed = {"sample": samples, "index": jnp.arange(n)}
        return {"train": indexed, "test": indexed}

    def make_network(self, key):
        raise NotImplementedError("use initial_network(key, data): the start depends on the data")

    def initial_network(self, key, data) -> FreeVariables:
        del key  # the start is the problem's initial guess for each sample
        return FreeVariables(jax.vmap(self.problem.initial_guess)(data["train"]["sample"]))

    def network_output(self, network, sample):
        return network.x[sample["index"]]

    def simulate(self, x, sample):
        return self.problem.simulate(x, sample["sample"])

    def loss(self, y, sample):
        return self.problem.loss(y, sample["sample"])

    # The wrapped problem's optional pieces, each on its own samples (``sample`` is the last
    # argument of every one of them); None where it has none.
    @property
    def metrics(self):  # pyright: ignore[reportIncompatibleVariableOverride]
        return _on_wrapped_sample(self.problem.metrics)

    @property
    def target(self):
        return _on_wrapped_sample(self.problem.target)

    @property
    def inverse(self):
        return _on_wrapped_sample(self.problem.inverse)


def _on_wrapped_sample(piece):
    """``piece(..., sample)`` of the wrapped problem as a piece of :class:`DirectOptimisation`,
    whose samples are ``{"sample": the wrapped problem's, "index": i}``; None stays None."""
    if piece is None:
        return None
    return lambda *args: piece(*args[:-1], args[-1]["sample"])
