"""The per-layer terms of KHIG's signal route: Kronecker factors and gradients, or gradients alone.

What the fresh rule (:class:`physgrad.methods.KroneckerPower` on convolution layers or with
``probes``) and its running factors (:class:`physgrad.methods.RunningFactors`) share. For
every dense layer (``z = W a + c``) and convolution layer (KFC: the kernel reshaped
(out, in·k₁⋯k_d), its input patches p̄_t; :mod:`physgrad.methods.conv_factors`) of the
per-sample program, layers in the order dense then convolutions:

* :func:`layer_pass` — one forward and one backward pass of the batch, as a plain gradient
  costs, give every layer's gradient ``∇W̄ = Σ D_gᵀ ā``: a convolution's kernel gradient is
  taken on the kernel operand itself (the backward pass's own kernel product, with no input
  patches), its bias column is the signal summed over positions; a kernel shared by several
  convolutions is one layer, its gradient and factors summed over its uses (their positions
  added to T: :mod:`physgrad.methods.conv_factors`). Its ``curvature()`` adds
  the factors from the same forward pass and one backward pass per cotangent (every output
  row, or ``probes`` Rademacher directions per sample):

      A = Σ ā āᵀ  (d_in' × d_in'),   G = (1/c) Σ D_vᵀ D_v  (d_out × d_out),

  sums over samples (and a convolution's output positions), ``c`` the probes per sample
  (1 for every row), ``count`` = b (dense) or b·T (convolution: KFC's count). A step that
  reuses stored factors calls the pass alone.
* :func:`layer_curvature` — both at once, ``(A, G, ∇W̄, count)`` per layer (the fresh rule).

The products run in the inputs' dtype at ``Precision.HIGHEST``: XLA's float64 products
on a CPU are ~10× slower and A's b·T patch products dominate the curvature; float32's
rounding, 1e-7 of a factor's top, sits below KHIG's default damping (the eigendecompositions
and the power are float64). Gradients are stopped on every output.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, PyTree

from ..jacobian import flat_output
from ..routes.base import DenseUse, Structure
from . import conv_factors as kfc

_dot = functools.partial(jnp.matmul, precision=jax.lax.Precision.HIGHEST)


def with_bias(a: Array, bias: bool) -> Array:
    """``ā = [a, 1]`` (rows, d_in + 1) with a bias, else ``a``."""
    return jnp.concatenate([a, jnp.ones((a.shape[0], 1), a.dtype)], axis=1) if bias else a


class LayerPass(NamedTuple):
    """One forward and one backward pass of the batch (:func:`layer_pass`): each layer's
    ``grads`` ∇W̄ (d_out × d_in', the bias last) and KFC ``counts`` (b, or b·T), the flat
    outputs ``y``, the batch ``loss``, its output gradient ``g`` (rows,), and ``curvature()``:
    each layer's ``(A, G)`` from the same forward pass and one more backward pass per
    cotangent (called only where the factors are wanted: inside a ``lax.cond`` the rest of
    the step does not pay for it)."""

    grads: list
    counts: list
    y: Array
    loss: Array
    g: Array
    curvature: Callable[[], list]


def layer_pass(structure: Structure, dense: tuple[DenseUse, ...], convs: tuple[kfc.ConvUse, ...], params: PyTree,
               batch: PyTree, loss_and_gradient, probes: int) -> LayerPass:  # fmt: skip
    """The gradients of every layer from one forward and one backward pass, and the factors'
    closure (:class:`LayerPass`). A zero perturbation on every layer's output (per sample:
    the signals D) and one on each convolution's kernel operand (shared by the samples: its
    cotangent is the kernel's gradient, summed, with no input patches); ``probes`` as
    :func:`~physgrad.methods.conv_factors.layer_signals`."""
    jaxpr = structure.jaxpr.jaxpr
    taps = [(u.eqn, u.operand) for u in dense] + [(c.eqn, 0) for c in convs]
    leaves = jax.tree.leaves(params)
    b = jax.tree.leaves(batch)[0].shape[0]

    def per_sample(eps, kernels, sample):
        shifts = {c.eqn: k for c, k in zip(convs, kernels)}
        y, taken = kfc._evaluate(structure, taps, leaves, jax.tree.leaves(sample), eps, shifts)
        return flat_output(y), taken

    def batched(eps, kernels):
        return jax.vmap(per_sample, in_axes=(0, None, 0))(eps, kernels, batch)

    def zeros(v, *lead):
        return jnp.zeros((*lead, *v.aval.shape), v.aval.dtype)

    eps = [zeros(jaxpr.eqns[e].outvars[0], b) for e, _ in taps]
    kernels = [zeros(jaxpr.eqns[c.eqn].invars[1]) for c in convs]
    y, pullback, taken = jax.vjp(batched, eps, kernels, has_aux=True)
    loss, g = loss_and_gradient(y)
    d_g, d_k = pullback(g.reshape(y.shape).astype(y.dtype))
    grads = [_dot(d.T, with_bias(x, u.bias is not None)) for u, x, d in zip(dense, taken, d_g)]
    layers = kfc.conv_layers(convs)
    index = {c.eqn: len(dense) + k for k, c in enumerate(convs)}  # a use's tap
    kernel_grads = {c.eqn: k for c, k in zip(convs, d_k)}
    for layer in layers:  # a shared kernel's gradient sums over its uses
        terms = []
        for c in layer.uses:
            spec = jaxpr.eqns[c.eqn].params["dimension_numbers"].rhs_spec
            use = jnp.transpose(kernel_grads[c.eqn], spec).reshape(c.d_out, c.d_in)  # channel-major as the patches
            if c.bias is not None:
                bias = kfc.conv_signals(structure, c, d_g[index[c.eqn]]).reshape(-1, c.d_out).sum(axis=0)
                use = jnp.concatenate([use, bias[:, None]], axis=1)
            terms.append(use)
        grads.append(sum(terms[1:], terms[0]))
    counts = [b] * len(dense) + [b * layer.positions for layer in layers]

    def curvature() -> list:
        dim = y.shape[1]
        if probes == 0:
            cotangents = jnp.broadcast_to(jnp.eye(dim, dtype=y.dtype)[:, None, :], (dim, b, dim))
        else:
            cotangents = jax.random.rademacher(kfc.probe_key(batch), (probes, b, dim), y.dtype)
        d_v, _ = jax.vmap(pullback)(cotangents)  # the kernels' cotangents unused: XLA drops them
        scale = 1.0 / (probes or 1)  # probes: G is the mean over them
        out = []
        for u, x, d in zip(dense, taken, d_v):
            a, d = with_bias(x, u.bias is not None), d.reshape(-1, u.d_out)
            out.append((_dot(a.T, a), scale * _dot(d.T, d)))
        for layer in layers:  # a shared kernel: its uses' patches and signals are more positions
            A = G = 0.0
            for c in layer.uses:
                p = with_bias(kfc.conv_patches(structure, c, taken[index[c.eqn]]), c.bias is not None)
                d = kfc.conv_signals(structure, c, d_v[index[c.eqn]]).reshape(-1, c.d_out)
                A, G = A + _dot(p.T, p), G + scale * _dot(d.T, d)
            out.append((A, G))
        return jax.lax.stop_gradient(out)

    grads, y, loss, g = jax.lax.stop_gradient((grads, y, loss, g))
    return LayerPass(grads, counts, y, loss, g, curvature)


def layer_curvature(structure: Structure, dense: tuple[DenseUse, ...], convs: tuple[kfc.ConvUse, ...],
                    params: PyTree, batch: PyTree, loss_and_gradient, probes: int):  # fmt: skip
    """``(layers, y, loss, g)``: per layer ``(A, G, ∇W̄, count)`` (module docstring) from
    :func:`layer_pass` and its factors, the flat outputs, the loss and its output gradient."""
    run = layer_pass(structure, dense, convs, params, batch, loss_and_gradient, probes)
    layers = [(A, G, grad, n) for (A, G), grad, n in zip(run.curvature(), run.grads, run.counts)]
    return layers, run.y, run.loss, run.g
