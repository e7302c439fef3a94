"""The Gram matrix ``J Jᵀ`` of the joint Jacobian from layer structure, never forming J.

For a dense layer ``z = W a (+ b)`` applied once per sample, the Jacobian row of output
``r`` (sample ``i``) with respect to ``W`` is a Kronecker product ``δ_r ⊗ a_i``, with
``δ_r = ∂y_r/∂z`` the signal back-propagated from output ``r`` to the layer's
pre-activation and ``a_i`` the layer's input for sample ``i``. Two such rows have the
inner product ``(δ_r·δ_s)(a_i·a_j)``, so the layer's share of the Gram matrix is

    G_W = (D Dᵀ) ⊙ (A Aᵀ)⇑,     D: rows × d_out,  A: samples × d_in,

where ``⇑`` repeats the sample-by-sample matrix ``A Aᵀ`` over each sample's output rows.
Every other parameter (biases, convolution kernels, a layer used twice, a custom
module) contributes its explicit Jacobian rows ``J_o``, one group of leaves at a time:

    J Jᵀ = Σ_dense (D Dᵀ) ⊙ (A Aᵀ)⇑ + Σ_groups J_o J_oᵀ.

A bias added right after the product (``z = W a + b``) has the rows ``D`` itself and folds
into its layer's term as ``(D Dᵀ) ⊙ (A Aᵀ + 1)⇑``, at no extra cost.

This is exact (not an approximation like K-FAC's): it is the Gram matrix of the same J,
at the cost of one backward pass per output row to the pre-activations and
``rows² · (Σ d_out + P_explicit)`` multiply-adds instead of ``rows² · P``.

Dense layers are found in the traced program, not by module type: a parameter leaf that
is a matrix used exactly once, as an operand of one ``dot_general`` contracting one of
its axes with a vector, is a dense layer (``eqx.nn.Linear``, :class:`physgrad.nets.Dense`,
a hand-written ``W @ x`` or ``x @ W``). The per-sample program is evaluated by a small
interpreter that adds a zero perturbation ``ε`` to that product's output (``∂y/∂ε = δ``)
and returns its vector operand (``a``).

Source: the Kronecker factorisation of a dense layer's per-example gradient is the basis
of K-FAC (Martens & Grosse 2015) and of per-example gradient norms (Goodfellow 2015);
here it gives the exact Gram matrix that the half-inverse gradient of Schnell, Holl &
Thuerey (ICLR 2022) decomposes.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.extend.core import ClosedJaxpr, Literal
from jaxtyping import Array, PyTree

from .jacobian import flat_output

# Explicit Jacobian rows are formed a group of leaves at a time, each group holding at
# most this many numbers (rows × its parameters), unless a single leaf is larger.
CHUNK_ELEMENTS = 2**26  # 256 MiB of float32


class DenseUse(NamedTuple):
    """A dense layer found in the per-sample program: equation ``eqn`` multiplies
    parameter leaf ``leaf`` (d_out × d_in or d_in × d_out) by the vector operand at
    position ``operand`` of that equation."""

    eqn: int
    leaf: int
    operand: int
    d_in: int
    d_out: int
    transposed: bool  # the leaf is stored (d_in, d_out): ``a @ W``
    bias: int | None = None  # leaf added right after the product (its rows are D itself)


class Structure(NamedTuple):
    """What :func:`find_structure` learnt about ``predict`` at these shapes."""

    jaxpr: ClosedJaxpr  # of (param leaves..., sample leaves...) -> outputs
    dense: tuple[DenseUse, ...]
    groups: tuple[tuple[int, ...], ...]  # explicit leaf indices, one group per Jacobian pass
    leaf_sizes: tuple[int, ...]
    treedef: object
    out_tree: object

    @property
    def explicit_parameters(self) -> int:
        return sum(self.leaf_sizes[k] for group in self.groups for k in group)


def _param_leaves(params):
    # None leaves (the static part of an eqx.partition) stay None: they are not inputs.
    leaves, treedef = jax.tree.flatten(params)
    return leaves, treedef


def find_structure(
    predict: Callable, params: PyTree, sample: PyTree, rows: int, chunk_elements: int = CHUNK_ELEMENTS
) -> Structure:
    """Trace ``predict(params, sample)`` for one sample and find its dense layers.

    ``rows`` is the number of Jacobian rows of the whole batch (to size the explicit
    groups). Only shapes and types are used: ``params`` and ``sample`` may be tracers."""
    leaves, treedef = _param_leaves(params)
    n = len(leaves)
    sample_leaves, sample_tree = jax.tree.flatten(sample)

    def program(*flat):
        return predict(jax.tree.unflatten(treedef, flat[:n]), jax.tree.unflatten(sample_tree, flat[n:]))

    # Traced on the values themselves (tracers inside a jit are fine): under shard_map
    # their types say which are device-varying, and the program records the casts.
    closed, out_shape = jax.make_jaxpr(program, return_shape=True)(*leaves, *sample_leaves)
    jaxpr = closed.jaxpr
    params_vars = {v: k for k, v in enumerate(jaxpr.invars[:n])}
    users: dict = {}  # var -> the equations reading it, once per operand slot
    for e, eqn in enumerate(jaxpr.eqns):
        for v in eqn.invars:
            if not isinstance(v, Literal):
                users.setdefault(v, []).append(e)

    def sole_parameter_use(v) -> bool:
        """``v`` is a parameter leaf read by exactly one operand and not returned."""
        return not isinstance(v, Literal) and v in params_vars and len(users.get(v, ())) == 1 and v not in jaxpr.outvars

    def bias_of(z):
        """The parameter leaf ``b`` of ``z + b`` when that sum is z's only use."""
        if len(users.get(z, ())) != 1 or z in jaxpr.outvars:
            return None
        eqn = jaxpr.eqns[users[z][0]]
        if eqn.primitive.name != "add":
            return None
        other = eqn.invars[1] if eqn.invars[0] is z else eqn.invars[0]
        if not sole_parameter_use(other):
            return None
        return params_vars[other] if other.aval.shape == z.aval.shape and other.aval.dtype == z.aval.dtype else None

    dense = []
    for e, eqn in enumerate(jaxpr.eqns):
        if eqn.primitive.name != "dot_general":
            continue
        (lc, rc), (lb, rb) = eqn.params["dimension_numbers"]
        if lb or rb or len(lc) != 1:
            continue
        for w_pos, a_pos, w_contract, a_contract in ((0, 1, lc[0], rc[0]), (1, 0, rc[0], lc[0])):
            w, a = eqn.invars[w_pos], eqn.invars[a_pos]
            if not sole_parameter_use(w):
                continue
            if w.aval.ndim != 2 or a.aval.ndim != 1 or a_contract != 0 or w is a:
                continue
            d_in = w.aval.shape[w_contract]
            d_out = w.aval.shape[1 - w_contract]
            bias = bias_of(eqn.outvars[0])
            dense.append(DenseUse(e, params_vars[w], a_pos, d_in, d_out, transposed=w_contract == 0, bias=bias))
            break
    dense_leaves = {u.leaf for u in dense} | {u.bias for u in dense if u.bias is not None}
    sizes = tuple(math.prod(x.shape) for x in leaves)
    per_group = max(1, chunk_elements // max(rows, 1))
    groups, current, filled = [], [], 0
    for k in range(n):
        if k in dense_leaves or sizes[k] == 0:
            continue
        if current and filled + sizes[k] > per_group:
            groups.append(tuple(current))
            current, filled = [], 0
        current.append(k)
        filled += sizes[k]
    if current:
        groups.append(tuple(current))
    out_tree = jax.tree.structure(out_shape)
    return Structure(closed, tuple(dense), tuple(groups), sizes, treedef, out_tree)


def _evaluate(structure: Structure, leaves, sample_leaves, eps):
    """Run the per-sample program with ``eps[k]`` added to dense product ``k``'s output;
    return the outputs and the dense layers' vector operands ``a``."""
    jaxpr = structure.jaxpr.jaxpr
    env = {}

    def read(v):
        return v.val if isinstance(v, Literal) else env[v]

    for v, x in zip(jaxpr.constvars, structure.jaxpr.consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, list(leaves) + list(sample_leaves)):
        env[v] = x
    by_eqn = {u.eqn: k for k, u in enumerate(structure.dense)}
    activations = [None] * len(structure.dense)
    for e, eqn in enumerate(jaxpr.eqns):
        invals = [read(v) for v in eqn.invars]
        bind = eqn.primitive.get_bind_params(eqn.params)
        # (subfuns, params) in older JAX, params alone in newer
        subfuns, params = bind if isinstance(bind, tuple) else ((), bind)
        context = getattr(getattr(eqn, "ctx", None), "manager", None) or contextlib.nullcontext()
        with context:
            out = eqn.primitive.bind(*subfuns, *invals, **params)
        if e in by_eqn:
            k = by_eqn[e]
            activations[k] = invals[structure.dense[k].operand]
            out = out + eps[k]
        if eqn.primitive.multiple_results:
            for v, x in zip(eqn.outvars, out):
                env[v] = x
        else:
            env[eqn.outvars[0]] = out
    outputs = jax.tree.unflatten(structure.out_tree, [read(v) for v in jaxpr.outvars])
    return outputs, activations


class Factors(NamedTuple):
    """One block of Jacobian rows in factored form: ``D[k]`` (rows, d_out_k) and ``A[k]``
    (samples, d_in_k) per dense layer, and the explicit rows ``J`` (rows, P_explicit) of
    the leaves in the groups taken (``None`` when none)."""

    D: tuple[Array, ...]
    A: tuple[Array, ...]
    J: Array | None


def factors(structure: Structure, params: PyTree, batch: PyTree, groups: tuple[int, ...] = (0,),
            axis: str | None = None) -> tuple[Factors, Array]:  # fmt: skip
    """The factors of this batch's Jacobian rows and the flat outputs ``y`` (b, d).

    One ``vmap(jacrev)`` pass: the derivatives with respect to the perturbations ``ε``
    (the ``D``'s) and to the explicit leaves of ``groups`` (their rows of J). Inside
    ``shard_map`` pass the mesh ``axis``: the perturbations are then device-varying, so
    each device keeps the derivatives of its own rows (differentiating an invariant input
    would sum them over the devices)."""
    leaves, _ = _param_leaves(params)
    explicit = [k for g in groups if g < len(structure.groups) for k in structure.groups[g]]

    def per_sample(eps, chosen, sample):
        full = list(leaves)
        for k, x in zip(explicit, chosen):
            full[k] = x
        y, acts = _evaluate(structure, full, jax.tree.leaves(sample), eps)
        y = flat_output(y)
        return y, (acts, y)

    eps = [jnp.zeros((u.d_out,), structure.jaxpr.jaxpr.eqns[u.eqn].outvars[0].aval.dtype) for u in structure.dense]
    if axis is not None:
        eps = jax.lax.pcast(eps, axis, to="varying")
    chosen = [leaves[k] for k in explicit]
    jac, (acts, y) = jax.vmap(jax.jacrev(per_sample, argnums=(0, 1), has_aux=True), in_axes=(None, None, 0))(
        eps, chosen, batch
    )
    d_eps, d_leaves = jac
    rows = y.shape[0] * y.shape[1]
    D = tuple(x.reshape(rows, -1) for x in d_eps)
    J = jnp.concatenate([x.reshape(rows, -1) for x in d_leaves], axis=1) if explicit else None
    return Factors(D, tuple(acts), J), y


def explicit_rows(predict: Callable, structure: Structure, params: PyTree, batch: PyTree, group: int) -> Array:
    """The explicit Jacobian rows (rows, P_group) of one group of leaves."""
    leaves, treedef = _param_leaves(params)
    chosen_idx = structure.groups[group]

    def per_sample(chosen, sample):
        full = list(leaves)
        for k, x in zip(chosen_idx, chosen):
            full[k] = x
        return flat_output(predict(jax.tree.unflatten(treedef, full), sample))

    jac = jax.vmap(jax.jacrev(per_sample), in_axes=(None, 0))([leaves[k] for k in chosen_idx], batch)
    rows = jac[0].shape[0] * jac[0].shape[1]
    return jnp.concatenate([x.reshape(rows, -1) for x in jac], axis=1)


def cross_gram(structure: Structure, left: Factors, right: Factors) -> Array:
    """``J_left J_rightᵀ`` (float64) from two blocks' factors; call in a float64 scope."""
    f64 = jnp.float64
    gram = None
    for use, d1, a1, d2, a2 in zip(structure.dense, left.D, left.A, right.D, right.A):
        b1, b2 = a1.shape[0], a2.shape[0]
        dd = d1.astype(f64) @ d2.astype(f64).T  # (r1, r2)
        aa = a1.astype(f64) @ a2.astype(f64).T  # (b1, b2), repeated over each sample's rows
        if use.bias is not None:  # the bias's rows are D: (D Dᵀ) ⊙ (A Aᵀ + 1)
            aa = aa + 1.0
        term = (dd.reshape(b1, -1, b2, dd.shape[1] // b2) * aa[:, None, :, None]).reshape(dd.shape)
        gram = term if gram is None else gram + term
    if left.J is not None:
        assert right.J is not None  # blocks of one structure: both hold explicit rows or neither
        term = left.J.astype(f64) @ right.J.astype(f64).T
        gram = term if gram is None else gram + term
    if gram is None:
        raise ValueError("the network has no parameters: no dense layer and no explicit leaf")
    return gram


def transpose_product(structure: Structure, block: Factors, w: Array, explicit: tuple[int, ...]) -> dict[int, Array]:
    """``Jᵀ w`` leaf by leaf (float64) from a block's factors: for a dense layer
    ``Σ_r w_r δ_r ⊗ a_{i(r)} = (Σ_k w ⊙ D)ᵀ A`` per sample, and ``J_oᵀ w`` for the
    ``explicit`` leaves whose rows the block holds (in that order). Consistent with
    :func:`cross_gram` to float64 rounding. Call in a float64 scope."""
    f64 = jnp.float64
    w = w.astype(f64)
    out = {}
    for use, d, a in zip(structure.dense, block.D, block.A):
        b = a.shape[0]
        weighted = (d.astype(f64) * w[:, None]).reshape(b, -1, use.d_out).sum(axis=1)  # (b, d_out)
        grad = weighted.T @ a.astype(f64)  # (d_out, d_in)
        out[use.leaf] = grad.T if use.transposed else grad
        if use.bias is not None:
            out[use.bias] = weighted.sum(axis=0)
    if explicit:
        assert block.J is not None  # the explicit leaves' rows
        flat = block.J.astype(f64).T @ w
        offset = 0
        for k in explicit:
            out[k] = flat[offset : offset + structure.leaf_sizes[k]]
            offset += structure.leaf_sizes[k]
    return out


def vjp_leaves(predict: Callable, structure: Structure, params: PyTree, batch: PyTree, w: Array,
               indices: tuple[int, ...]) -> dict[int, Array]:  # fmt: skip
    """``J_oᵀ w`` for the leaves ``indices`` by one vector–Jacobian product of the batch
    outputs (the other leaves held constant); ``w`` (rows,) in the outputs' dtype."""
    leaves, treedef = _param_leaves(params)

    def outputs(chosen):
        full = list(leaves)
        for k, x in zip(indices, chosen):
            full[k] = x
        p = jax.tree.unflatten(treedef, full)
        return jax.vmap(lambda s: flat_output(predict(p, s)))(batch)

    y, pullback = jax.vjp(outputs, [leaves[k] for k in indices])
    (cotangents,) = pullback(w.reshape(y.shape).astype(y.dtype))
    return dict(zip(indices, cotangents))
