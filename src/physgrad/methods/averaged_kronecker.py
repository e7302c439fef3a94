"""KHIG with running averages of its Kronecker factors, refreshed as K-FAC does.

Sources: Martens & Grosse, *Optimizing Neural Networks with Kronecker-factored Approximate
Curvature*, ICML 2015, §5 and §8 (exponentially decayed averages of the factors, updated
every T₁ steps, their inverses recomputed every T₃ steps; kfac-jax's
``curvature_update_period`` and ``inverse_update_period``); the rule is
:class:`physgrad.methods.KroneckerPower` (:mod:`physgrad.methods.kronecker_hig`, where the
factors and the power are derived; convolution layers: :mod:`physgrad.methods.conv_factors`).

Per layer (dense or convolution) and step t, with the factors ``G(batch_t)``, ``A(batch_t)``
of this batch, on the collecting steps t ≡ 0 (mod ``curvature_every``)

    G_t = β G_{t−1} + (1 − β) G(batch_t),   A_t likewise   (G_0, A_0: the first batch's),

(``G_t = G_{t−1}`` on the other steps), and the eigendecompositions of ``G_t`` and ``A_t``
recomputed every ``inverse_every`` steps (a multiple of ``curvature_every``; reused in
between); the layer's gradient ∇W̄ is always this batch's, so

    ΔW̄ = Q_G [ φ(γ αᵀ / n) ⊙ (Q_Gᵀ ∇W̄ Q_A) ] Q_Aᵀ,   φ(λ) = (λ + δ)^p,

with (γ, Q_G), (α, Q_A) the last eigendecompositions and n = b (dense) or b·T (KFC's count).

What a step costs. On dense layers with every output row (the rule's structured route) the
signals D are computed every step anyway (the gradient needs them), so only the
eigendecompositions are saved. On convolution layers or with ``probes`` (the signal route,
:mod:`physgrad.methods.layer_terms`) a step that collects no factors runs one forward and
one backward pass for the gradients (a convolution's kernel gradient on its operand, no
input patches) and skips the probes' backward passes, the patches and the factor products
(inside a ``lax.cond``): with ``curvature_every = inverse_every = k`` one step in k pays
for the curvature, the others cost about a plain gradient step.

The running factors are the state of a
control (:class:`RunningFactors`, :class:`physgrad.methods.AbstractControl`) that hands
the rule its per-layer direction; :class:`AveragedKronecker` is the final method that fills
:class:`physgrad.methods.AbstractOptaxMethod`'s fields with it.

The state's layout
------------------
The factors of a dense layer are kept per parameter leaf, before the network is traced: a
2-D leaf of shape (r, c) holds a left factor of (r + 1)² and a right factor of (c + 1)²
(one more row and column for a bias folded into either side). Once the trace shows which
leaves are dense layers, W @ x (W: d_out × d_in) keeps G in the top-left d_out² of the left
factor and A in the top-left d_in'² of the right one; a @ W (W: d_in × d_out) the other way
round. A kernel leaf of 3 or more axes laid out (out, in, *window), as Equinox's, holds
(out + 1)² (G) and (in·k₁⋯k_d + 1)² (A, the bias last) when in·k₁⋯k_d < :data:`CONV_SIDE_MAX`
(a wider leaf holds none, and a convolution on it is refused in one line). So the state's
shapes follow from the parameters alone, as an optax state's do, and a leaf that turns out
not to be a layer only holds zeros.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array

from ..precision import float64_scope, to_float64
from ..routes.base import DenseUse
from ..routes.structured import explicit_rows
from . import conv_factors as kfc
from .kronecker_hig import KroneckerPower, kronecker_factors, layer_gradient, power_direction
from .layer_terms import layer_pass
from .method import AbstractControl, AbstractOptaxMethod


class KroneckerAverages(NamedTuple):
    """:class:`RunningFactors`' state. Per parameter leaf (None for leaves that are not
    2-D): ``factors`` the running ``(left, right)`` factors, ``eigen`` their last
    eigendecompositions ``(λ_left, Q_left, λ_right, Q_right)``; ``count`` the steps taken."""

    factors: tuple
    eigen: tuple
    count: Array


class RunningFactors(AbstractControl):
    """The running averages of KHIG's factors as the control of a :class:`KroneckerPower`
    rule: its state is :class:`KroneckerAverages`, and each dense layer's direction is the
    power of the averaged factors (module docstring). ``curvature_ema = 0`` with
    ``inverse_every = 1`` is the rule with fresh factors (HIG's way); ``curvature_every``
    steps between factor updates (module docstring: what the other steps skip).

    The running factors are stored in the parameters' dtype; their eigendecompositions run
    in float64 as the fresh rule's. Float32 storage keeps eigenvalues down to ~1e-7 of a
    factor's largest, below the default damping (1e-4 of the block's largest product).

    Stats: ``refreshed`` (1 when this step recomputed the eigendecompositions).
    """

    curvature_ema: float = eqx.field(static=True, default=0.95)
    inverse_every: int = eqx.field(static=True, default=5)
    curvature_every: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if not 0.0 <= self.curvature_ema < 1.0:
            raise ValueError(f"curvature_ema must be in [0, 1), got {self.curvature_ema}")
        if self.inverse_every < 1:
            raise ValueError(f"inverse_every must be >= 1, got {self.inverse_every}")
        if self.curvature_every < 1 or self.inverse_every % self.curvature_every:
            raise ValueError(f"curvature_every must be >= 1 and divide inverse_every={self.inverse_every}, "
                             f"got {self.curvature_every}")  # fmt: skip

    def init(self, params):
        factors, eigen = [], []
        for leaf in jax.tree.leaves(params):
            sides = _sides(leaf)
            if sides is None:
                factors.append(None)
                eigen.append(None)
                continue
            factors.append(tuple(jnp.zeros((n, n), leaf.dtype) for n in sides))
            eigen.append(tuple(x for n in sides for x in (jnp.zeros((n,), leaf.dtype), jnp.eye(n, dtype=leaf.dtype))))
        return KroneckerAverages(tuple(factors), tuple(eigen), jnp.zeros((), jnp.int32))

    def direct(self, rule, objective, params, batch, state, acceptance):
        if not isinstance(rule, KroneckerPower):
            raise ValueError(f"running Kronecker factors need a KroneckerPower rule, got {type(rule).__name__}")
        leaves = jax.tree.leaves(params)
        factors, eigen = list(state.factors), list(state.eigen)
        beta = jnp.where(state.count == 0, 0.0, self.curvature_ema)  # the first batch starts the average
        refresh = state.count % self.inverse_every == 0
        collect = state.count % self.curvature_every == 0
        plan = rule.plan(objective, params, batch)
        if plan.convs or rule.probes:
            return _signal_direct(rule, plan, params, batch, state, beta, collect, refresh)

        # Called by the rule once per dense layer while it traces; the new averages are
        # collected here and become the state after the step.
        def dense(use: DenseUse, D, a, g):
            bias = use.bias is not None
            A, G = kronecker_factors(D, a, bias)
            if factors[use.leaf] is None:
                raise ValueError(f"khig: dense layer leaf {use.leaf} is not a 2-D parameter")
            dtype = leaves[use.leaf].dtype
            sides = {"G": 1 if use.transposed else 0, "A": 0 if use.transposed else 1}
            slots, spectra = list(factors[use.leaf]), list(eigen[use.leaf])
            out = {}
            for name, fresh in (("G", G), ("A", A)):
                side, n = sides[name], fresh.shape[0]
                stored = slots[side][:n, :n].astype(fresh.dtype)
                average = jnp.where(collect, beta * stored + (1 - beta) * fresh, stored)
                slots[side] = slots[side].at[:n, :n].set(average.astype(dtype))
                old = (spectra[2 * side][:n].astype(fresh.dtype), spectra[2 * side + 1][:n, :n].astype(fresh.dtype))
                lam, q = jax.lax.cond(refresh, lambda m=average: tuple(jnp.linalg.eigh(m)), lambda o=old: o)
                spectra[2 * side] = spectra[2 * side].at[:n].set(lam.astype(dtype))
                spectra[2 * side + 1] = spectra[2 * side + 1].at[:n, :n].set(q.astype(dtype))
                out[name] = (lam, q)
            factors[use.leaf], eigen[use.leaf] = tuple(slots), tuple(spectra)
            (gamma, q_g), (alpha, q_a) = out["G"], out["A"]
            return power_direction(layer_gradient(D, a, g, bias), gamma, q_g, alpha, q_a, a.shape[0], rule.power,
                                   rule.truncation, rule.damping)  # fmt: skip

        direction, stats = rule.directions(objective, params, batch, dense)
        new = KroneckerAverages(tuple(factors), tuple(eigen), state.count + 1)
        return direction, {**stats, "refreshed": refresh.astype(jnp.int32)}, new


# A kernel leaf of 3 or more axes, (out, in, *window) as Equinox's, holds the factors of a
# convolution layer only while in·k₁⋯k_d stays below this (its A side is that wide, squared).
CONV_SIDE_MAX = 4096


def _sides(leaf) -> tuple[int, int] | None:
    """The (left, right) factor sizes a leaf holds: (r + 1, c + 1) for a 2-D leaf (r, c), (out + 1,
    in·k₁⋯k_d + 1) for a kernel (out, in, *window) narrower than :data:`CONV_SIDE_MAX`, else None."""
    if leaf.ndim < 2 or jnp.iscomplexobj(leaf):
        return None
    rest = math.prod(leaf.shape[1:])
    return (leaf.shape[0] + 1, rest + 1) if leaf.ndim == 2 or rest < CONV_SIDE_MAX else None


def _signal_direct(rule: KroneckerPower, plan, params, batch, state: KroneckerAverages, beta, collect, refresh):
    """:meth:`RunningFactors.direct` where the rule takes the signal route (convolution layers,
    or ``probes``): on a collecting step the fresh ``(A, G, ∇W̄)`` of every layer
    (:func:`~physgrad.methods.layer_terms.layer_pass` and its ``curvature()``, inside a
    ``lax.cond``) enter the averages; on any other step only the pass's gradients are
    computed (the cost of a plain gradient) and the stored factors and eigendecompositions
    are reused."""
    structure, dense, convs = plan.structure, plan.structure.dense, plan.convs
    leaves = jax.tree.leaves(params)
    b = jax.tree.leaves(batch)[0].shape[0]
    # per layer: its leaf, the sides holding (G, A), d_out, d_in' and KFC's count (b or b·T)
    layout = [(u.leaf, (1, 0) if u.transposed else (0, 1), u.d_out, u.d_in + (u.bias is not None), b) for u in dense]
    layout += [
        (c.leaf, (0, 1), c.d_out, c.d_in + (c.bias is not None), b * c.positions) for c in kfc.conv_layers(convs)
    ]
    for leaf, (g_side, a_side), d_out, d_in, _ in layout:
        slots = state.factors[leaf]
        if slots is None or slots[g_side].shape[0] < d_out or slots[a_side].shape[0] < d_in:
            raise ValueError(f"khig: running factors of leaf {leaf} (shape {leaves[leaf].shape}) do not fit its layer "
                             f"({d_out} outputs, {d_in} inputs); they are kept for 2-D weights and kernels laid out "
                             f"(out, in, *window) with in·window < {CONV_SIDE_MAX}")  # fmt: skip
    run = layer_pass(structure, dense, convs, params, batch, plan.jacobian.loss_and_gradient, rule.probes)
    shapes = jax.eval_shape(run.curvature)
    fresh: list = jax.lax.cond(
        collect, run.curvature, lambda: jax.tree.map(lambda m: jnp.zeros(m.shape, m.dtype), shapes)
    )
    grads, y, loss, g = run.grads, run.y, run.loss, run.g
    factors, eigen, averages = list(state.factors), list(state.eigen), []
    for (leaf, sides, *_), (A, G) in zip(layout, fresh):
        slots = list(factors[leaf])
        for side, m in zip(sides, (G, A)):
            n = m.shape[0]
            old = slots[side][:n, :n].astype(m.dtype)
            average = jnp.where(collect, beta * old + (1 - beta) * m, old)
            slots[side] = slots[side].at[:n, :n].set(average.astype(slots[side].dtype))
            averages.append(average)
        factors[leaf] = tuple(slots)
    J = explicit_rows(plan.jacobian.predict, structure, params, batch, 0) if plan.explicit else None
    J = jax.lax.stop_gradient(J)
    with float64_scope():

        def decompose():  # (A₀, G₀, A₁, G₁, …), as the rule reads them
            return kfc.eigh_all([to_float64(averages[j ^ 1]) for j in range(len(averages))], rule._stacked)

        def stored():
            out = []
            for leaf, (g_side, a_side), d_out, d_in, _ in layout:
                for side, n in ((a_side, d_in), (g_side, d_out)):
                    out.append((to_float64(eigen[leaf][2 * side][:n]), to_float64(eigen[leaf][2 * side + 1][:n, :n])))
            return out

        eig = jax.lax.cond(refresh, decompose, stored)
        for k, (leaf, (g_side, a_side), *_) in enumerate(layout):
            spectra = list(eigen[leaf])
            for side, (lam, q) in ((a_side, eig[2 * k]), (g_side, eig[2 * k + 1])):
                n = lam.shape[0]
                spectra[2 * side] = spectra[2 * side].at[:n].set(lam.astype(spectra[2 * side].dtype))
                spectra[2 * side + 1] = spectra[2 * side + 1].at[:n, :n].set(q.astype(spectra[2 * side + 1].dtype))
            eigen[leaf] = tuple(spectra)
        deltas = [rule._power(to_float64(grad), eig, k, lay[4]) for k, (grad, lay) in enumerate(zip(grads, layout))]
        J64 = None if J is None else to_float64(J)
        direction, stats = rule._assemble(plan, params, deltas[: len(dense)], deltas[len(dense) :], J64,
                                          to_float64(g), loss, y.dtype)  # fmt: skip
    new = KroneckerAverages(tuple(factors), tuple(eigen), state.count + 1)
    return direction, {**stats, "refreshed": refresh.astype(jnp.int32)}, new


class AveragedKronecker(AbstractOptaxMethod):
    """Kronecker-factored HIG with running averages of the factors, refreshed as K-FAC does
    (module docstring): a final class that fills :class:`AbstractOptaxMethod`'s fields with
    the rule, the optimizer and the :class:`RunningFactors` control. The leftover block
    (parameters outside the dense layers) stays exact and fresh. The state is
    :class:`physgrad.methods.MethodState` ``(optimizer, None, KroneckerAverages)``.

    Fields:
        rule: the :class:`KroneckerPower` whose power, truncation and damping apply.
        optimizer: applies the direction (``optax.sgd(η)``: HIG's step).
        curvature_ema: β, the weight of the past factors (K-FAC's ``curvature_ema``).
        inverse_every: steps between eigendecompositions (K-FAC's ``inverse_update_period``).
        curvature_every: steps between factor updates (K-FAC's ``curvature_update_period``;
            divides ``inverse_every``). On convolution layers or with probes the other steps
            compute the gradient alone.
    """

    rule: KroneckerPower
    optimizer: optax.GradientTransformation = eqx.field(static=True, default=optax.sgd(1.0))
    curvature_ema: float = eqx.field(static=True, default=0.95)
    inverse_every: int = eqx.field(static=True, default=5)
    curvature_every: int = eqx.field(static=True, default=1)
    acceptance: None = eqx.field(default=None, init=False)
    extras: tuple[str, ...] = eqx.field(static=True, default=("value",), init=False)

    @property
    def control(self) -> RunningFactors:
        return RunningFactors(self.curvature_ema, self.inverse_every, self.curvature_every)

    def __check_init__(self):
        _ = self.control  # RunningFactors checks β and the period


__all__ = ["AveragedKronecker", "KroneckerAverages", "RunningFactors"]
