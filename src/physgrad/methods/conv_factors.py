"""Kronecker factors of convolution layers (KFC) for KHIG, and the layers' shared signals.

Source: Grosse & Martens, *A Kronecker-factored approximate Fisher matrix for convolution
layers*, ICML 2016 (the factors and their three assumptions); the power and truncation
applied to them are KHIG's (:mod:`physgrad.methods.kronecker_hig`).

The factors
-----------
A convolution ``z[:, t] = K̄ p̄_t`` (kernel K: out × in × k₁ … k_d, reshaped to the dense
weight ``K̄ = [K_(out, in·k₁⋯k_d)  c]`` with the bias c as a last column) sees at each output
position t the input patch ``p_t`` (in·k₁⋯k_d numbers, channel-major as the kernel;
``p̄_t = [p_t; 1]``), taken after padding (zero padding in the convolution, circular padding
as a ``jnp.pad(mode="wrap")`` or Equinox's ``padding_mode="CIRCULAR"`` before it), with the
strides, dilations (``rhs_dilation``) and input dilation (``lhs_dilation``: a transposed
convolution) of the operation itself. With ``D_{i,t} = ∂y_i/∂z_{i,t}`` (dim y × out), the
layer's Jacobian rows for sample i are ``Σ_t D_{i,t} ⊗ p̄_{i,t}ᵀ`` and its Gauss–Newton block
is ``Σ_i Σ_{t,t'} D_{i,t}ᵀD_{i,t'} ⊗ p̄_{i,t} p̄_{i,t'}ᵀ``. Independent activations and
derivatives, spatial homogeneity and spatially uncorrelated derivatives (KFC's IAD, SH and
SUD) replace it by

    (1/(b T)) G ⊗ A,    G = Σ_i Σ_t D_{i,t}ᵀ D_{i,t}  (out × out),
                        A = Σ_i Σ_t p̄_{i,t} p̄_{i,t}ᵀ   (in·k' × in·k'),

T the output positions of one sample (all of its spatial positions, times the number of
images the per-sample program convolves at once). With T = 1 this is the dense layer's
``(1/b) G ⊗ A``, and it is exact where the dense one is (one layer, the same linear physics
for every sample). The layer's gradient is ``∇K̄ = Σ_i Σ_t (D_{i,t}ᵀ g_i) p̄_{i,t}ᵀ``.

G through the simulator: every row or a few probes
---------------------------------------------------
``G`` sums over every simulator output (a backward pass per row of J, as the dense layers'
G and exact HIG's structured route). On a U-Net the outputs are a field (thousands of rows
per sample), so ``probes = s > 0`` estimates it instead, as K-FAC's Monte Carlo Fisher:
``G ≈ (1/s) Σ_{k≤s} Σ_i Σ_t (D_{i,t}ᵀ v_{ik})(D_{i,t}ᵀ v_{ik})ᵀ`` with Rademacher vectors
``v_ik`` (dim y; ``E[v vᵀ] = I``, so the estimate is unbiased), s backward passes per sample.
A rule is a pure function with no state, so the probes' key is drawn from the batch's own
values (:func:`probe_key`): a new batch draws new probes, the same batch the same ones.

Kernels computed from a parameter
---------------------------------
A kernel leaf may reach its convolution through reshaping (Equinox's layout, a flip) or a
reparametrisation (weight standardisation, :func:`physgrad.nets.standardised_weight`); the
factors belong to the kernel the convolution uses, ``K = f(θ)``. Its direction ``ΔK`` is
brought back to the leaf as a gradient is, by the transposed derivative of f:
``Δθ = (∂f/∂θ)ᵀ ΔK``. For reshaping this is exactly ΔK rearranged; for a standardised kernel
it is ΔK projected off the directions the standardisation removes (each output channel's
mean and scale) and scaled by √(2/fan_in)/std(θ) (about 1 at He's initialisation).

Shared kernels
--------------
A kernel leaf read by several convolutions (a network applied at every step of an unrolled
rollout, as the KS corrector's; one network applied twice) is one layer whose uses are more
positions: with ``D^u_{i,t}`` and ``p̄^u_{i,t}`` the signals and patches of use u,

    (1/(b T)) G ⊗ A,   G = Σ_u Σ_i Σ_t D^uᵀ D^u,   A = Σ_u Σ_i Σ_t p̄^u p̄^uᵀ,   T = Σ_u T_u,

and the gradient ``∇K̄ = Σ_u Σ_i Σ_t (D^uᵀ g_i) p̄^uᵀ`` sums over the uses as any gradient
does. This assumes, besides KFC's three, that the uses are independent: the cross terms
``D^uᵀ D^{u'} ⊗ p̄^u p̄^{u'}ᵀ`` between uses are dropped, as between positions (the simplest
option of Martens, Ba & Johnson, *Kronecker-factored curvature approximations for recurrent
neural networks*, ICLR 2018, which treats the time steps of a recurrent network as
independent; their other options model the correlation across steps). Every use must
convolve with the same kernel computed the same way from the leaf (the same chain of
equations, shape and layout); the bias is the layer's when every use adds the same bias
leaf and nothing else reads it (else the bias leaves join the exact leftover block).

Refused in one line, naming the convolution: grouped convolutions (``feature_group_count``
or ``batch_group_count`` > 1: each group is its own layer, not factored here), a kernel
computed from more than one parameter leaf or from the sample, a kernel leaf read other
than as these convolutions' kernels, and a shared leaf whose uses compute different kernels.
"""

from __future__ import annotations

import itertools
import math
from collections import defaultdict
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.extend.core import Literal
from jaxtyping import Array, PyTree

from ..jacobian import flat_output
from ..precision import float64_scope, to_float64
from ..routes.base import DenseUse, JointJacobian, Structure
from .base import Objective
from .conv_program import ConvUse, checked_layer, conv_layers, unrolled_structure
from .conv_program import bind as _bind

_SQUEEZING = {"squeeze", "reshape", "expand_dims"}


def find_convolutions(structure: Structure) -> tuple[ConvUse, ...]:
    """The convolutions of the traced per-sample program that KHIG factors, one per
    equation (convolutions of fixed stencils, with no parameter in the kernel, are physics
    and are skipped; :func:`conv_layers` groups those of one kernel leaf), or a one-line
    ``ValueError`` naming the first one KHIG cannot factor."""
    jaxpr = structure.jaxpr.jaxpr
    n = len(structure.leaf_sizes)
    sample = -1  # the taint of anything computed from the sample
    taint: dict = {v: frozenset({k}) for k, v in enumerate(jaxpr.invars[:n])}
    taint.update({v: frozenset({sample}) for v in jaxpr.invars[n:]})
    users: dict = defaultdict(list)
    producer: dict = {}
    for e, eqn in enumerate(jaxpr.eqns):
        seen = frozenset()
        for v in eqn.invars:
            if not isinstance(v, Literal):
                seen |= taint.get(v, frozenset())
                users[v].append(e)
        for v in eqn.outvars:
            taint[v] = seen
            producer[v] = e
    outputs = {v for v in jaxpr.outvars if not isinstance(v, Literal)}
    found: list[ConvUse] = []
    for e, eqn in enumerate(jaxpr.eqns):
        if eqn.primitive.name != "conv_general_dilated":
            continue
        kernel = eqn.invars[1]
        sources = frozenset() if isinstance(kernel, Literal) else taint.get(kernel, frozenset())
        if not sources:
            continue
        rhs, out = _shape(kernel), _shape(eqn.outvars[0])
        where = f"khig: convolution {e} (kernel {rhs})"
        params = eqn.params
        if params["feature_group_count"] != 1 or params["batch_group_count"] != 1:
            raise ValueError(f"{where} is grouped; grouped convolutions have no Kronecker factors here; use hig")
        if len(sources) != 1 or sample in sources:
            raise ValueError(f"{where} has a kernel computed from {len(sources)} leaves or the sample; use hig")
        (leaf,) = sources
        chain = _backward_slice(kernel, producer, jaxpr)
        if any(taint[v] - {leaf} for c in chain for v in jaxpr.eqns[c].invars if not isinstance(v, Literal)):
            raise ValueError(f"{where}: its kernel mixes leaf {leaf} with other values; use hig")
        dims = params["dimension_numbers"]
        d_out, d_in = rhs[dims.rhs_spec[0]], math.prod(rhs) // rhs[dims.rhs_spec[0]]
        bias = _bias_of(eqn, dims.out_spec[1], users, jaxpr, structure, n, outputs)
        found.append(ConvUse(e, leaf, chain, d_in, d_out, math.prod(out) // d_out, bias))
    checked: list[ConvUse] = []
    for layer in conv_layers(tuple(found)):
        checked.extend(checked_layer(layer, jaxpr, users, outputs))
    return tuple(sorted(checked, key=lambda c: c.eqn))


def _shape(v) -> tuple[int, ...]:
    return tuple(v.aval.shape)


def _backward_slice(var, producer: dict, jaxpr) -> tuple[int, ...]:
    """The equations computing ``var`` from the program's inputs, in program order."""
    needed, stack = set(), [var]
    while stack:
        v = stack.pop()
        e = producer.get(v)
        if e is None or e in needed:
            continue
        needed.add(e)
        stack.extend(u for u in jaxpr.eqns[e].invars if not isinstance(u, Literal))
    return tuple(sorted(needed))


def _bias_of(eqn, feature_axis: int, users: dict, jaxpr, structure: Structure, n: int, outputs) -> int | None:
    """The leaf ``c`` of ``z + c`` right after the convolution (through squeezes), broadcast
    along every axis but the output channels', when that sum is z's only use (the caller
    checks that nothing but its layer's sums reads ``c``)."""
    z = eqn.outvars[0]
    shape = list(z.aval.shape)
    axis: int | None = feature_axis  # where the channels are in the current value's shape
    d_out = shape[feature_axis]
    leaves = {v: k for k, v in enumerate(jaxpr.invars[:n])}
    while len(users.get(z, ())) == 1 and z not in outputs:
        nxt = jaxpr.eqns[users[z][0]]
        if nxt.primitive.name in _SQUEEZING:
            new = list(nxt.outvars[0].aval.shape)
            if [s for s in new if s != 1] != [s for s in shape if s != 1]:
                return None  # a reshape that mixes axes
            # the channel axis keeps its rank among the non-unit axes
            if d_out == 1:
                axis = None
            elif axis is not None:
                rank = sum(1 for s in shape[:axis] if s != 1)
                axis = [i for i, s in enumerate(new) if s != 1][rank]
            z, shape = nxt.outvars[0], new
            continue
        if nxt.primitive.name != "add":
            return None
        other = nxt.invars[1] if nxt.invars[0] is z else nxt.invars[0]
        # a bias leaf read elsewhere too is refused by the caller (a shared kernel's uses all read it)
        if isinstance(other, Literal) or other not in leaves or other in outputs:
            return None
        c = other.aval.shape
        if len(c) != len(shape) or math.prod(c) != d_out:
            return None
        if d_out > 1 and (axis is None or c[axis] != d_out):
            return None
        return leaves[other]
    return None


# --- the layers' signals, inputs and factors -------------------------------------------
class Signals(NamedTuple):
    """Per layer (dense layers first, then convolutions, each in program order): its input
    ``x`` (dense: (b, d_in); convolution: its input image(s), (b, *lhs shape)), the
    gradient's signal ``d_g`` (the output gradient g pulled back to the pre-activations,
    (b, *z shape)) and the curvature's signals ``d_v`` (c, b, *z shape) from c cotangents
    (every output row, or the probes)."""

    x: tuple[Array, ...]
    d_g: tuple[Array, ...]
    d_v: tuple[Array, ...]


def probe_key(batch: PyTree, seed: int = 0) -> Array:
    """A PRNG key drawn from the batch's values (a pure rule has no state to carry one)."""
    bits = jnp.uint32(seed)
    for x in jax.tree.leaves(batch):
        x = jnp.asarray(x)
        if x.size == 0:
            continue
        flat = x.ravel()
        real = (flat.real if jnp.iscomplexobj(flat) else flat).astype(jnp.float32)
        # a position-weighted sum: permuting the batch draws new probes too
        weights = jnp.cos(jnp.arange(real.shape[0], dtype=jnp.float32))
        bits = bits ^ jax.lax.bitcast_convert_type(jnp.sum(real * weights), jnp.uint32)
    return jax.random.fold_in(jax.random.key(seed), bits)


def layer_signals(structure: Structure, dense: tuple[DenseUse, ...], convs: tuple[ConvUse, ...], params: PyTree,
                  batch: PyTree, loss_and_gradient, probes: int) -> tuple[Signals, Array, Array, Array]:  # fmt: skip
    """``(signals, y, loss, g)`` from one forward pass of the batch with a zero perturbation
    on every layer's pre-activations and one backward pass per cotangent: ``g`` (rows,)
    and, with ``probes = 0``, every output row (exact G), else ``probes`` Rademacher vectors
    per sample. ``loss_and_gradient(y) -> (loss, g)`` as :meth:`JointJacobian.loss_and_gradient`."""
    jaxpr = structure.jaxpr.jaxpr
    taps = [(u.eqn, u.operand) for u in dense] + [(c.eqn, 0) for c in convs]
    leaves = jax.tree.leaves(params)
    b = jax.tree.leaves(batch)[0].shape[0]

    def per_sample(eps, sample):
        y, taken = _evaluate(structure, taps, leaves, jax.tree.leaves(sample), eps)
        return flat_output(y), taken

    def batched(eps):
        return jax.vmap(per_sample)(eps, batch)

    eps = [jnp.zeros((b, *jaxpr.eqns[e].outvars[0].aval.shape), jaxpr.eqns[e].outvars[0].aval.dtype) for e, _ in taps]
    y, pullback, taken = jax.vjp(batched, eps, has_aux=True)
    loss, g = loss_and_gradient(y)
    (d_g,) = pullback(g.reshape(y.shape).astype(y.dtype))
    dim = y.shape[1]
    if probes == 0:
        cotangents = jnp.broadcast_to(jnp.eye(dim, dtype=y.dtype)[:, None, :], (dim, b, dim))
    else:
        cotangents = jax.random.rademacher(probe_key(batch), (probes, b, dim), y.dtype)
    (d_v,) = jax.vmap(pullback)(cotangents)
    return Signals(tuple(taken), tuple(d_g), tuple(d_v)), y, loss, g  # pyright: ignore[reportArgumentType]


def _evaluate(structure: Structure, taps, leaves, sample_leaves, eps, kernels: dict | None = None):
    """Run the per-sample program with ``eps[k]`` added to tapped equation k's output (and
    ``kernels[e]`` to convolution e's kernel operand); return the outputs and the tapped
    operands (a dense layer's vector, a convolution's input)."""
    jaxpr = structure.jaxpr.jaxpr
    env = {}

    def read(v):
        return v.val if isinstance(v, Literal) else env[v]

    for v, x in zip(jaxpr.constvars, structure.jaxpr.consts):
        env[v] = x
    for v, x in zip(jaxpr.invars, list(leaves) + list(sample_leaves)):
        env[v] = x
    by_eqn = {e: k for k, (e, _) in enumerate(taps)}
    taken: list = [None] * len(taps)
    for e, eqn in enumerate(jaxpr.eqns):
        invals = [read(v) for v in eqn.invars]
        if kernels and e in kernels:
            invals[1] = invals[1] + kernels[e]
        out = _bind(eqn, invals)
        if e in by_eqn:
            k = by_eqn[e]
            taken[k] = invals[taps[k][1]]
            out = out + eps[k]
        if eqn.primitive.multiple_results:
            for v, x in zip(eqn.outvars, out):
                env[v] = x
        else:
            env[eqn.outvars[0]] = out
    return jax.tree.unflatten(structure.out_tree, [read(v) for v in jaxpr.outvars]), taken


def conv_patches(structure: Structure, use: ConvUse, x: Array) -> Array:
    """The input patches ``p_t`` (b · T, in·k₁⋯k_d) of convolution ``use`` for the inputs
    ``x`` (b, *lhs shape), channel-major as the kernel reshaped by :func:`kernel_matrix`.

    Taken by slicing, not by a convolution with an identity kernel (whose multiply-adds
    would cost as much as ``A`` itself): the input padded as the convolution pads it (and
    dilated by ``lhs_dilation`` − 1 zeros between entries), then one strided slice per
    kernel offset."""
    eqn = structure.jaxpr.jaxpr.eqns[use.eqn]
    p, dims = eqn.params, eqn.params["dimension_numbers"]
    kernel = eqn.invars[1].aval.shape
    window = tuple(kernel[a] for a in dims.rhs_spec[2:])
    out = eqn.outvars[0].aval.shape
    out_spatial = tuple(out[a] for a in dims.out_spec[2:])

    def one(image):
        image = jnp.transpose(image, dims.lhs_spec)  # (N, C, *spatial)
        config = [(0, 0, 0), (0, 0, 0)] + [(lo, hi, d - 1) for (lo, hi), d in zip(p["padding"], p["lhs_dilation"])]
        image = jax.lax.pad(image, jnp.zeros((), image.dtype), config)
        taps = []
        for offset in itertools.product(*(range(k) for k in window)):
            start = [0, 0] + [o * r for o, r in zip(offset, p["rhs_dilation"])]
            limit = [image.shape[0], image.shape[1]] + [
                s + (n - 1) * st + 1 for s, n, st in zip(start[2:], out_spatial, p["window_strides"])
            ]
            taps.append(jax.lax.slice(image, start, limit, [1, 1, *p["window_strides"]]))  # (N, C, *out)
        patches = jnp.stack(taps, axis=2)  # (N, C, ∏k, *out): channel-major as the kernel
        patches = patches.reshape(patches.shape[0], -1, *out_spatial)
        return jnp.moveaxis(patches, 1, -1).reshape(-1, patches.shape[1])  # (N·T, C·∏k)

    return jax.vmap(one)(x).reshape(-1, use.d_in)


def conv_signals(structure: Structure, use: ConvUse, d: Array) -> Array:
    """Signals on the convolution's output (..., *z shape) as (..., T, out), positions in
    the order of :func:`conv_patches`."""
    dims = structure.jaxpr.jaxpr.eqns[use.eqn].params["dimension_numbers"]
    lead = d.ndim - len(dims.out_spec)
    d = jnp.transpose(d, tuple(range(lead)) + tuple(lead + a for a in dims.out_spec))  # (..., N, O, *spatial)
    d = jnp.moveaxis(d, lead + 1, -1)
    return d.reshape(*d.shape[:lead], -1, use.d_out)


def kernel_matrix(structure: Structure, use: ConvUse, delta: Array) -> Array:
    """The (out, in·k₁⋯k_d) matrix ``delta`` back in the kernel operand's own layout."""
    eqn = structure.jaxpr.jaxpr.eqns[use.eqn]
    spec = eqn.params["dimension_numbers"].rhs_spec
    shape = eqn.invars[1].aval.shape
    standard = delta.reshape(tuple(shape[a] for a in spec))  # (O, I, *k)
    inverse = [0] * len(spec)
    for i, a in enumerate(spec):
        inverse[a] = i
    return jnp.transpose(standard, inverse)


def kernel_pullback(structure: Structure, use: ConvUse, leaf: Array, delta: Array) -> Array:
    """``(∂f/∂θ)ᵀ ΔK`` for the kernel ``K = f(θ)`` of ``use`` (its ``chain``) at ``leaf``;
    ``delta`` in the kernel operand's layout."""
    jaxpr = structure.jaxpr.jaxpr
    kernel = jaxpr.eqns[use.eqn].invars[1]

    def f(theta):
        env = dict(zip(jaxpr.constvars, structure.jaxpr.consts))
        env[jaxpr.invars[use.leaf]] = theta
        for e in use.chain:
            eqn = jaxpr.eqns[e]
            out = _bind(eqn, [v.val if isinstance(v, Literal) else env[v] for v in eqn.invars])
            for v, x in zip(eqn.outvars, out if eqn.primitive.multiple_results else [out]):
                env[v] = x
        return env[kernel]

    _, pull = jax.vjp(f, leaf)
    return pull(delta.astype(kernel.aval.dtype))[0]


def eigh_all(matrices: list[Array], batched: bool = True) -> list[tuple[Array, Array]]:
    """``jnp.linalg.eigh`` of every symmetric matrix: same-size matrices stacked into one
    call per size (one kernel launch instead of one per factor), or one call each."""
    if not batched:
        return [tuple(jnp.linalg.eigh(m)) for m in matrices]  # pyright: ignore[reportReturnType]
    by_size: dict[int, list[int]] = defaultdict(list)
    for k, m in enumerate(matrices):
        by_size[m.shape[0]].append(k)
    out: list = [None] * len(matrices)
    for indices in by_size.values():
        lam, q = jnp.linalg.eigh(jnp.stack([matrices[k] for k in indices]))
        for j, k in enumerate(indices):
            out[k] = (lam[j], q[j])
    return out


class ConvFactors(NamedTuple):
    """One convolution layer's KFC factors (float64): the kernel and bias leaves (indices in
    ``jax.tree.leaves(params)``), ``A`` (in·k' × in·k'), ``G`` (out × out) and the count
    ``b·T`` of patch–signal pairs they sum over."""

    kernel: int
    bias: int | None
    A: Array
    G: Array
    count: int


def conv_layer_factors(predict, params: PyTree, batch: PyTree, probes: int = 0) -> list[ConvFactors]:
    """The factors ``A = Σ_i Σ_t p̄ p̄ᵀ`` and ``G = Σ_i Σ_t D_{i,t}ᵀ D_{i,t}`` of every convolution
    layer of ``predict`` (``params``: arrays only) for this batch, in program order (a shared
    kernel: one layer, the sums also over its uses), computed as KHIG computes them
    (``probes`` as its setting); for inspection and tests."""
    structure = JointJacobian.of(Objective(predict), params, batch).structure
    structure = unrolled_structure(structure, params, jax.tree.map(lambda a: a[0], batch))
    convs = find_convolutions(structure)

    def no_loss(y):
        return jnp.zeros((), y.dtype), jnp.zeros((y.size,), y.dtype)

    sig, *_ = layer_signals(structure, (), convs, params, batch, no_loss, probes)
    index = {c.eqn: k for k, c in enumerate(convs)}
    out = []
    with float64_scope():
        for layer in conv_layers(convs):
            A = G = jnp.zeros((), jnp.float64)
            for c in layer.uses:  # a shared kernel: its uses are more positions of one layer
                k = index[c.eqn]
                p = to_float64(conv_patches(structure, c, sig.x[k]))
                if c.bias is not None:
                    p = jnp.concatenate([p, jnp.ones((p.shape[0], 1), p.dtype)], axis=1)
                d = to_float64(conv_signals(structure, c, sig.d_v[k])).reshape(-1, c.d_out)
                A, G = A + p.T @ p, G + d.T @ d / (probes or 1)
            b = jax.tree.leaves(batch)[0].shape[0]
            out.append(ConvFactors(layer.leaf, layer.bias, A, G, b * layer.positions))
    return out
