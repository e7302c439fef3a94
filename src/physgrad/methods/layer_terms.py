"""The per-layer terms of KHIG's signal route: Kronecker factors and gradients, or gradients alone.

What the fresh rule (:class:`physgrad.methods.KroneckerPower` on convolution layers or with
``probes``) and its running factors (:class:`physgrad.methods.RunningFactors`) share. For
every dense layer (``z = W a + c``) and convolution layer (KFC: the kernel reshaped
(out, in·k₁⋯k_d), its input patches p̄_t; :mod:`physgrad.methods.conv_factors`) of the
per-sample program, layers in the order dense then convolutions:

* :func:`layer_curvature` — ``(A, G, ∇W̄, count)`` from one forward pass, the gradient's
  backward pass and one backward pass per cotangent (every output row, or ``probes``
  Rademacher directions per sample):

      A = Σ ā āᵀ  (d_in' × d_in'),   G = (1/c) Σ D_vᵀ D_v  (d_out × d_out),   ∇W̄ = Σ D_gᵀ ā,

  sums over samples (and a convolution's output positions), ``c`` the probes per sample
  (1 for every row), ``count`` = b (dense) or b·T (convolution: KFC's count).
* :func:`layer_gradients` — ``∇W̄`` alone, from one forward and one backward pass, as a
  plain gradient costs: a convolution's kernel gradient is taken on the kernel operand
  itself (the backward pass's own kernel product), with no input patches, and its bias
  column is the signal summed over positions. What a step that reuses stored factors needs.

Both run the products in the inputs' dtype at ``Precision.HIGHEST``: XLA's float64 products
on a CPU are ~10× slower and A's b·T patch products dominate the curvature; float32's
rounding, 1e-7 of a factor's top, sits below KHIG's default damping (the eigendecompositions
and the power are float64). Gradients are stopped on every output.
"""

from __future__ import annotations

import functools

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


def layer_curvature(structure: Structure, dense: tuple[DenseUse, ...], convs: tuple[kfc.ConvUse, ...],
                    params: PyTree, batch: PyTree, loss_and_gradient, probes: int):  # fmt: skip
    """``(layers, y, loss, g)``: per layer ``(A, G, ∇W̄, count)`` (module docstring), the
    flat outputs, the batch loss and its output gradient ``g`` (rows,)."""
    sig, y, loss, g = kfc.layer_signals(structure, dense, convs, params, batch, loss_and_gradient, probes)
    patches = [kfc.conv_patches(structure, c, x) for c, x in zip(convs, sig.x[len(dense) :])]
    scale = 1.0 / (probes or 1)  # probes: G is the mean over them
    layers = []
    for use, x, d_g, d_v in zip(dense, sig.x, sig.d_g, sig.d_v):
        a, d_v = with_bias(x, use.bias is not None), d_v.reshape(-1, use.d_out)
        layers.append((_dot(a.T, a), scale * _dot(d_v.T, d_v), _dot(d_g.T, a), a.shape[0]))
    for c, p, d_g, d_v in zip(convs, patches, sig.d_g[len(dense) :], sig.d_v[len(dense) :]):
        p = with_bias(p, c.bias is not None)
        d_v = kfc.conv_signals(structure, c, d_v).reshape(-1, c.d_out)
        d_g = kfc.conv_signals(structure, c, d_g).reshape(-1, c.d_out)
        layers.append((_dot(p.T, p), scale * _dot(d_v.T, d_v), _dot(d_g.T, p), p.shape[0]))  # KFC's count: b·T
    counts = [n for *_, n in layers]  # static sizes, kept out of stop_gradient's arrays
    terms, y, loss, g = jax.lax.stop_gradient(([t[:3] for t in layers], y, loss, g))
    return [(*t, n) for t, n in zip(terms, counts)], y, loss, g


def layer_gradients(structure: Structure, dense: tuple[DenseUse, ...], convs: tuple[kfc.ConvUse, ...],
                    params: PyTree, batch: PyTree, loss_and_gradient) -> tuple[list[Array], Array, Array, Array]:  # fmt: skip
    """``(grads, y, loss, g)``: each layer's ``∇W̄`` (d_out × d_in', the bias last), equal to
    :func:`layer_curvature`'s, from one forward and one backward pass: a zero perturbation on
    every layer's output (the dense layers' signals, the convolutions' bias) and one on each
    convolution's kernel operand, shared by the samples (its gradient is the kernel's, summed)."""
    jaxpr = structure.jaxpr.jaxpr
    taps = [(u.eqn, u.operand) for u in dense] + [(c.eqn, 0) for c in convs]
    leaves = jax.tree.leaves(params)
    b = jax.tree.leaves(batch)[0].shape[0]

    def per_sample(eps, kernels, sample):
        shifts = {c.eqn: k for c, k in zip(convs, kernels)}
        y, taken = kfc._evaluate(structure, taps, leaves, jax.tree.leaves(sample), eps, shifts)
        return flat_output(y), taken[: len(dense)]

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
    for c, d, k in zip(convs, d_g[len(dense) :], d_k):
        spec = structure.jaxpr.jaxpr.eqns[c.eqn].params["dimension_numbers"].rhs_spec
        grad = jnp.transpose(k, spec).reshape(c.d_out, c.d_in)  # (O, I·k₁⋯k_d), channel-major as the patches
        if c.bias is not None:
            bias = kfc.conv_signals(structure, c, d).reshape(-1, c.d_out).sum(axis=0)
            grad = jnp.concatenate([grad, bias[:, None]], axis=1)
        grads.append(grad)
    return jax.lax.stop_gradient((grads, y, loss, g))  # pyright: ignore[reportReturnType]
