"""Kronecker-factored half-inverse gradients (KHIG): HIG's scaling under K-FAC's factors.

Sources: Schnell, Holl & Thuerey, *Half-Inverse Gradients for Physical Deep Learning*,
ICLR 2022 (the update and its truncation); Martens & Grosse, *Optimizing Neural Networks
with Kronecker-factored Approximate Curvature*, ICML 2015 (the factors). physgrad's own
combination of the two (issue 34 of the project).

HIG as a power of the Gauss–Newton matrix
-----------------------------------------
With ``J = U Σ Vᵀ`` the joint per-sample Jacobian of the simulator outputs (rows = b · dim y,
sample-major; columns = parameters) and ``g = ∂L/∂y`` the output gradient of the batch-mean
loss, ``Jᵀ g`` is the ordinary gradient and, on the row space of J,

    V Σ^κ Uᵀ g = (JᵀJ)^p Jᵀ g,        κ = 2p + 1,

since ``(JᵀJ)^p Jᵀ g = V Σ^{2p} Vᵀ V Σ Uᵀ g`` (powers of the kept eigenvalues only, the
pseudo-inverse's convention). HIG (κ = −½) is ``p = −¾``; Gauss–Newton (κ = −1) is
``p = −1``; ``p = −½`` gives κ = 0, ``V Uᵀ g``, every kept direction at unit scale.

The Kronecker factors
---------------------
A dense layer ``z = W a + c`` (W: d_out × d_in; the bias folded in as a last column of
``W̄ = [W c]`` acting on ``ā = [a; 1]``) applied once per sample has the Jacobian rows
``D_i ⊗ ā_iᵀ`` for sample i, with ``D_i = ∂y_i/∂z_i`` (dim y × d_out) the simulator output's
derivative with respect to the layer's pre-activations. Its block of ``JᵀJ`` is
``Σ_i D_iᵀD_i ⊗ ā_iā_iᵀ`` (row-major vec of W̄), which K-FAC's independence assumption
replaces by the product of the sums divided by the batch size,

    JᵀJ|_layer ≈ (1/b) G ⊗ A,   G = Σ_i D_iᵀ D_i  (d_out × d_out),   A = Σ_i ā_i ā_iᵀ  (d_in' × d_in'),

d_in' = d_in + 1 with a bias. Every layer is its own block (block-diagonal over layers, as
K-FAC), so with the eigendecompositions ``G = Q_G diag(γ) Q_Gᵀ`` and ``A = Q_A diag(α) Q_Aᵀ``
the layer's update is

    ΔW̄ = Q_G [ φ(γ αᵀ / b) ⊙ (Q_Gᵀ ∇W̄ Q_A) ] Q_Aᵀ,      φ(λ) = (λ + δ)^p,

with ``∇W̄ = Σ_i (D_iᵀ g_i) ā_iᵀ`` the layer's gradient; without damping and truncation this
is ``b^{−p} G^p ∇W̄ A^p``: two eigendecompositions of d_out and d_in' wide per layer instead
of HIG's one of min(b · dim y, P) wide.

Truncation and damping
----------------------
HIG drops singular values σ ≤ τ σ_max; the eigenvalue products ``λ = γ_j α_k / b`` stand for
σ² (exactly so where the factorisation is exact), so KHIG drops ``λ ≤ τ² λ_max``, with
``λ_max`` the largest product *of that layer's block* (each block is truncated relative to
its own top). The same τ thus means the same on both rules. Damping ``δ = damping · λ_max``
is relative to the block's top, as Levenberg–Marquardt's ``λ = μ σ_max²`` in physgrad.
The default ``damping = 1e-4`` is needed off the exact case: the Kronecker product's
spectrum ``γ_j α_k`` spans the product of the two factors' condition numbers, far below
the smallest σ² of J itself (on the oscillators at batch 16, J keeps 64 singular values
above τ = 1e-6 where the factors keep 891 products), and ``p < 0`` turns those tiny products
into huge steps; with ``damping = 0`` KHIG diverges there at HIG's η = 1.

When it is exact, and when it is not
------------------------------------
The factorisation is exact when the network's only trainable parameters are one dense
layer and ``D_i`` is the same for every sample (linear physics after a linear layer, the
same for all samples): then ``Σ_i D_iᵀD_i ⊗ ā_iā_iᵀ = (1/b) G ⊗ A`` and KHIG equals HIG
to rounding. Otherwise it approximates HIG twice: (1) across layers, the cross-layer blocks
of ``JᵀJ`` are dropped (each layer is scaled by its own spectrum, not the joint one);
(2) within a layer, the correlation between ``D_iᵀD_i`` and ``ā_iā_iᵀ`` over samples is
dropped (nonlinear networks or simulators, sample-dependent physics).

What it sees
------------
Dense layers are found in the traced per-sample program as physgrad's structured
half-inverse route finds them (:func:`physgrad.routes.find_structure`: any parameter
matrix used once in a ``W @ x`` or ``x @ W`` with a vector, ``eqx.nn.Linear``,
:class:`physgrad.nets.Dense`, hand-written), with a bias added right after the product
folded in. Every other parameter (a weight used twice, a free scale, a layer hidden inside
a nested ``jit``) joins one leftover block handled *exactly*: the κ-power of its own
explicit Jacobian rows ``J_o``, ``(J_oᵀJ_o)^p J_oᵀ g``, through the eigendecomposition of
the smaller of ``J_oᵀJ_o`` and ``J_oJ_oᵀ``; it is refused in one line when that matrix is
wider than ``explicit_max``. Convolution layers (``eqx.nn.Conv``, the U-Nets' and ResNets'
kernels, strided, dilated, transposed, zero or circular padding) get the Kronecker factors
of Grosse & Martens 2016, with the kernel reshaped (out, in·k₁⋯k_d) as the dense weight and
``b·T`` (T output positions per sample) in place of b (:mod:`physgrad.methods.conv_factors`);
a kernel shared by several convolutions (a network unrolled over time steps) is one layer
whose uses are more positions (uses assumed independent, as K-FAC for recurrent networks'
simplest option); grouped convolutions are refused in one line. ``probes = s > 0``
estimates every G from s random output directions per sample instead of every output row
(K-FAC's Monte Carlo way; for fields of outputs, where a backward pass per row costs as much
as exact HIG's Jacobian).

Cost: one backward pass per Jacobian row to the pre-activations (the same signals ``D``
HIG's structured route uses), ``rows · d_out²`` and ``b · d_in'²`` multiply-adds for the
factors, and two float64 ``eigh`` of d_out and d_in' per layer, same-size factors stacked
into one ``eigh`` call per size on an accelerator (``eigh_batched``). The factors are fresh for
every batch (HIG's way); :class:`AveragedKronecker` keeps running averages of them and
recomputes their eigendecompositions every k steps (K-FAC's way;
:mod:`physgrad.methods.averaged_kronecker`). The factors and their eigendecompositions are computed in float64
(``A`` and ``G`` square the conditioning of the activations and the signals, as the Gram
matrix does in HIG's Gram route) and the direction is cast back to each leaf's dtype.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from ..precision import float64_scope, to_float64
from ..routes import JointJacobian, structured
from ..routes.base import DenseUse, Structure
from ..routes.structured import explicit_rows
from . import conv_factors as kfc
from . import layer_terms
from .base import AbstractJacobianRule, Estimator, Objective, required
from .conv_program import unrolled_structure

_F64 = 8


class BlockSpectrum(NamedTuple):
    """What one block's truncation kept: the count, the largest eigenvalue product λ_max
    and the smallest kept one (``inf`` when none is kept)."""

    rank: Array
    top: Array
    bottom_kept: Array


def kept_power(lam: Array, power: float, truncation: float, damping: float) -> tuple[Array, BlockSpectrum]:
    """``φ(λ) = (λ + δ)^p`` where ``λ > τ² λ_max``, else 0 (dropped, not clamped), with
    ``δ = damping · λ_max``; and the block's :class:`BlockSpectrum`. ``lam ≥ 0`` (any shape)
    are eigenvalues of a curvature block (σ² in HIG's terms)."""
    lam = jnp.maximum(lam, 0.0)  # eigh's rounding may leave tiny negatives for zero eigenvalues
    top = jnp.max(lam)
    keep = lam > truncation**2 * top
    # Guard the power before the `where`: 0**negative would leak inf/NaN.
    safe = jnp.where(keep, lam, jnp.ones_like(lam))
    values = jnp.where(keep, (safe + damping * top) ** power, jnp.zeros_like(lam))
    bottom = jnp.min(jnp.where(keep, lam, jnp.inf))
    return values, BlockSpectrum(jnp.sum(keep).astype(jnp.int32), top, bottom)


def kronecker_factors(D: Array, a: Array, bias: bool) -> tuple[Array, Array]:
    """``(A, G)`` of one dense layer: ``A = Σ_i ā_i ā_iᵀ`` (d_in' × d_in', ā = [a; 1] with a
    bias) from its inputs ``a`` (b, d_in), and ``G = Σ_i D_iᵀ D_i = DᵀD`` (d_out × d_out) from
    its back-propagated signals ``D`` (rows, d_out), every sample's rows stacked. Sums, not
    means: the layer's Gauss–Newton block is approximated by ``(1/b) G ⊗ A``."""
    a = _with_bias(a, bias)
    return a.T @ a, D.T @ D


def _with_bias(a: Array, bias: bool) -> Array:
    return jnp.concatenate([a, jnp.ones((a.shape[0], 1), a.dtype)], axis=1) if bias else a


def layer_gradient(D: Array, a: Array, g: Array, bias: bool) -> Array:
    """``∇W̄ = Σ_i (D_iᵀ g_i) ā_iᵀ`` (d_out × d_in'): the layer's gradient of the batch loss
    from its signals ``D`` (rows, d_out), inputs ``a`` (b, d_in) and the output gradient ``g``
    (rows,); each sample's signals weighted by its output gradient."""
    b, d_out = a.shape[0], D.shape[1]
    weighted = (D * g[:, None]).reshape(b, -1, d_out).sum(axis=1)  # (b, d_out)
    return weighted.T @ _with_bias(a, bias)


def power_direction(grad: Array, gamma: Array, q_g: Array, alpha: Array, q_a: Array, b: int, power: float,
                    truncation: float, damping: float) -> tuple[Array, BlockSpectrum]:  # fmt: skip
    """``Q_G [φ(γαᵀ/b) ⊙ (Q_Gᵀ ∇W̄ Q_A)] Q_Aᵀ`` from the factors' eigendecompositions
    ``G = Q_G diag(γ) Q_Gᵀ`` and ``A = Q_A diag(α) Q_Aᵀ``."""
    phi, spectrum = kept_power(jnp.outer(gamma, alpha) / b, power, truncation, damping)
    return q_g @ (phi * (q_g.T @ grad @ q_a)) @ q_a.T, spectrum


def dense_block_direction(D: Array, a: Array, g: Array, bias: bool, power: float, truncation: float,
                          damping: float) -> tuple[Array, BlockSpectrum]:  # fmt: skip
    """``ΔW̄ = Q_G [φ(γαᵀ/b) ⊙ (Q_Gᵀ ∇W̄ Q_A)] Q_Aᵀ`` (d_out × d_in') for one dense layer from
    its signals ``D`` (rows, d_out), inputs ``a`` (b, d_in) and the output gradient ``g``
    (rows,), with this batch's factors; the bias, if any, is the last column."""
    A, G = kronecker_factors(D, a, bias)
    alpha, q_a = jnp.linalg.eigh(A)
    gamma, q_g = jnp.linalg.eigh(G)
    return power_direction(layer_gradient(D, a, g, bias), gamma, q_g, alpha, q_a, a.shape[0], power, truncation,
                           damping)  # fmt: skip


def explicit_block_direction(J: Array, g: Array, power: float, truncation: float,
                             damping: float) -> tuple[Array, BlockSpectrum]:  # fmt: skip
    """``(J_oᵀJ_o)^p J_oᵀ g`` (P_o,) exactly, from the eigendecomposition of the smaller of
    ``J_oᵀJ_o`` and ``J_oJ_oᵀ`` (the same nonzero eigenvalues σ²):
    ``Q φ(Λ) Qᵀ J_oᵀ g`` or ``J_oᵀ U φ(Λ) Uᵀ g``."""
    rows, size = J.shape
    if size <= rows:
        lam, q = jnp.linalg.eigh(J.T @ J)
        phi, spectrum = kept_power(lam, power, truncation, damping)
        return q @ (phi * (q.T @ (J.T @ g))), spectrum
    lam, u = jnp.linalg.eigh(J @ J.T)
    phi, spectrum = kept_power(lam, power, truncation, damping)
    return J.T @ (u @ (phi * (u.T @ g))), spectrum


class Plan(NamedTuple):
    """What KHIG does for these shapes: the program's structure (one explicit group
    holding every leftover leaf), the leftover block's size and the convolution layers."""

    structure: Structure
    explicit: tuple[int, ...]
    explicit_parameters: int
    rows: int
    jacobian: JointJacobian  # the step's shape facts (one trace of predict)
    convs: tuple[kfc.ConvUse, ...] = ()


DenseDirection = Callable[[DenseUse, Array, Array, Array], tuple[Array, BlockSpectrum]]


class KroneckerPower(AbstractJacobianRule):
    """Per dense layer ``ΔW̄ = φ(G, A) ∇W̄``: the power ``p`` of K-FAC's block ``(1/b) G ⊗ A``
    of ``JᵀJ`` applied to the gradient (p = −¾: HIG's κ = −½; p = −1: Gauss–Newton), the
    leftover parameters' block exactly. See :mod:`physgrad.methods.kronecker_hig`."""

    power: float = eqx.field(static=True, default=-0.75)
    truncation: float = eqx.field(static=True, default=1e-6)
    damping: float = eqx.field(static=True, default=1e-4)
    explicit_max: int = eqx.field(static=True, default=1024)
    probes: int = eqx.field(static=True, default=0)
    # None: stacked off a CPU (one launch per size on an accelerator), one call per factor on
    # a CPU, where XLA's stacked eigh measured no faster (benchmarks/khig_conv_step.py)
    eigh_batched: bool | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if not self.truncation >= 0:
            raise ValueError(f"truncation must be >= 0, got {self.truncation}")
        if not self.damping >= 0:
            raise ValueError(f"damping must be >= 0, got {self.damping}")
        if not self.power < 0:
            raise ValueError(f"power must be negative (-0.75: HIG, -1: Gauss-Newton), got {self.power}")
        if self.explicit_max < 0:
            raise ValueError(f"explicit_max must be >= 0, got {self.explicit_max}")
        if self.probes < 0:
            raise ValueError(f"probes must be >= 0 (0: every output row), got {self.probes}")

    name: ClassVar[str] = "khig"

    def plan(self, objective: Objective, params: PyTree, batch: PyTree) -> Plan:
        """The dense layers and the leftover block for these shapes, or a one-line
        ``ValueError`` for what KHIG refuses (complex parameters, grouped convolutions, a
        kernel leaf read other than as convolution kernels, a leftover block wider than
        ``explicit_max``)."""
        leaves = jax.tree.leaves(params)
        if any(jnp.iscomplexobj(x) for x in leaves):
            raise ValueError("khig: complex parameters have no real Kronecker factors; use hig")
        required(objective.predict, "predict")
        jacobian = JointJacobian.of(objective, params, batch)
        rows = jacobian.rows
        # Convolutions inside nested calls or scans inlined (an unrolled network's steps), and
        # one explicit group: the leftover block is one Jacobian of all its leaves.
        sample = jax.tree.map(lambda a: a[0], batch)
        structure = unrolled_structure(jacobian.structure, params, sample).regrouped(rows, 2**62)
        convs = kfc.find_convolutions(structure)
        layers = {c.leaf for c in convs} | {c.bias for c in convs if c.bias is not None}
        explicit = tuple(k for group in structure.groups for k in group if k not in layers)
        structure = structure._replace(groups=(explicit,) if explicit else ())
        size = sum(structure.leaf_sizes[k] for k in explicit)
        if explicit and min(rows, size) > self.explicit_max:
            raise ValueError(
                f"khig: {size} parameters are outside the dense layers it sees and their exact block needs an "
                f"eigendecomposition of {min(rows, size)} > explicit_max={self.explicit_max}; use hig, or raise "
                "explicit_max"
            )
        return Plan(structure, explicit, size, rows, jacobian, convs)

    def describe(self, objective, params, batch):
        """``{"dense": [(d_out, d_in', bias), …], "conv": [(d_out, d_in', positions), …],
        "explicit_parameters": P_o, "jacobian": (rows, P)}`` for these shapes (nothing is computed)."""
        plan = self.plan(objective, params, batch)
        dense = [(u.d_out, u.d_in + (u.bias is not None), u.bias is not None) for u in plan.structure.dense]
        conv = [(c.d_out, c.d_in + (c.bias is not None), c.positions) for c in kfc.conv_layers(plan.convs)]
        return {"dense": dense, "conv": conv, "explicit_parameters": plan.explicit_parameters,
                "jacobian": plan.jacobian.shape}  # fmt: skip

    def footprint(self, objective, params, batch, devices=1):
        plan = self.plan(objective, params, batch)
        b = jax.tree.leaves(batch)[0].shape[0]
        itemsize = max((jnp.dtype(x.dtype).itemsize for x in jax.tree.leaves(params)), default=4)
        dense = plan.structure.dense
        d_out, d_in = sum(u.d_out for u in dense), sum(u.d_in + 1 for u in dense)
        signals = (plan.rows * (d_out + plan.explicit_parameters) + b * d_in) * (itemsize + _F64)
        # factors, their eigenvectors and eigh's workspace; the leftover block's Gram likewise
        squares = sum(u.d_out**2 + (u.d_in + 1) ** 2 for u in dense) * 3 * _F64
        leftover = 3 * min(plan.rows, plan.explicit_parameters) ** 2 * _F64 if plan.explicit else 0
        if plan.convs or self.probes:  # signals per cotangent (rows or probes) on every layer, and patches
            c = self.probes or plan.rows // b
            z = sum(u.d_out for u in dense) + sum(u.d_out * u.positions for u in plan.convs)
            patches = sum(u.positions * (u.d_in + 1) for u in plan.convs)
            signals += ((c + 1) * b * z + b * patches) * (itemsize + _F64)
            squares += sum(u.d_out**2 + (u.d_in + 1) ** 2 for u in kfc.conv_layers(plan.convs)) * 3 * _F64
        return signals + squares + leftover

    def footprint_note(self, objective, params, batch):
        plan = self.plan(objective, params, batch)
        widths = "+".join(str(u.d_out) for u in plan.structure.dense) or "0"
        convs = f", {len(kfc.conv_layers(plan.convs))} convolution layers" if plan.convs else ""
        return f"khig: {plan.rows} rows × ({widths}) signals{convs}, {plan.explicit_parameters} leftover parameters"

    def __call__(self, objective, params, batch):
        return self.directions(objective, params, batch)

    def directions(self, objective, params, batch, dense: DenseDirection | None = None):
        """``(direction, stats)``, each dense layer's ``ΔW̄`` from ``dense(use, D, a, g)`` (float64
        signals, inputs and output gradient; returns ``(ΔW̄, BlockSpectrum)``), by default
        the power of this batch's factors (:func:`dense_block_direction`); convolution layers
        from their KFC factors; the leftover block exactly."""
        plan = self.plan(objective, params, batch)
        if plan.convs or self.probes:
            if dense is not None:
                raise ValueError("khig: a per-layer direction hook covers dense layers with every output row; "
                                 "convolution layers and probes take khig's own factors (fresh, or running averages)")  # fmt: skip
            return self._signal_directions(plan, params, batch)
        structure = plan.structure
        block, y = structured.factors(structure, params, batch, groups=(0,) if plan.explicit else ())
        loss, g = plan.jacobian.loss_and_gradient(y)
        # Constants for differentiation: the float64 scope below cannot be transposed.
        block, g = jax.lax.stop_gradient((block, g))
        with float64_scope():
            g64 = to_float64(g)
            layers = [(use, to_float64(D), to_float64(a)) for use, D, a in zip(structure.dense, block.D, block.A)]
            if dense is None:
                factors = [kronecker_factors(D, a, use.bias is not None) for use, D, a in layers]
                eig = kfc.eigh_all([m for pair in factors for m in pair], self._stacked)
                deltas = [self._power(layer_gradient(D, a, g64, use.bias is not None), eig, k, a.shape[0])
                          for k, (use, D, a) in enumerate(layers)]  # fmt: skip
            else:
                deltas = [dense(use, D, a, g64) for use, D, a in layers]
            J = None if block.J is None else to_float64(block.J)
            return self._assemble(plan, params, deltas, [], J, g64, loss, y.dtype)

    @property
    def _stacked(self) -> bool:
        return self.eigh_batched if self.eigh_batched is not None else jax.default_backend() != "cpu"

    def _power(self, grad: Array, eig: list, k: int, count: int) -> tuple[Array, BlockSpectrum]:
        """Layer k's power direction from ``eig``, the eigendecompositions (A₀, G₀, A₁, G₁, …)."""
        (alpha, q_a), (gamma, q_g) = eig[2 * k], eig[2 * k + 1]
        return power_direction(grad, gamma, q_g, alpha, q_a, count, self.power, self.truncation, self.damping)

    def _signal_directions(self, plan: Plan, params, batch):
        """Dense and convolution layers from the signals of one pass per cotangent (every
        output row, or ``probes`` random ones: :func:`~physgrad.methods.layer_terms.layer_curvature`)."""
        structure, dense = plan.structure, plan.structure.dense
        layers, y, loss, g = layer_terms.layer_curvature(structure, dense, plan.convs, params, batch,
                                                         plan.jacobian.loss_and_gradient, self.probes)  # fmt: skip
        J = explicit_rows(plan.jacobian.predict, structure, params, batch, 0) if plan.explicit else None
        J = jax.lax.stop_gradient(J)
        with float64_scope():
            eig = kfc.eigh_all([to_float64(m) for A, G, _, _ in layers for m in (A, G)], self._stacked)
            deltas = [self._power(to_float64(grad), eig, k, count) for k, (_, _, grad, count) in enumerate(layers)]
            J64 = None if J is None else to_float64(J)
            return self._assemble(plan, params, deltas[: len(dense)], deltas[len(dense) :], J64, to_float64(g),
                                  loss, y.dtype)  # fmt: skip

    def _assemble(self, plan: Plan, params, dense: list, conv: list, J: Array | None, g64: Array, loss, dtype):
        """The direction with the parameters' structure and the step's stats from the layers'
        ``(ΔW̄, spectrum)`` and the leftover rows ``J`` (float64; in a float64 scope)."""
        structure, leaves = plan.structure, jax.tree.leaves(params)
        pieces: dict[int, Array] = {}
        spectra = [s for _, s in dense + conv]
        for use, (delta, _) in zip(structure.dense, dense):
            weight = delta[:, : use.d_in]
            pieces[use.leaf] = (weight.T if use.transposed else weight).astype(leaves[use.leaf].dtype)
            if use.bias is not None:
                pieces[use.bias] = delta[:, use.d_in].astype(leaves[use.bias].dtype)
        for layer, (delta, _) in zip(kfc.conv_layers(plan.convs), conv):
            use = layer.uses[0]  # every use computes the same kernel from the leaf (find_convolutions)
            kernel = kfc.kernel_matrix(structure, use, delta[:, : use.d_in]).astype(leaves[use.leaf].dtype)
            pieces[use.leaf] = kfc.kernel_pullback(structure, use, jax.lax.stop_gradient(leaves[use.leaf]), kernel)
            if use.bias is not None:
                pieces[use.bias] = delta[:, use.d_in].reshape(leaves[use.bias].shape).astype(leaves[use.bias].dtype)
        if plan.explicit:
            assert J is not None  # the explicit rows of group 0: every leftover leaf
            flat, spectrum = explicit_block_direction(J, g64, self.power, self.truncation, self.damping)
            offset = 0
            for k in plan.explicit:
                size = structure.leaf_sizes[k]
                pieces[k] = flat[offset : offset + size].reshape(leaves[k].shape).astype(leaves[k].dtype)
                offset += size
            spectra.append(spectrum)
        stats = _spectrum_stats(spectra, dtype)
        direction = [pieces.get(k, jnp.zeros_like(x)) for k, x in enumerate(leaves)]
        return jax.tree.unflatten(jax.tree.structure(params), direction), {"loss": loss, **stats}


class LayerFactors(NamedTuple):
    """One dense layer's Kronecker factors (float64): the parameter leaves it covers (by
    their index in ``jax.tree.leaves(params)``), ``A`` (d_in' × d_in') and ``G`` (d_out × d_out)."""

    weight: int
    bias: int | None
    A: Array
    G: Array


def dense_signals(predict, params: PyTree, batch: PyTree):
    """``(structure, block)``: the dense layers :func:`kronecker_hig` sees in ``predict`` and
    their back-propagated signals D and inputs A for this batch (gradient stopped), as the rule
    computes them; what :func:`layer_factors` and the eigenvalue-corrected form inspect."""
    structure = JointJacobian.of(Objective(predict), params, batch).structure
    block, _ = structured.factors(structure, params, batch, groups=())
    return structure, jax.lax.stop_gradient(block)


def layer_factors(predict, params: PyTree, batch: PyTree) -> list[LayerFactors]:
    """The Kronecker factors ``A = Σ_i ā_i ā_iᵀ`` and ``G = Σ_i D_iᵀ D_i`` of every dense layer
    that :func:`kronecker_hig` sees in ``predict`` for this batch (``params``: arrays only),
    in program order; for inspection and tests, computed as the rule computes them."""
    structure, block = dense_signals(predict, params, batch)
    out = []
    with float64_scope():
        for use, D, a in zip(structure.dense, block.D, block.A):
            A, G = kronecker_factors(to_float64(D), to_float64(a), use.bias is not None)
            out.append(LayerFactors(use.leaf, use.bias, A, G))
    return out


def _spectrum_stats(spectra: list[BlockSpectrum], dtype) -> dict[str, Array]:
    """``rank`` (eigenvalue products kept, all blocks), ``sigma_max`` (√ of the largest
    block top) and ``sigma_min_kept`` (√ of the smallest kept product): HIG's statistics,
    with σ² read as the eigenvalue products."""
    if not spectra:
        raise ValueError("khig: the network has no parameters")
    rank = sum(s.rank for s in spectra)
    top = jnp.max(jnp.stack([s.top for s in spectra]))
    bottom = jnp.min(jnp.stack([s.bottom_kept for s in spectra]))
    return {"rank": jnp.asarray(rank, jnp.int32), "sigma_max": jnp.sqrt(top).astype(dtype),
            "sigma_min_kept": jnp.sqrt(bottom).astype(dtype)}  # fmt: skip


def kronecker_hig(predict, loss, *, truncation: float = 1e-6, power: float = -0.75, damping: float = 1e-4,
                  explicit_max: int = 1024, probes: int = 0) -> Estimator:  # fmt: skip
    """Kronecker-factored half-inverse gradients: ``(params, batch) -> (direction, stats)``.

    Per dense layer ``z = W a + c`` (bias folded in as ``W̄ = [W c]``, ``ā = [a; 1]``)

        ΔW̄ = b^{−p} G^p ∇W̄ A^p,   G = Σ_i D_iᵀ D_i,   A = Σ_i ā_i ā_iᵀ,

    the power ``p`` of K-FAC's block ``(1/b) G ⊗ A`` of the Gauss–Newton matrix ``JᵀJ`` applied
    to the layer's gradient, with ``D_i = ∂y_i/∂z_i`` the simulator output's derivative with
    respect to the layer's pre-activations. ``p = −¾`` is HIG's ``V Σ^{−½} Uᵀ g = (JᵀJ)^{−¾} Jᵀ g``
    and equals :func:`physgrad.hig` where the Gauss–Newton block is exactly Kronecker (one
    dense layer, linear physics shared by the samples); ``p = −1`` is Kronecker-factored
    Gauss–Newton. Apply with ``optax.sgd(η)`` (HIG's η) or any chain, as :func:`physgrad.hig`.

    Arguments:
        predict: ``predict(params, sample) -> y``, network and simulator for one sample.
        loss: ``loss(y, sample) -> L_i``; the rule uses the batch mean.
        truncation: τ as in :func:`physgrad.hig`: eigenvalue products ``λ ≤ τ² λ_max`` of a
            block are dropped (λ stands for σ²), λ_max the block's largest.
        power: ``p`` (−¾: HIG; −1: Gauss–Newton; −½: every kept direction at unit scale).
        damping: ``δ/λ_max``: the kept products are raised as ``(λ + δ)^p``, δ relative to
            the block's largest product. 0 is the pure analogue of HIG (equal to it where
            the factorisation is exact); off that case the products of the factors' small
            eigenvalues reach far below J's own spectrum and, raised to ``p``, blow up the
            step (the oscillators diverge at HIG's η = 1), so the default damps them (1e-4).
        explicit_max: the widest eigendecomposition allowed for the parameters outside the
            dense and convolution layers it sees (handled exactly as one block; refused beyond).
        probes: 0 builds every G from every simulator output row (a backward pass each);
            ``s > 0`` from s Rademacher output directions per sample (K-FAC's Monte Carlo
            estimate, unbiased; for outputs that are fields, as the U-Nets').

    ``stats``: ``loss``; ``rank``, the eigenvalue products kept over all blocks;
    ``sigma_max`` and ``sigma_min_kept``, √ of the largest and of the smallest kept product
    (HIG's σ range). A convolution layer is factored as Grosse & Martens (KFC) do: its
    kernel reshaped (out, in·k₁⋯k_d) as W, its input patches as ā and ``b·T`` (T output
    positions) in place of b (:mod:`physgrad.methods.conv_factors`). See
    :mod:`physgrad.methods.kronecker_hig` for the derivation and its assumptions.
    """
    rule = KroneckerPower(power, truncation, damping, explicit_max, probes)
    return Estimator(rule, Objective(predict, loss))


def __getattr__(name: str):
    # The averaged method moved to its own module (issue 52); the old path works for one release.
    if name in ("AveragedKronecker", "KroneckerAverages"):
        import warnings

        from . import averaged_kronecker

        warnings.warn(f"physgrad.methods.kronecker_hig.{name} moved to physgrad.methods.averaged_kronecker.{name}",
                      DeprecationWarning, stacklevel=2)  # fmt: skip
        return getattr(averaged_kronecker, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
