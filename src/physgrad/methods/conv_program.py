"""The per-sample program as KHIG's convolution factors read it: unrolled, and each kernel's convolutions as one layer.

Two steps before :func:`physgrad.methods.conv_factors.find_convolutions`:

* :func:`unrolled_structure` — a convolution inside a nested call (``jax.jit``,
  ``jax.checkpoint``) or a ``lax.scan`` body (a network applied at every step of a rollout,
  as the KS corrector's) is not an equation of the traced program, so the factors could not
  see it. The program is traced again through :func:`inline`, which evaluates the nested
  calls and scans that hold a convolution equation by equation (a scan step by step, at most
  :data:`physgrad.loops.MAX_UNROLL` steps) and binds every other equation as it is. The
  result computes the same values; each step of an unrolled network is then its own
  convolutions, reading the same kernel leaf.
* :func:`conv_layers` and :func:`checked_layer` — the convolutions of one kernel leaf are one
  layer (:class:`ConvLayer`, its uses more positions of it; :class:`ConvUse` one convolution; the assumption is stated in
  :mod:`physgrad.methods.conv_factors`), refused in one line where the leaf is read other
  than as their kernels or the uses compute different kernels from it.
"""

from __future__ import annotations

import contextlib
from typing import NamedTuple

import jax
from jax.extend.core import ClosedJaxpr, Literal
from jaxtyping import PyTree

from ..loops import MAX_UNROLL, primitives
from ..routes.base import Structure, find_structure

# Equations that call a nested program with the same inputs and outputs (inlined as they are)
_CALLS = {"pjit", "jit", "closed_call", "core_call", "remat2", "checkpoint"}


def bind(eqn, invals):
    """Bind equation ``eqn`` of a traced program to ``invals``, in its context."""
    bound = eqn.primitive.get_bind_params(eqn.params)
    subfuns, params = bound if isinstance(bound, tuple) else ((), bound)  # (subfuns, params) in older JAX
    context = getattr(getattr(eqn, "ctx", None), "manager", None) or contextlib.nullcontext()
    with context:
        return eqn.primitive.bind(*subfuns, *invals, **params)


def _holds_convolution(jaxpr) -> bool:
    return any(name == "conv_general_dilated" for name in primitives(jaxpr))


def _nested(eqn):
    """``(jaxpr, consts)`` of a call or scan equation whose body holds a convolution, else None."""
    name = eqn.primitive.name
    inner = eqn.params.get("jaxpr") if name in _CALLS or name == "scan" else None
    if inner is None:
        return None
    jaxpr, consts = (inner.jaxpr, inner.consts) if isinstance(inner, ClosedJaxpr) else (inner, ())
    if not _holds_convolution(jaxpr):
        return None
    if name == "scan" and not 0 < eqn.params["length"] <= MAX_UNROLL:
        return None
    return jaxpr, consts


def inline(jaxpr, consts, args) -> list:
    """Evaluate ``jaxpr`` on ``args`` (traced: the equations land in the caller's trace), its
    nested calls and scans that hold a convolution evaluated equation by equation."""
    env = {}

    def read(v):
        return v.val if isinstance(v, Literal) else env[v]

    env.update(zip(jaxpr.constvars, consts))
    env.update(zip(jaxpr.invars, args))
    for eqn in jaxpr.eqns:
        invals = [read(v) for v in eqn.invars]
        nested = _nested(eqn)
        if nested is None:
            out = bind(eqn, invals)
            outs = out if eqn.primitive.multiple_results else [out]
        elif eqn.primitive.name == "scan":
            outs = _scan(eqn.params, *nested, invals)
        else:
            outs = inline(*nested, invals)
        env.update(zip(eqn.outvars, outs))
    return [read(v) for v in jaxpr.outvars]


def _scan(params, body, consts, invals) -> list:
    """A ``lax.scan`` step by step: ``(consts, carry, xs) -> (carry, stacked ys)``."""
    n_const, n_carry, length = params["num_consts"], params["num_carry"], params["length"]
    fixed, carry, xs = invals[:n_const], invals[n_const : n_const + n_carry], invals[n_const + n_carry :]
    ys = []
    for i in reversed(range(length)) if params["reverse"] else range(length):
        out = inline(body, consts, [*fixed, *carry, *(jax.lax.index_in_dim(x, i, keepdims=False) for x in xs)])
        carry = out[:n_carry]
        ys.append(out[n_carry:])
    if params["reverse"]:
        ys.reverse()
    return [*carry, *(jax.numpy.stack(column) for column in zip(*ys))] if ys and ys[0] else list(carry)


def unrolled_structure(structure: Structure, params: PyTree, sample: PyTree) -> Structure:
    """``structure`` itself when every convolution is an equation of its program, else the
    program traced again with the calls and scans holding convolutions inlined (its dense
    layers found again; one explicit group)."""
    program = structure.jaxpr
    if not any(_nested(eqn) is not None for eqn in program.jaxpr.eqns):
        return structure

    def predict(p, s):
        outs = inline(program.jaxpr, program.consts, [*jax.tree.leaves(p), *jax.tree.leaves(s)])
        return jax.tree.unflatten(structure.out_tree, outs)

    return find_structure(predict, params, sample, 1, 2**62)


class ConvUse(NamedTuple):
    """A convolution layer found in the per-sample program: equation ``eqn`` convolves its
    input with a kernel computed from parameter leaf ``leaf`` alone by the equations
    ``chain`` (reshaping, or a reparametrisation); ``bias`` the leaf added right after it.
    ``d_out`` = out channels, ``d_in`` = in·k₁⋯k_d (without the bias column), ``positions``
    the output positions T of one sample."""

    eqn: int
    leaf: int
    chain: tuple[int, ...]
    d_in: int
    d_out: int
    positions: int
    bias: int | None = None


class ConvLayer(NamedTuple):
    """One kernel leaf's convolutions as one KFC layer: its ``uses`` (one ``ConvUse`` per
    convolution reading the kernel, in program order; several where the kernel is shared,
    e.g. a network applied at every step of an unrolled rollout), with the layer's kernel
    and bias leaves, widths and ``positions`` = Σ_uses T_u."""

    uses: tuple[ConvUse, ...]

    @property
    def leaf(self) -> int:
        return self.uses[0].leaf

    @property
    def bias(self) -> int | None:
        return self.uses[0].bias

    @property
    def d_in(self) -> int:
        return self.uses[0].d_in

    @property
    def d_out(self) -> int:
        return self.uses[0].d_out

    @property
    def positions(self) -> int:
        return sum(u.positions for u in self.uses)


def conv_layers(convs: tuple[ConvUse, ...]) -> tuple[ConvLayer, ...]:
    """The convolutions grouped by kernel leaf, layers in the order of their first use."""
    by_leaf: dict[int, list[ConvUse]] = {}
    for c in convs:
        by_leaf.setdefault(c.leaf, []).append(c)
    return tuple(ConvLayer(tuple(uses)) for uses in by_leaf.values())


def checked_layer(layer: ConvLayer, jaxpr, users: dict, outputs: set) -> tuple[ConvUse, ...]:
    """The uses of one kernel leaf, refused in one line unless the leaf reaches nothing but
    these convolutions' kernels, every use computes the same kernel from it, and no use
    convolves a value computed from the kernel; the bias kept only where every use adds the
    same bias leaf and nothing else reads it (else the bias leaves join the leftover block)."""
    first = layer.uses[0]
    where = f"khig: convolution {first.eqn} (kernel {tuple(jaxpr.eqns[first.eqn].invars[1].aval.shape)})"
    convs = {u.eqn for u in layer.uses}
    # every value computed from the leaf without passing through one of its convolutions
    reach = {jaxpr.invars[layer.leaf]}
    for e, other in enumerate(jaxpr.eqns):
        if e not in convs and any(v in reach for v in other.invars if not isinstance(v, Literal)):
            reach.update(other.outvars)
    allowed = convs.union(*(u.chain for u in layer.uses))
    elsewhere = any(v in outputs or any(u not in allowed for u in users[v]) for v in reach)
    if elsewhere or any(jaxpr.eqns[u.eqn].invars[0] in reach for u in layer.uses):
        raise ValueError(f"{where}: parameter leaf {layer.leaf} is also used outside its convolutions' kernels; "
                         "use hig")  # fmt: skip
    if len({_kernel_signature(u, jaxpr) for u in layer.uses}) > 1:
        raise ValueError(f"{where}: parameter leaf {layer.leaf} reaches its {len(layer.uses)} convolutions as "
                         "differently computed kernels; use hig")  # fmt: skip
    biases = {u.bias for u in layer.uses}
    bias = biases.pop() if len(biases) == 1 else None
    if bias is not None and len(users[jaxpr.invars[bias]]) != len(layer.uses):
        bias = None
    return tuple(u._replace(bias=bias) for u in layer.uses)


def _kernel_signature(use: ConvUse, jaxpr) -> tuple:
    """What makes the kernel operand of ``use`` the same function of its leaf as another
    use's: the chain's primitives and parameters, and the kernel's shape and layout."""
    eqn = jaxpr.eqns[use.eqn]
    chain = tuple((jaxpr.eqns[c].primitive.name, str(jaxpr.eqns[c].params)) for c in use.chain)
    return chain, tuple(eqn.invars[1].aval.shape), eqn.params["dimension_numbers"].rhs_spec
