"""K-FAC through the simulator, with kfac-jax.

Sources: Martens & Grosse, *Optimizing Neural Networks with Kronecker-factored Approximate
Curvature*, ICML 2015 (the Kronecker factors, factored Tikhonov damping, the adaptive
learning rate and momentum from the exact quadratic model, Levenberg–Marquardt damping);
Botev & Martens, *KFAC-JAX*, 2022 (github.com/google-deepmind/kfac-jax: the curvature
estimator, the graph matcher and the optimizer used here).

What is approximated
--------------------
The curvature is the Gauss–Newton matrix of network *and* physics together. For a batch of
b samples with network parameters θ, simulator outputs y_i = P(f(x_i; θ)) ∈ ℝ^m (flattened)
and the batch-mean loss L = (1/b) Σ_i L_i(y_i),

    G = (1/b) Σ_i J_iᵀ H_i J_i,      J_i = ∂y_i/∂θ  (m × dim θ),   H_i = ∂²L_i/∂y_i²  (m × m),

and the update is θ ← θ + α Δ + μ v with Δ = −(Ĝ + λI)⁻¹ ∇L, v the previous update, and
α, μ chosen by minimising the quadratic model ½ dᵀ(G + λI)d + ∇Lᵀd exactly over the plane
spanned by Δ and v (kfac-jax's ``use_adaptive_learning_rate`` / ``use_adaptive_momentum``);
λ follows Levenberg–Marquardt: every ``damping_interval`` steps the reduction ratio
ρ = (L(θ') − L(θ)) / (model change) scales λ by ``damping_decay^interval`` up (ρ < ¼) or
down (ρ > ¾) (``use_adaptive_damping``). Ĝ is block-diagonal over layers; a dense layer
z = W a + c (a with a 1 appended for the bias) has the Kronecker block

    G_layer ≈ E[ā āᵀ] ⊗ E[ḡ ḡᵀ]   ((in+1)² and out² factors; ḡ = back-propagated
                                    output derivatives, sampled by kfac-jax's
                                    ``ggn_curvature_prop`` or exact with ``ggn_exact``),

inverted with factored damping (or exactly, ``exact_inverses``); ``blocks=full`` keeps the
layer's block dense instead ((in+1)·out squared: small layers only). Parameters kfac-jax
does not recognise as a dense layer (free variables of direct optimisation, scales)
get kfac-jax's generic diagonal block (``full``: dense);
convolutional networks are refused (below).

How the problem's loss is registered
------------------------------------
kfac-jax needs the loss as one of its registered losses; physgrad's L_i(y) is any function.
It is registered as a squared error (kfac-jax's ``register_squared_error_loss`` with
weight ½, i.e. ½‖z − z*‖²) on a linear transform of the simulator output,
z_i = C_iᵀ y_i with C_i held constant (stop-gradient), so that the registered loss's
Hessian in y is C_i C_iᵀ:

- ``loss_hessian=exact``: C_i = V √max(Λ, 0) from H_i = V Λ Vᵀ (per sample, exact m × m
  Hessian and eigendecomposition): G is the Gauss–Newton matrix of the problem's own loss
  (the negative curvature of a non-convex L_i dropped, as Gauss–Newton does). Costs O(b m³).
- ``loss_hessian=rayleigh``: C_i = √w_i I with w_i = gᵀH_i g / gᵀg, g = ∂L_i/∂y_i (one
  Hessian-vector product): exact for L_i = c‖y_i − y*_i‖² (any c, the common case),
  an isotropic approximation otherwise. Costs O(b m).
- ``auto`` (default): ``exact`` for m ≤ 256, else ``rayleigh``.

The gradient (∇L) and the loss values are always the problem's own; only the curvature
uses the registration.

How it runs inside the engine
-----------------------------
The engine compiles ``step`` as one function and gives ``init`` the parameters alone, so:

- kfac-jax's :class:`kfac_jax.Optimizer` (``multi_device=False``) is built per trace and
  called inside the engine's jit: its staged methods nest as inner jits. Its ``step`` needs
  the step number as a Python int only to decide statically whether the damping is
  adapted this step; ``global_step_int`` is passed a stand-in with the right residue and
  the traced step counter chooses between the two traced variants (``lax.cond``). No
  burn-in (it would need a data iterator): the first step estimates the curvature alone.
- Equinox keeps a dense kernel as (out, in) and applies it per sample (``W @ x`` under
  vmap), which kfac-jax's patterns (``x @ W``) do not match: kfac-jax sees the parameters
  with dense kernels transposed to (in, out), and an extra graph pattern matches
  ``vmap(x ↦ Wᵀx + c)`` (physgrad's :class:`~physgrad.nets.Dense`, ``eqx.nn.Linear``).
- ``init(params)`` has no batch, but kfac-jax's state depends on the blocks it matches.
  kfac-jax orders blocks by parameter, so ``init`` builds the state by tracing a stand-in
  function that applies each dense layer of ``params`` once in that form (and uses every
  other parameter generically). The step checks that the network's real registration gives
  the same state; a network whose layers kfac-jax sees differently is refused in one line.
- The method state is kfac-jax's state (as a flat tuple of arrays, so that checkpoints and
  the compiled step see plain arrays) and a PRNG key for its curvature sampling, seeded
  by ``seed``.

Refused, in one line: complex simulator outputs or parameters (kfac-jax's losses are
real; the quantum problems), a solver without derivatives, and networks that kfac-jax
registers other than as dense layers applied once per sample: the convolutional networks
(U-Net, ConvResNet), where kfac-jax's own patterns pick up parts of Equinox's convolutions
that the parameter-only ``init`` cannot foresee.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Callable
from typing import Any, NamedTuple, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp

from ..nets import Dense
from .base import OPEN_LOOP, AbstractMethod, required, trainable


class Blocks(enum.StrEnum):
    """The curvature blocks: ``KFAC`` (Kronecker factors per dense layer) or ``FULL`` (dense
    per-layer blocks, small networks only)."""

    KFAC = "kfac"
    FULL = "full"


class Estimation(enum.StrEnum):
    """kfac-jax's curvature estimator: ``GGN_CURVATURE_PROP`` (sampled, its default) or
    ``GGN_EXACT`` (one backward pass per output dimension after the loss transform)."""

    GGN_CURVATURE_PROP = "ggn_curvature_prop"
    GGN_EXACT = "ggn_exact"


class LossHessian(enum.StrEnum):
    """How the problem's loss is registered with kfac-jax (:func:`_curvature_output`):
    ``EXACT`` (its per-sample Hessian, convex part), ``RAYLEIGH`` (its Rayleigh quotient
    along the gradient, isotropic) or ``AUTO`` (exact up to ``EXACT_HESSIAN_MAX`` outputs)."""

    AUTO = "auto"
    EXACT = "exact"
    RAYLEIGH = "rayleigh"


_E = TypeVar("_E", bound=enum.StrEnum)


def _member(kind: type[_E], name: str) -> Callable[[Any], _E]:
    """A field converter: an enum member from itself or its value, with a one-line error
    naming the setting and its valid values."""

    def convert(value: Any) -> _E:
        try:
            return kind(value)
        except ValueError:
            valid = ", ".join(m.value for m in kind)
            raise ValueError(f"unknown {name} {value!r}; valid choices: {valid}") from None

    return convert


EXACT_HESSIAN_MAX = 256  # dim y up to which ``auto`` forms the loss Hessian


@functools.cache
def _kfac_jax():
    """kfac-jax, imported on first use: importing it pulls in distrax/TFP, which add
    warning filters (importing physgrad must not change global state). Without it: one line
    naming the extra (:class:`physgrad.extras.MissingExtra`)."""
    from ..extras import import_extra

    kfac_jax = import_extra("kfac_jax", "kfac", "kfac")
    _patch_eval_jaxpr_eqn(kfac_jax.tag_graph_matcher)
    return kfac_jax


def _patch_eval_jaxpr_eqn(tgm) -> None:
    """Make kfac-jax 0.0.8's jaxpr interpreter work with JAX >= 0.7, where
    ``Primitive.get_bind_params`` returns the parameters alone (it returned
    ``(subfuns, params)`` before). kfac-jax's tracer calls ``tgm.eval_jaxpr_eqn`` for
    every equation when estimating curvature; without this every curvature update fails
    with "not enough values to unpack". Replaced only if the installed JAX has the new
    convention, and only inside kfac-jax's own module (nothing else calls it)."""
    if getattr(tgm.eval_jaxpr_eqn, "_physgrad_compatible", False):
        return
    probe = jax.make_jaxpr(jnp.sin)(1.0).eqns[0]
    if not isinstance(probe.primitive.get_bind_params(probe.params), dict):
        return  # the old convention: kfac-jax's own interpreter works

    from jax.extend import source_info_util

    def eval_jaxpr_eqn(eqn, in_values):
        params = eqn.primitive.get_bind_params(eqn.params)
        with source_info_util.user_context(eqn.source_info.traceback):
            output = eqn.primitive.bind(*in_values, **params)
        return output if isinstance(output, list) else [output]

    eval_jaxpr_eqn._physgrad_compatible = True
    tgm.eval_jaxpr_eqn = eval_jaxpr_eqn


# --- Equinox dense layers in kfac-jax's layout -------------------------------------------
def _is_dense(node) -> bool:
    """An Equinox dense layer (physgrad's Dense or eqx.nn.Linear) in a parameter tree."""
    return isinstance(node, Dense | eqx.nn.Linear) and getattr(node.weight, "ndim", 0) == 2


def _transpose_kernels(params):
    """Dense kernels (out, in) ↔ (in, out); its own inverse. kfac-jax's dense blocks read
    a kernel as (in, out)."""
    flip = lambda m: eqx.tree_at(lambda m: m.weight, m, m.weight.T) if _is_dense(m) else m  # noqa: E731
    return jax.tree.map(flip, params, is_leaf=_is_dense)


def _default_float(tree):
    """Floating leaves in JAX's default float (float64 under x64, else float32). kfac-jax
    mixes its own scalars and sampled vectors, made in the default float, with the model's
    arrays; with a float32 model under x64 its branches disagree in dtype. So kfac-jax
    always computes in the default float and the step rounds back to the parameters' dtype."""
    wide = jax.dtypes.canonicalize_dtype(jnp.float64)
    return jax.tree.map(lambda a: a.astype(wide) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)


def _dense_with_bias(x, params):
    """The pattern kfac-jax should see as a dense layer: Equinox's per-sample ``W x + c``,
    vmapped over the batch, with the kernel given transposed (in, out)."""
    kernel, bias = params
    return jax.vmap(lambda xi: kernel.T @ xi + bias)(x)


def _dense_no_bias(x, params):
    (kernel,) = params
    return jax.vmap(lambda xi: kernel.T @ xi)(x)


def _dense_parameters(reversed_eqns):
    """The layer tag's parameters: kfac-jax's dense metadata and the matmul's settings
    (the tag's operands are output, input, then the parameters)."""
    kfac_jax = _kfac_jax()
    params = kfac_jax.tag_graph_matcher.num_unique_inputs(reversed_eqns[::-1]) - 1
    for eqn in reversed_eqns:
        if eqn.primitive.name == "dot_general":
            meta = kfac_jax.LayerMetaData(variant="dense", outputs_index=(0,), inputs_index=(1,),
                                          params_index=tuple(range(2, 2 + params)))  # fmt: skip
            return dict(meta=meta, **eqn.params)
    raise AssertionError("a dense pattern without a matmul")


@functools.cache
def _graph_patterns():
    """kfac-jax's own patterns plus Equinox's dense layers (with and without bias)."""
    kfac_jax = _kfac_jax()
    tgm = kfac_jax.tag_graph_matcher
    import numpy as np

    ours = tuple(
        tgm.GraphPattern(
            name=name,
            tag_primitive=kfac_jax.layers_and_loss_tags.layer_tag,
            compute_func=func,
            parameters_extractor_func=_dense_parameters,
            example_args=[np.zeros((2, 3)), [np.zeros(s) for s in shapes]],  # pyright: ignore[reportArgumentType]  # kfac-jax types them as JAX arrays; NumPy ones trace the same
        )  # fmt: skip
        for name, func, shapes in (
            ("equinox_dense_with_bias", _dense_with_bias, ((3, 4), (4,))),
            ("equinox_dense_no_bias", _dense_no_bias, ((3, 4),)),
        )
    )
    return ours + tuple(tgm.DEFAULT_GRAPH_PATTERNS)


# --- the registered loss ------------------------------------------------------------------
def _curvature_output(objective, y, batch, loss_hessian: LossHessian):
    """z (b, k) with ½‖z − z*‖² having the loss's Hessian (or its isotropic part) in y."""
    b = y.shape[0]
    flat = y.reshape(b, -1)
    m = flat.shape[1]
    per_sample = lambda v, s: objective.loss(v.reshape(y.shape[1:]), s)  # noqa: E731
    if loss_hessian is LossHessian.AUTO:
        loss_hessian = LossHessian.EXACT if m <= EXACT_HESSIAN_MAX else LossHessian.RAYLEIGH
    if loss_hessian is LossHessian.EXACT:
        hessian = jax.lax.stop_gradient(jax.vmap(jax.hessian(per_sample))(flat, batch))
        eigenvalues, vectors = jnp.linalg.eigh(hessian)
        # Gauss–Newton keeps the loss's convex part: negative eigenvalues dropped.
        root = vectors * jnp.sqrt(jnp.maximum(eigenvalues, 0.0))[:, None, :]
        return jnp.einsum("bmk,bm->bk", root, flat)

    def weight(v, s):
        g = jax.grad(per_sample)(v, s)
        _, hg = jax.jvp(lambda u: jax.grad(per_sample)(u, s), (v,), (g,))
        gg = jnp.vdot(g, g)
        return jnp.where(gg > 0, jnp.maximum(jnp.vdot(g, hg), 0.0) / jnp.where(gg > 0, gg, 1.0), 0.0)

    scale = jax.lax.stop_gradient(jnp.sqrt(jax.vmap(weight)(flat, batch)))
    return scale[:, None] * flat


def _refuse_complex(objective, params, batch) -> None:
    """The one-line ValueError for what kfac-jax cannot take (complex parameters or outputs, a
    rollout), from shapes alone (``params``, ``batch`` may be ``jax.ShapeDtypeStruct``)."""
    if any(jnp.issubdtype(leaf.dtype, jnp.complexfloating) for leaf in jax.tree.leaves(params)):
        raise ValueError(
            "kfac: the network has complex parameters, which kfac-jax does not support; use gn, hig or adam"
        )
    predict = required(objective.predict, "predict")
    sample = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape[1:], a.dtype), batch)
    y = jax.eval_shape(predict, params, sample)
    if not isinstance(y, jax.ShapeDtypeStruct):  # a closed loop's trajectory: the controller runs every step
        raise ValueError(f"kfac: predict returns a {type(y).__name__} of {len(jax.tree.leaves(y))} arrays (a rollout), and kfac-jax's loss and dense blocks need one array per sample from layers applied once; use a rollout method")  # fmt: skip  # noqa: E501
    complex_outputs = [leaf.dtype for leaf in jax.tree.leaves(y) if jnp.issubdtype(leaf.dtype, jnp.complexfloating)]
    if complex_outputs:
        raise ValueError(f"kfac: the simulator output is complex ({complex_outputs[0]}) and kfac-jax's losses are "
                         "real; use gn, hig or adam")  # fmt: skip


class KFACState(NamedTuple):
    """kfac-jax's optimizer state as a flat tuple of arrays, and the PRNG key data (uint32)
    for its curvature sampling."""

    kfac: tuple
    rng: jax.Array


class KFAC(AbstractMethod):
    """K-FAC (kfac-jax) on the Gauss–Newton curvature of network and simulator (module
    docstring); hyperparameters as :func:`kfac`."""

    adaptive: bool = eqx.field(static=True, default=True)
    lr: float = eqx.field(static=True, default=1e-3)
    momentum: float = eqx.field(static=True, default=0.9)
    damping: float = eqx.field(static=True, default=1e-3)
    adaptive_damping: bool = eqx.field(static=True, default=True)
    min_damping: float = eqx.field(static=True, default=1e-8)
    damping_interval: int = eqx.field(static=True, default=5)
    damping_decay: float = eqx.field(static=True, default=0.9)
    curvature_ema: float = eqx.field(static=True, default=0.95)
    inverse_every: int = eqx.field(static=True, default=5)
    blocks: Blocks = eqx.field(static=True, default=Blocks.KFAC, converter=_member(Blocks, "blocks"))
    estimation: Estimation = eqx.field(
        static=True, default=Estimation.GGN_CURVATURE_PROP, converter=_member(Estimation, "estimation")
    )
    loss_hessian: LossHessian = eqx.field(
        static=True, default=LossHessian.AUTO, converter=_member(LossHessian, "loss_hessian")
    )
    exact_inverses: bool = eqx.field(static=True, default=False)
    l2_reg: float = eqx.field(static=True, default=0.0)
    seed: int = eqx.field(static=True, default=0)
    precon_power: float = eqx.field(static=True, default=-1.0)

    def __check_init__(self):
        if not (self.damping > 0 and self.min_damping >= 0 and self.damping_interval >= 1 and self.inverse_every >= 1):
            raise ValueError("kfac needs damping > 0, min_damping >= 0, damping_interval >= 1 and inverse_every >= 1")
        if not (0 < self.damping_decay < 1 and 0 <= self.curvature_ema < 1):
            raise ValueError("kfac needs 0 < damping_decay < 1 and 0 <= curvature_ema < 1")
        if not self.precon_power < 0 or (self.precon_power != -1 and not self.exact_inverses):
            raise ValueError(f"kfac needs precon_power < 0, and exact_inverses=true unless -1; got {self.precon_power}")

    def check(self, objective):
        objective.require(OPEN_LOOP, "kfac")

    def footprint(self, objective, params, batch, devices: int = 1) -> int:
        """0 (kfac-jax's curvature blocks are not counted); refuses from shapes alone what
        :meth:`step` would refuse, so a run or a bench says so before any data exist."""
        params, static = trainable(params)
        _refuse_complex(objective.bind_static(static), params, batch)
        return 0

    # --- kfac-jax's optimizer, configured ---------------------------------------------------
    def _optimizer(self, func):
        kfac_jax = _kfac_jax()
        full = {"dense": kfac_jax.DenseFull, "generic": kfac_jax.NaiveFull} if self.blocks is Blocks.FULL else None
        return kfac_jax.Optimizer(
            value_and_grad_func=jax.value_and_grad(func),
            l2_reg=self.l2_reg,
            use_adaptive_learning_rate=self.adaptive,
            use_adaptive_momentum=self.adaptive,
            use_adaptive_damping=self.adaptive_damping,
            initial_damping=self.damping if self.adaptive_damping else None,
            min_damping=self.min_damping,
            damping_adaptation_interval=self.damping_interval,
            damping_adaptation_decay=self.damping_decay,
            num_burnin_steps=0,  # burn-in needs a data iterator; the EMA starts from the first batch
            estimation_mode=self.estimation.value,
            curvature_ema=self.curvature_ema,
            curvature_update_period=1,  # every step: keeps kfac-jax's static step logic step-independent
            inverse_update_period=self.inverse_every,
            use_exact_inverses=self.exact_inverses,
            precon_power=self.precon_power,
            layer_tag_to_block_ctor=full,
            auto_register_kwargs=dict(graph_patterns=_graph_patterns()),
            multi_device=False,
        )

    def _fixed(self) -> dict[str, Any]:
        """What kfac-jax's step takes as arguments rather than adapting."""
        out = {}
        if not self.adaptive:
            out.update(learning_rate=jnp.asarray(self.lr), momentum=jnp.asarray(self.momentum))
        if not self.adaptive_damping:
            out.update(damping=jnp.asarray(self.damping))
        return out

    # --- state ------------------------------------------------------------------------------
    def init(self, params):
        params = trainable(params)[0]  # a whole module: its array leaves
        kparams = _default_float(_transpose_kernels(params))
        optimizer = self._optimizer(_stand_in)
        state = optimizer.init(kparams, jax.random.key(self.seed), jnp.zeros((2,)))
        return KFACState(tuple(jax.tree.leaves(state)), jax.random.key_data(jax.random.key(self.seed + 1)))

    def step(self, objective, params, state, batch):
        params, static = trainable(params)  # the array leaves (a whole module's others come back unchanged)
        objective = objective.bind_static(static)
        real = jnp.result_type(*[leaf.dtype for leaf in jax.tree.leaves(params)])
        # Checked before kfac-jax traces anything (a plain call: no JAX boundary adds to the
        # message when the step is called outside a jit).
        _refuse_complex(objective, params, batch)
        predict, loss = required(objective.predict, "predict"), required(objective.loss, "loss")

        def func(kparams, batch):
            y = jax.vmap(predict, (None, 0))(_transpose_kernels(kparams), batch)
            z = _curvature_output(objective, y, batch, self.loss_hessian)
            # kfac-jax draws its curvature-sampling vectors in JAX's default float (float64
            # under x64): the registered output has that dtype, cast back along the graph.
            # kfac-jax's squared error is weight·‖z − z*‖² (Hessian 2·weight·I): weight ½.
            _kfac_jax().register_squared_error_loss(z.astype(jax.dtypes.canonicalize_dtype(jnp.float64)), weight=0.5)
            return jnp.mean(jax.vmap(loss)(y, batch))

        kparams = _default_float(_transpose_kernels(params))
        optimizer = self._optimizer(func)
        key, rng = jax.random.split(jax.random.wrap_key_data(state.rng))
        # The network's own registration (finalises the optimizer; the values are unused).
        like = optimizer.init(kparams, rng, batch)
        leaves, treedef = jax.tree.flatten(like)
        if [(a.shape, a.dtype) for a in leaves] != [(a.shape, a.dtype) for a in state.kfac]:
            raise ValueError("kfac: kfac-jax registers this network's layers other than as dense layers applied once "
                             "per sample (convolutions, shared or repeated layers); use gn, hig or adam")  # fmt: skip
        kstate = jax.tree.unflatten(treedef, state.kfac)

        def run(adapt_damping: bool):
            # kfac-jax decides from the Python step number whether to adapt the damping;
            # any number with the right residue gives the same computation.
            n = self.damping_interval
            step_number = 2 * n - 1 if adapt_damping else 2 * n
            new, new_state, stats = optimizer.step(kparams, kstate, rng, batch=batch, global_step_int=step_number,  # pyright: ignore[reportAssignmentType]  # 3 values: func has no state
                                                   **self._fixed())  # fmt: skip
            new_leaves = tuple(a.astype(b.dtype) for a, b in zip(jax.tree.leaves(new_state), state.kfac))
            picked = {k: jnp.asarray(stats[k], real) for k in ("loss", "learning_rate", "momentum", "damping", "rho")}
            return new, new_leaves, picked

        if self.adaptive_damping and self.damping_interval > 1:
            due = (kstate.step_counter + 1) % self.damping_interval == 0
            new, new_leaves, stats = jax.lax.cond(due, lambda: run(True), lambda: run(False))
        else:
            new, new_leaves, stats = run(self.adaptive_damping)
        new = jax.tree.map(lambda a, b: a.astype(b.dtype), _transpose_kernels(new), params)
        return eqx.combine(new, static), KFACState(new_leaves, jax.random.key_data(key)), stats


def _stand_in(kparams, batch):
    """A function with the same kfac-jax blocks as any network with these parameters whose
    dense layers are each applied once per sample: every dense layer in the matched form,
    every other parameter used generically. Traced by ``init`` for the state's shapes only."""
    outputs = []
    for node in jax.tree.leaves(kparams, is_leaf=_is_dense):
        if _is_dense(node):
            x = jnp.ones((batch.shape[0], node.weight.shape[0]), node.weight.dtype)
            params = [node.weight] if node.bias is None else [node.weight, node.bias]
            outputs.append(jnp.sum((_dense_with_bias if len(params) == 2 else _dense_no_bias)(x, params), axis=1))
        else:
            outputs.append(jnp.broadcast_to(jnp.sum(node), batch.shape))
    z = jnp.stack([jnp.real(o) for o in outputs], axis=1)
    _kfac_jax().register_squared_error_loss(z, weight=0.5)
    return 0.5 * jnp.mean(jnp.sum(z**2, axis=1))


def kfac(
    *,
    adaptive: bool = True,
    lr: float = 1e-3,
    momentum: float = 0.9,
    damping: float = 1e-3,
    adaptive_damping: bool = True,
    min_damping: float = 1e-8,
    damping_interval: int = 5,
    damping_decay: float = 0.9,
    curvature_ema: float = 0.95,
    inverse_every: int = 5,
    blocks: Blocks | str = Blocks.KFAC,
    estimation: Estimation | str = Estimation.GGN_CURVATURE_PROP,
    loss_hessian: LossHessian | str = LossHessian.AUTO,
    exact_inverses: bool = False,
    l2_reg: float = 0.0,
    seed: int = 0,
    precon_power: float = -1.0,
) -> AbstractMethod:
    """K-FAC (Martens & Grosse 2015) through the simulator with kfac-jax: Kronecker-factored Gauss–Newton of network and physics, adaptive step, momentum and damping.

    Arguments:
        adaptive: kfac-jax's adaptive learning rate and momentum (exact quadratic model);
            False: fixed ``lr`` and ``momentum``.
        damping: λ, the initial value when ``adaptive_damping`` (Levenberg–Marquardt every
            ``damping_interval`` steps, factor ``damping_decay^interval``, floor
            ``min_damping``), else fixed. It scales with the loss.
        curvature_ema: decay of the factors' moving average; ``inverse_every``: steps
            between refreshing their inverses.
        blocks: :class:`Blocks` (or its value: ``"kfac"``, ``"full"``).
        estimation: :class:`Estimation` (or ``"ggn_curvature_prop"``, ``"ggn_exact"``).
        loss_hessian: :class:`LossHessian` (or ``"auto"``, ``"exact"``, ``"rayleigh"``).
        exact_inverses: invert the damped Kronecker blocks exactly (eigendecompositions)
            instead of kfac-jax's factored damping.
        l2_reg: weight decay coefficient known to the curvature (not added to the loss).
        seed: the PRNG seed of kfac-jax's curvature sampling.
        precon_power: p in ``(Ĝ + λI)^p ∇L`` (−0.75: HIG's, ``kfac_hig``); ≠ −1 needs ``exact_inverses``.
    """
    from ..extras import require

    require("kfac", "kfac")  # kfac-jax is the optional extra physgrad[kfac]
    hyperparameters = {name: value for name, value in locals().items() if name in KFAC.__dataclass_fields__}
    return KFAC(**hyperparameters)
