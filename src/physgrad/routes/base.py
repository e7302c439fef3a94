"""The route protocol and the joint-Jacobian value a route is handed.

Gauss–Newton and half-inverse gradients need ``J^κ g = V Σ^κ Uᵀ g`` for the joint
per-sample Jacobian ``J = ∂y/∂θ`` (rows = batch × output size, sample-major; columns = the
P network parameters, ``ravel_pytree`` order) and the output gradient ``g = ∂L/∂y`` of the
batch-mean loss (Schnell, Holl, Thuerey, ICLR 2022). A route decides how, as lineax's
solvers decide how a linear system is solved: :class:`AbstractRoute.compute` takes the
:class:`JointJacobian` of the step, a value that holds what every route asks of J's shape —
rows, parameter count, one sample's output shape and the dense-layer structure of the
per-sample program — built ONCE per step by one trace of the user's ``predict``
(:meth:`JointJacobian.of`). Routes compute J's rows by replaying that traced program
(:meth:`JointJacobian.predict`), so tracing a jitted step calls ``predict`` once on one
device (the sharded routes trace it again inside ``shard_map``, where the per-device types
differ), and the loss and ``g`` come from the outputs the route already has
(:meth:`JointJacobian.loss_and_gradient`), never from a second forward pass.

The dense-layer structure (:func:`find_structure`): a parameter leaf that is a matrix used
exactly once, as an operand of one ``dot_general`` contracting one of its axes with a
vector, is a dense layer (``eqx.nn.Linear``, :class:`physgrad.nets.Dense`, a hand-written
``W @ x`` or ``x @ W``), found in the traced program, not by module type; a bias added right
after the product is recorded with it. The other leaves are "explicit": their Jacobian rows
are formed in groups of at most ``CHUNK_ELEMENTS`` numbers (:mod:`.structured`).

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import abc
import dataclasses
import functools
import math
from collections.abc import Callable
from typing import Any, ClassVar, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.extend.core import ClosedJaxpr, Literal, jaxpr_as_fun
from jax.flatten_util import ravel_pytree
from jax.sharding import PartitionSpec
from jaxtyping import Array, PyTree

from ..distributed import AXIS
from ..jacobian import flat_output, stacked_jacobian

F64 = 8  # bytes of a float64

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
    treedef: Any
    out_tree: Any

    @property
    def explicit_parameters(self) -> int:
        return sum(self.leaf_sizes[k] for group in self.groups for k in group)

    def regrouped(self, rows: int, chunk_elements: int) -> Structure:
        """The explicit leaves cut into groups of at most ``chunk_elements // rows``
        parameters (a larger leaf alone), in leaf order; no tracing."""
        dense_leaves = {u.leaf for u in self.dense} | {u.bias for u in self.dense if u.bias is not None}
        per_group = max(1, chunk_elements // max(rows, 1))
        groups, current, filled = [], [], 0
        for k, size in enumerate(self.leaf_sizes):
            if k in dense_leaves or size == 0:
                continue
            if current and filled + size > per_group:
                groups.append(tuple(current))
                current, filled = [], 0
            current.append(k)
            filled += size
        if current:
            groups.append(tuple(current))
        return self._replace(groups=tuple(groups))


def find_structure(
    predict: Callable, params: PyTree, sample: PyTree, rows: int, chunk_elements: int = CHUNK_ELEMENTS
) -> Structure:
    """Trace ``predict(params, sample)`` for one sample and find its dense layers.

    ``rows`` is the number of Jacobian rows of the whole batch (to size the explicit
    groups). Only shapes and types are used: ``params`` and ``sample`` may be tracers."""
    return _trace(predict, params, sample)[0].regrouped(rows, chunk_elements)


def _trace(predict: Callable, params: PyTree, sample: PyTree) -> tuple[Structure, Any]:
    """The one trace of ``predict``: its program, dense layers (no groups yet) and output shape."""
    # None leaves (the static part of an eqx.partition) stay None: they are not inputs.
    leaves, treedef = jax.tree.flatten(params)
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
    sizes = tuple(math.prod(x.shape) for x in leaves)
    structure = Structure(closed, tuple(dense), (), sizes, treedef, jax.tree.structure(out_shape))
    return structure, out_shape


def batch_output_map(predict: Callable[[PyTree, PyTree], Array], params: PyTree, batch: PyTree):
    """``(F, θ)``: the raveled parameters and ``F(θ)`` = every sample's flat output,
    concatenated sample-major (the rows of the stacked Jacobian)."""
    flat, unravel = ravel_pytree(params)

    def outputs(theta):
        return jax.vmap(lambda s: flat_output(predict(unravel(theta), s)))(batch).ravel()

    return outputs, flat


@dataclasses.dataclass(frozen=True)
class JointJacobian:
    """The joint Jacobian of one step as a value: the pieces it is made of and its shape
    facts, built once by :meth:`of` (one trace of ``predict``) and handed to a route.

    ``rows`` = batch × output size (complex outputs count twice: (Re, Im) pairs), ``size`` =
    P, ``output`` one sample's output (a ``jax.ShapeDtypeStruct``), ``structure`` the traced
    per-sample program with its dense layers and explicit groups (``CHUNK_ELEMENTS``)."""

    objective: Any  # predict(params, sample) -> y and loss(y, sample) -> L_i
    params: PyTree
    batch: PyTree
    structure: Structure
    output: Any
    batch_size: int
    rows: int
    size: int

    @classmethod
    def of(cls, objective, params: PyTree, batch: PyTree) -> JointJacobian:
        """The value for this step; ``params`` and ``batch`` may be tracers, arrays or
        shape stand-ins (footprints)."""
        sample = jax.tree.map(lambda a: a[0], batch)
        structure, output = _trace(objective.predict, params, sample)
        if not hasattr(output, "shape"):  # a pytree of outputs (a closed loop's trajectory)
            raise ValueError(
                "the Jacobian routes need predict(params, sample) to return one array per sample, "
                f"got {type(output).__name__}; for a closed-loop rollout use bptt, sbptt_m or sbptt_c"
            )
        per_sample = math.prod(output.shape) * (2 if jnp.issubdtype(output.dtype, jnp.complexfloating) else 1)
        b = jax.tree.leaves(batch)[0].shape[0]
        rows, size = b * per_sample, sum(math.prod(x.shape) for x in jax.tree.leaves(params))
        return cls(objective, params, batch, structure.regrouped(rows, CHUNK_ELEMENTS), output, b, rows, size)

    @property
    def shape(self) -> tuple[int, int]:
        return self.rows, self.size

    @property
    def itemsize(self) -> int:
        """Bytes of the parameters' widest float (J's entries)."""
        return max((jnp.dtype(x.dtype).itemsize for x in jax.tree.leaves(self.params)), default=4)

    def predict(self, params: PyTree, sample: PyTree) -> Array:
        """The user's ``predict``, replayed from the traced program (no new trace of it)."""
        s = self.structure
        run = jaxpr_as_fun(s.jaxpr)
        return jax.tree.unflatten(s.out_tree, run(*jax.tree.leaves(params), *jax.tree.leaves(sample)))

    def loss_and_gradient(self, y: Array, devices: int = 1) -> tuple[Array, Array]:
        """The batch-mean loss (divided by ``devices``: a device's share of the global mean)
        and its gradient ``g`` w.r.t. the flat outputs ``y`` (b, d), raveled sample-major."""
        output, loss = self.output, self.objective.loss

        def unflatten(y_flat):  # the flat outputs back in predict's shape
            if jnp.issubdtype(output.dtype, jnp.complexfloating):
                pairs = y_flat.reshape(y_flat.shape[0], *output.shape, 2)
                return (pairs[..., 0] + 1j * pairs[..., 1]).astype(output.dtype)
            return y_flat.reshape(y_flat.shape[0], *output.shape)

        def mean_loss(y_flat):
            return jnp.mean(jax.vmap(loss)(unflatten(y_flat), self.batch)) / devices

        value, g = jax.value_and_grad(mean_loss)(y)
        return value, g.ravel()

    def jacobian_and_gradient(self, devices: int = 1) -> tuple[Array, Array, Array]:
        """``J`` (rows, P), ``g`` (rows,) and this batch's share of the loss (the batch is
        1/devices of the global one)."""
        jac, y = stacked_jacobian(self.predict, self.params, self.batch)
        loss, g = self.loss_and_gradient(y, devices)
        return jac, g, loss

    def output_gradient(self) -> tuple[Array, Array]:
        """``g = ∂L/∂y`` (rows,) and the batch-mean loss, by one forward pass (no J)."""
        outputs, flat = batch_output_map(self.predict, self.params, self.batch)
        loss, g = self.loss_and_gradient(outputs(flat).reshape(self.batch_size, -1))
        return g, loss


class AbstractRoute(eqx.Module):
    """How ``J^κ g`` is computed: ``route.compute(jacobian, exponent, truncation) ->
    (direction, loss, stats)`` for a :class:`JointJacobian`; ``route(objective, params,
    batch, exponent, truncation)`` builds the value and computes.

    ``exponent`` is κ or a :class:`~physgrad.routes.spectrum.Damped` filter; ``truncation``
    τ drops σ ≤ τ σ_max. The direction is flat (P,), in ``ravel_pytree`` order and the
    parameters' dtype; ``stats`` holds ``route`` (:attr:`code`, the index in
    :data:`physgrad.routes.ROUTE_NAMES`), ``rank``, ``sigma_max``, ``sigma_min_kept``."""

    code: ClassVar[int]

    @abc.abstractmethod
    def compute(
        self, jacobian: JointJacobian, exponent, truncation: float
    ) -> tuple[Array, Array, dict[str, Array]]: ...

    def __call__(self, objective, params, batch, exponent, truncation: float):
        jacobian = JointJacobian.of(objective, params, batch)
        return self.resolve(jacobian).compute(jacobian, exponent, truncation)

    def instead(self, jacobian: JointJacobian) -> AbstractRoute | None:
        """None when this route takes this Jacobian's shape; else the route that runs in
        its place (a route that cannot take a shape says so here, and only here)."""
        return None

    def resolve(self, jacobian: JointJacobian) -> AbstractRoute:
        """The route that runs on this Jacobian: this one, or the one it names
        :meth:`instead`; an :class:`~physgrad.routes.Auto` chooses by shape. Callers
        compute with, and measure, the resolved route."""
        other = self.instead(jacobian)
        return self if other is None else other

    def check_batch_size(self, batch_size: int) -> None:
        """Raise ``ValueError`` if the route cannot take batches of this size."""

    def footprint(self, objective, params, batch, devices: int = 1) -> int:
        """Bytes per device of the large arrays of the route that runs (:meth:`resolve`)
        for this (global) batch spread over ``devices`` devices, from shapes alone
        (nothing is computed); 0 when the route cannot tell."""
        jacobian = JointJacobian.of(objective, params, batch)
        return self.resolve(jacobian).footprint_of(jacobian, devices)

    @abc.abstractmethod
    def footprint_of(self, jacobian: JointJacobian, devices: int = 1) -> int:
        """:meth:`footprint` of a built value, for a shape this route takes."""

    @classmethod
    def name(cls) -> str:
        """The route's name as steps report it (:data:`~physgrad.routes.ROUTE_NAMES`)."""
        return cls.__name__.lower()

    def stats(self, spectrum: dict[str, Array]) -> dict[str, Array]:
        """A step's statistics: this route's code and the spectrum."""
        return {"route": jnp.asarray(self.code, jnp.int32), **spectrum}


class AbstractMatrixFree(AbstractRoute):
    """A route that never forms J: from the map ``(params, sample) -> y``, the batch and
    ``g`` (one forward pass, :meth:`JointJacobian.output_gradient`) to the direction."""

    @abc.abstractmethod
    def power(
        self,
        predict: Callable[[PyTree, PyTree], Array],
        params: PyTree,
        batch: PyTree,
        grad: Array,
        exponent,
        truncation: float,
    ) -> tuple[Array, dict[str, Array]]:
        """``(J^κ g, spectrum)``: ``predict`` gives one sample's output, ``batch`` holds b
        samples (leading axis), ``grad`` is ``g`` (m,), sample-major as the stacked
        Jacobian's rows; the direction is raveled in ``ravel_pytree`` order, in the
        parameters' dtype."""

    def compute(self, jacobian, exponent, truncation):
        g, loss = jacobian.output_gradient()
        direction, spectrum = self.power(jacobian.predict, jacobian.params, jacobian.batch, g, exponent, truncation)
        return direction, loss, self.stats(spectrum)


def over_devices(local: Callable, jacobian: JointJacobian, devices: int, exponent, truncation):
    """``local(objective, params, batch, devices=, exponent=, truncation=)`` run by every
    device on its share of the batch (``shard_map``), parameters replicated; returns the
    replicated ``(direction, loss, spectrum)``."""
    spec = PartitionSpec(AXIS)
    body = functools.partial(local, jacobian.objective, devices=devices, exponent=exponent, truncation=truncation)
    out = jax.shard_map(body, in_specs=(PartitionSpec(), spec), out_specs=PartitionSpec())
    return out(jacobian.params, jacobian.batch)
