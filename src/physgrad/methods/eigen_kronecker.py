"""Eigenvalue-corrected KHIG: the Kronecker eigenbasis kept, its eigenvalues replaced by the
exact diagonal of the layer's Gauss–Newton block in that basis.

Sources: George, Laurent, Bouthillier, Ballas & Vincent, *Fast Approximate Natural Gradient
Descent in a Kronecker-factored Eigenbasis* (EKFAC), NeurIPS 2018 (the corrected diagonal,
the basis refreshed less often than the diagonal); Vyas et al., *SOAP: Improving and
Stabilizing Shampoo using Adam*, 2024 (the same idea for Shampoo's basis); the rule and its
factors are :class:`physgrad.methods.KroneckerPower` (:mod:`physgrad.methods.kronecker_hig`);
HIG's power and truncation are Schnell, Holl & Thuerey, ICLR 2022.

The correction
--------------
KHIG approximates a dense layer's block of ``JᵀJ`` by ``(1/b) G ⊗ A`` and scales the
gradient in the factors' eigenbasis ``U = U_G ⊗ U_A`` by the products ``γ_i α_j / b``. That
basis is kept; the products are replaced by the diagonal of the layer's *exact* block
``Σ_s D_sᵀD_s ⊗ ā_s ā_sᵀ`` in it. With ``g_{s,k} = D_s[k]`` (the derivative of output k of
sample s with respect to the layer's pre-activations, d_out) and ``ā_s`` the layer input with
the bias entry, the block's Jacobian row for (s, k) is ``g_{s,k} ⊗ ā_sᵀ`` and

    Λ_ij = [Uᵀ (JᵀJ) U]_(ij),(ij) = Σ_{s,k} (U_Gᵀ g_{s,k})_i² (U_Aᵀ ā_s)_j²
         = Σ_s P_si Q_sj,   P = Σ_k (D_s U_G)²  (b × d_out),   Q = (Ā U_A)²  (b × d_in'),

one product ``Pᵀ Q`` of the per-sample projected Jacobians (squared elementwise). Of all
diagonal scalings in this basis, Λ is the one closest to the exact block in the Frobenius
norm (EKFAC's argument); it is exact wherever the block is (one sample; one dense layer
under linear physics shared by the samples: then ``Λ_ij = γ_i α_j / b`` and the rule equals
KHIG, and HIG). The layer's direction is

    ΔW̄ = U_G [ φ(Λ) ⊙ (U_Gᵀ ∇W̄ U_A) ] U_Aᵀ,      φ(λ) = (λ + δ)^p  for λ > τ² λ_max, else 0,

with KHIG's power p (−¾: HIG's κ = −½), HIG's relative truncation τ and damping
``δ = damping · λ_max``, λ_max the largest Λ of the layer (:func:`kept_power`). The leftover
parameters (outside the dense layers) keep KHIG's exact block.

The basis and its refresh
-------------------------
The eigenbases ``U_G``, ``U_A`` come from this batch's factors every ``basis_every`` steps and
are the method's state in between; Λ is fresh every step (it needs the signals ``D`` that the
gradient needs anyway). ``basis_every = 1`` is fully fresh (HIG's way). The bases are kept
per parameter leaf in the layout of :mod:`physgrad.methods.averaged_kronecker`: a 2-D leaf
(r, c) holds a left basis of (r + 1)² and a right one of (c + 1)², the layer's in their
top-left corners (identity elsewhere), so the state's shapes follow from the parameters.

Why its own method and not a setting of ``khig``: KHIG's rule is stateless (fresh factors,
an :class:`~physgrad.methods.Estimator`), while the kept basis is state, as the running
factors of :class:`~physgrad.methods.AveragedKronecker` are; and its cost and memory
differ (the projections below). It reuses the rule's tracing, signals, leftover block and
truncation unchanged, through the rule's per-layer hook.

Cost per layer and step, beyond KHIG's: the projections ``D U_G`` (rows · d_out²) and
``Ā U_A`` (b · d_in'²) and the product ``Pᵀ Q`` (b · d_out · d_in'); the eigendecompositions
only on refresh steps. Memory: the projected signals, as large as the signals themselves.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jaxtyping import Array

from ..precision import float64_scope, to_float64
from ..routes.base import DenseUse
from .base import trainable
from .kronecker_hig import BlockSpectrum, KroneckerPower, dense_signals, kept_power, kronecker_factors, layer_gradient
from .method import AbstractControl, AbstractOptaxMethod

_F64 = 8


def _with_bias(a: Array, bias: bool) -> Array:
    return jnp.concatenate([a, jnp.ones((a.shape[0], 1), a.dtype)], axis=1) if bias else a


def corrected_eigenvalues(D: Array, a: Array, q_g: Array, q_a: Array, bias: bool) -> Array:
    """``Λ_ij = Σ_{s,k} (U_Gᵀ g_{s,k})_i² (U_Aᵀ ā_s)_j²`` (d_out × d_in'): the diagonal of one
    dense layer's exact Gauss–Newton block in the basis ``U_G ⊗ U_A``, from its signals ``D``
    (rows = b · dim y sample-major, d_out), inputs ``a`` (b, d_in) and the bases ``q_g``
    (d_out × d_out) and ``q_a`` (d_in' × d_in')."""
    b = a.shape[0]
    P = jnp.sum(((D @ q_g) ** 2).reshape(b, -1, q_g.shape[1]), axis=1)  # (b, d_out)
    Q = (_with_bias(a, bias) @ q_a) ** 2  # (b, d_in')
    return P.T @ Q


def corrected_direction(D: Array, a: Array, g: Array, q_g: Array, q_a: Array, bias: bool, power: float,
                        truncation: float, damping: float) -> tuple[Array, BlockSpectrum]:  # fmt: skip
    """``U_G [φ(Λ) ⊙ (U_Gᵀ ∇W̄ U_A)] U_Aᵀ`` (d_out × d_in') for one dense layer: the power of
    its corrected eigenvalues (:func:`corrected_eigenvalues`) in the kept basis applied to
    its gradient; the bias, if any, is the last column."""
    lam = corrected_eigenvalues(D, a, q_g, q_a, bias)
    phi, spectrum = kept_power(lam, power, truncation, damping)
    grad = layer_gradient(D, a, g, bias)
    return q_g @ (phi * (q_g.T @ grad @ q_a)) @ q_a.T, spectrum


def eigenbases(D: Array, a: Array, bias: bool) -> tuple[Array, Array]:
    """``(U_G, U_A)``: the eigenvectors of this batch's factors ``G = DᵀD`` and ``A = ĀᵀĀ``."""
    A, G = kronecker_factors(D, a, bias)
    return jnp.linalg.eigh(G)[1], jnp.linalg.eigh(A)[1]


class Eigenbases(NamedTuple):
    """:class:`KeptEigenbasis`' state: per parameter leaf the ``(left, right)`` bases (None
    for leaves that are not 2-D; module docstring for the layout), and the steps taken."""

    bases: tuple
    count: Array


class KeptEigenbasis(AbstractControl):
    """The Kronecker eigenbases of a :class:`KroneckerPower` rule's dense layers, kept as
    state and refreshed from the batch's factors every ``basis_every`` steps; each step the
    layer's direction is the power of the corrected eigenvalues in them (module docstring).

    The bases are stored in the parameters' dtype and used in float64, as the rule's factors.
    Stats: ``refreshed`` (1 when this step recomputed the bases).
    """

    basis_every: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if self.basis_every < 1:
            raise ValueError(f"basis_every must be >= 1, got {self.basis_every}")

    def init(self, params):
        bases = []
        for leaf in jax.tree.leaves(params):
            if leaf.ndim != 2 or jnp.iscomplexobj(leaf):
                bases.append(None)
            else:
                bases.append(tuple(jnp.eye(n + 1, dtype=leaf.dtype) for n in leaf.shape))
        return Eigenbases(tuple(bases), jnp.zeros((), jnp.int32))

    def direct(self, rule, objective, params, batch, state, acceptance):
        if not isinstance(rule, KroneckerPower):
            raise ValueError(f"a kept Kronecker eigenbasis needs a KroneckerPower rule, got {type(rule).__name__}")
        bases = list(state.bases)
        leaves = jax.tree.leaves(params)
        refresh = state.count % self.basis_every == 0

        # Called by the rule once per dense layer while it traces (float64 D, a, g); the
        # refreshed bases are collected here and become the state after the step.
        def dense(use: DenseUse, D, a, g):
            bias = use.bias is not None
            if bases[use.leaf] is None:
                raise ValueError(f"ekhig: dense layer leaf {use.leaf} is not a 2-D parameter")
            # W @ x keeps U_G left and U_A right; x @ W (W stored d_in × d_out) the other way round.
            g_side, a_side = (1, 0) if use.transposed else (0, 1)
            n_g, n_a = D.shape[1], use.d_in + bias
            slots = list(bases[use.leaf])
            old = (slots[g_side][:n_g, :n_g].astype(D.dtype), slots[a_side][:n_a, :n_a].astype(D.dtype))
            q_g, q_a = jax.lax.cond(refresh, lambda: eigenbases(D, a, bias), lambda: old)
            dtype = leaves[use.leaf].dtype
            slots[g_side] = slots[g_side].at[:n_g, :n_g].set(q_g.astype(dtype))
            slots[a_side] = slots[a_side].at[:n_a, :n_a].set(q_a.astype(dtype))
            bases[use.leaf] = tuple(slots)
            return corrected_direction(D, a, g, q_g, q_a, bias, rule.power, rule.truncation, rule.damping)

        direction, stats = rule.directions(objective, params, batch, dense)
        return direction, {**stats, "refreshed": refresh.astype(jnp.int32)}, Eigenbases(tuple(bases), state.count + 1)


class EigenCorrectedKronecker(AbstractOptaxMethod):
    """Eigenvalue-corrected Kronecker-factored HIG (module docstring): a final class that
    fills :class:`AbstractOptaxMethod`'s fields with a :class:`KroneckerPower` rule (its
    power, truncation, damping and leftover block apply), the optimizer and the
    :class:`KeptEigenbasis` control. The state is :class:`physgrad.methods.MethodState`
    ``(optimizer, None, Eigenbases)``.

    Fields:
        rule: the :class:`KroneckerPower` rule.
        optimizer: applies the direction (``optax.sgd(η)``: HIG's step).
        basis_every: steps between recomputing the eigenbases (1: every step).
    """

    rule: KroneckerPower
    optimizer: optax.GradientTransformation = eqx.field(static=True, default=optax.sgd(1.0))
    basis_every: int = eqx.field(static=True, default=1)
    acceptance: None = eqx.field(default=None, init=False)
    extras: tuple[str, ...] = eqx.field(static=True, default=("value",), init=False)

    @property
    def control(self) -> KeptEigenbasis:
        return KeptEigenbasis(self.basis_every)

    def __check_init__(self):
        _ = self.control  # KeptEigenbasis checks the period

    def footprint(self, objective, params, batch, devices=1):
        """KHIG's, plus the projected signals and inputs (float64) and the kept bases."""
        arrays, static = trainable(params)
        objective = objective.bind_static(static)
        plan = self.rule.plan(objective, arrays, batch)
        b = jax.tree.leaves(batch)[0].shape[0]
        dense = plan.structure.dense
        projected = (plan.rows * sum(u.d_out for u in dense) + b * sum(u.d_in + 1 for u in dense)) * _F64
        kept = sum(u.d_out**2 + (u.d_in + 1) ** 2 for u in dense) * _F64
        return self.rule.footprint(objective, arrays, batch, devices) + projected + kept


def layer_corrections(predict, params, batch) -> list[tuple[int, Array, Array, Array]]:
    """``[(weight leaf, U_G, U_A, Λ)]`` for every dense layer that KHIG sees in ``predict``,
    with this batch's bases, computed as the method computes them (float64; for inspection
    and tests). ``params``: arrays only."""
    structure, block = dense_signals(predict, params, batch)
    out = []
    with float64_scope():
        for use, D, a in zip(structure.dense, block.D, block.A):
            D, a = to_float64(D), to_float64(a)
            q_g, q_a = eigenbases(D, a, use.bias is not None)
            out.append((use.leaf, q_g, q_a, corrected_eigenvalues(D, a, q_g, q_a, use.bias is not None)))
    return out


__all__ = ["EigenCorrectedKronecker", "Eigenbases", "KeptEigenbasis", "corrected_eigenvalues", "layer_corrections"]
