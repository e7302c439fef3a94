"""The structured route: the Gram matrix ``J Jᵀ`` from layer structure, never forming J.

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
``rows² · (Σ d_out + P_explicit)`` multiply-adds instead of ``rows² · P``. The kept
eigenpairs are as the Gram route's and ``Jᵀ w`` comes from the same factors.

The dense layers are those of the step's :class:`~.base.JointJacobian` (found in the traced
per-sample program, :func:`~.base.find_structure`). A small interpreter evaluates that
program adding a zero perturbation ``ε`` to each dense product's output (``∂y/∂ε = δ``) and
returning its vector operand (``a``).

Source: the Kronecker factorisation of a dense layer's per-example gradient is the basis
of K-FAC (Martens & Grosse 2015) and of per-example gradient norms (Goodfellow 2015);
here it gives the exact Gram matrix that the half-inverse gradient of Schnell, Holl &
Thuerey (ICLR 2022) decomposes.

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.extend.core import Literal
from jaxtyping import Array, PyTree

from ..distributed import AXIS, data_axis_size
from ..jacobian import flat_output
from ..precision import float64_scope, to_float64
from .base import CHUNK_ELEMENTS, F64, AbstractRoute, JointJacobian, Structure, over_devices
from .gram import Gram, gram_bytes, on_device_0, ring_gram
from .spectrum import cast_spectrum, gram_power


class Structured(AbstractRoute):
    """The exact Gram matrix ``J Jᵀ`` from layer structure (module docstring).

    Each dense layer contributes ``(D Dᵀ) ⊙ (A Aᵀ)⇑`` from its back-propagated signals D
    (rows × d_out) and inputs A (samples × d_in); the other parameters contribute their
    explicit Jacobian rows, ``chunk_elements`` numbers at a time. Products accumulate in
    float64, so the update equals :class:`~.gram.Gram`'s without ever holding J. A tall J
    (rows > P) goes to :class:`~.gram.Gram`. Under a device mesh each device keeps its rows'
    factors and the ring passes D, A and the explicit rows instead of rows of J."""

    code = 2
    chunk_elements: int = eqx.field(static=True, default=CHUNK_ELEMENTS)

    def instead(self, jacobian):
        # A tall J: its Gram matrix J Jᵀ is wider than J itself, and the Gram route's JᵀJ
        # is the smaller one.
        return Gram() if jacobian.rows > jacobian.size else None

    def compute(self, jacobian: JointJacobian, exponent, truncation):
        devices = data_axis_size()
        if devices == 1:
            plan = jacobian.structure.regrouped(jacobian.rows, self.chunk_elements)
            direction, loss, spectrum = _structured_direction(jacobian, plan, exponent, truncation)
        else:
            direction, loss, spectrum = over_devices(_sharded_structured, jacobian, devices, exponent, truncation)
        return direction, loss, self.stats(spectrum)

    def footprint_of(self, jacobian, devices=1):
        plan = jacobian.structure.regrouped(jacobian.rows, self.chunk_elements)
        local_rows, local_b = -(-jacobian.rows // devices), -(-jacobian.batch_size // devices)
        per_byte = jacobian.itemsize + F64
        d_out, d_in = sum(u.d_out for u in plan.dense), sum(u.d_in for u in plan.dense)
        group = max((sum(plan.leaf_sizes[k] for k in g) for g in plan.groups), default=0)
        explicit = plan.explicit_parameters if devices > 1 else group
        return (local_rows * (d_out + explicit) + local_b * d_in) * per_byte + gram_bytes(jacobian.shape)


def _assemble(params, pieces: dict, cast: bool = True) -> Array:
    """The flat direction (P,) in ``ravel_pytree`` order from per-leaf pieces (cast to
    each leaf's dtype, or kept as they are)."""
    leaves = jax.tree.leaves(params)
    return jnp.concatenate(
        [pieces[k].reshape(-1).astype(x.dtype if cast else pieces[k].dtype) for k, x in enumerate(leaves)]
    )


def _structured_direction(jacobian: JointJacobian, plan: Structure, exponent, truncation):
    """One device: the Gram matrix group by group, ``w = U Σ^{κ−1} Uᵀ g``, then ``Jᵀ w``."""
    params, batch = jacobian.params, jacobian.batch
    block, y = factors(plan, params, batch, groups=(0,))
    loss, g = jacobian.loss_and_gradient(y)
    whole = len(plan.groups) <= 1  # the first pass holds every explicit row
    # Constants for differentiation: the float64 scopes below cannot be transposed.
    block, g = jax.lax.stop_gradient((block, g))
    with float64_scope():
        gram = cross_gram(plan, block, block)
    for group in range(1, len(plan.groups)):
        rows = jax.lax.stop_gradient(explicit_rows(jacobian.predict, plan, params, batch, group))
        with float64_scope():
            rows = to_float64(rows)
            gram = gram + rows @ rows.T
    with float64_scope():
        w, spectrum = gram_power(gram, to_float64(g), exponent, truncation)
        pieces = transpose_product(plan, block, w, plan.groups[0] if whole and plan.groups else ())
        leaves = jax.tree.leaves(params)
        pieces = {k: v.astype(leaves[k].dtype) for k, v in pieces.items()}
        w = w.astype(y.dtype)
        spectrum = cast_spectrum(spectrum, y.dtype)
    if not whole:
        rest = tuple(k for group in plan.groups for k in group)
        stopped = jax.lax.stop_gradient(params)
        pieces.update(vjp_leaves(jacobian.predict, plan, stopped, batch, w, rest))
    return _assemble(params, pieces), loss, spectrum


def _sharded_structured(objective, params, batch, *, devices, exponent, truncation):
    """Data parallel: each device keeps its rows' factors (all explicit rows in one block)
    and the ring passes them (rows/N × (Σ d_out + P_explicit) + samples/N × Σ d_in numbers
    per hop instead of rows/N × P)."""
    params = jax.lax.pcast(params, AXIS, to="varying")  # each device keeps its own rows (gram._sharded_direction)
    local = JointJacobian.of(objective, params, batch)
    plan = local.structure.regrouped(local.rows, 2**62)
    block, y = factors(plan, params, batch, groups=tuple(range(len(plan.groups))), axis=AXIS)
    loss, g = local.loss_and_gradient(y, devices)
    block, g = jax.lax.stop_gradient((block, g))
    r = g.shape[0]
    explicit = tuple(k for group in plan.groups for k in group)
    me = jax.lax.axis_index(AXIS)
    with float64_scope():
        gram = ring_gram(block, functools.partial(cross_gram, plan), r, AXIS, devices)
        g_all = jax.lax.all_gather(to_float64(g), AXIS, tiled=True)
        w, spectrum = on_device_0(lambda G, v: gram_power(G, v, exponent, truncation), gram, g_all, axis=AXIS)
        own = jax.lax.dynamic_slice_in_dim(w, me * r, r)
        pieces = transpose_product(plan, block, own, explicit)
        direction = jax.lax.psum(_assemble(params, pieces, cast=False), AXIS)
        direction = direction.astype(jax.tree.leaves(params)[0].dtype)
        spectrum = cast_spectrum(spectrum, direction.dtype)
    return direction, jax.lax.psum(loss, AXIS), spectrum


# --- the factors of J's rows -----------------------------------------------------------
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
    leaves = jax.tree.leaves(params)
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


def _with_leaves(predict: Callable, structure: Structure, params: PyTree, indices: tuple[int, ...]):
    """``predict`` as a function of the leaves ``indices`` (the others held at ``params``)."""
    leaves = jax.tree.leaves(params)

    def chosen_predict(chosen, sample):
        full = list(leaves)
        for k, x in zip(indices, chosen):
            full[k] = x
        return flat_output(predict(jax.tree.unflatten(structure.treedef, full), sample))

    return chosen_predict, [leaves[k] for k in indices]


def explicit_rows(predict: Callable, structure: Structure, params: PyTree, batch: PyTree, group: int) -> Array:
    """The explicit Jacobian rows (rows, P_group) of one group of leaves."""
    per_sample, chosen = _with_leaves(predict, structure, params, structure.groups[group])
    jac = jax.vmap(jax.jacrev(per_sample), in_axes=(None, 0))(chosen, batch)
    rows = jac[0].shape[0] * jac[0].shape[1]
    return jnp.concatenate([x.reshape(rows, -1) for x in jac], axis=1)


def vjp_leaves(predict: Callable, structure: Structure, params: PyTree, batch: PyTree, w: Array,
               indices: tuple[int, ...]) -> dict[int, Array]:  # fmt: skip
    """``J_oᵀ w`` for the leaves ``indices`` by one vector–Jacobian product of the batch
    outputs (the other leaves held constant); ``w`` (rows,) in the outputs' dtype."""
    per_sample, chosen = _with_leaves(predict, structure, params, indices)
    y, pullback = jax.vjp(lambda c: jax.vmap(lambda s: per_sample(c, s))(batch), chosen)
    (cotangents,) = pullback(w.reshape(y.shape).astype(y.dtype))
    return dict(zip(indices, cotangents))


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
