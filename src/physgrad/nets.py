"""Networks in Equinox with the papers' (Keras) initialisation.

The HIG paper's networks are Keras ``Dense`` stacks: glorot-uniform kernels,
``U(−a, a)`` with ``a = sqrt(6 / (fan_in + fan_out))``, and zero biases. Equinox's own
``Linear`` initialises differently, so the weights are re-drawn here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .errors import warn_deprecated


def identity(x: Array) -> Array:
    """The identity activation (a linear network)."""
    return x


# The deprecated string spellings of MLP's activation (one release); the command line's own
# names are physgrad.harness.objects.ACTIVATIONS.
_ACTIVATION_NAMES = {
    "relu": jax.nn.relu,
    "tanh": jax.nn.tanh,
    "sigmoid": jax.nn.sigmoid,
    "gelu": jax.nn.gelu,
    "identity": identity,
}


def glorot_uniform(key: PRNGKeyArray, fan_out: int, fan_in: int, dtype) -> Array:
    """Glorot/Xavier uniform kernel of shape (fan_out, fan_in) (Glorot & Bengio 2010)."""
    limit = (6.0 / (fan_in + fan_out)) ** 0.5
    return jax.random.uniform(key, (fan_out, fan_in), dtype, -limit, limit)


class Dense(eqx.Module):
    """Affine layer ``y = W x + b`` with a glorot-uniform ``W`` (out, in) and zero ``b``."""

    weight: Float[Array, "out in"]
    bias: Float[Array, " out"]

    def __init__(self, in_size: int, out_size: int, *, key: PRNGKeyArray, dtype=jnp.float32):
        self.weight = glorot_uniform(key, out_size, in_size, dtype)
        self.bias = jnp.zeros((out_size,), dtype)

    def __call__(self, x: Float[Array, " in"]) -> Float[Array, " out"]:
        return self.weight @ x + self.bias


class MLP(eqx.Module):
    """Fully connected network ``sizes[0] → … → sizes[-1]``, activation on hidden layers only.

    Example: ``MLP((4, 20, 20, 20, 96), jax.nn.relu, key=k)`` is the HIG oscillator network
    (2,956 parameters). Input and output are unbatched vectors; vmap over samples.
    ``activation`` is any elementwise function (``jax.nn.tanh``, ``jax.nn.relu``, ...); a name
    (``"tanh"``) still works for one release, with a ``DeprecationWarning``.
    """

    layers: tuple[Dense, ...]
    activation: Callable[[Array], Array] = eqx.field(static=True)

    def __init__(
        self, sizes: Sequence[int], activation: Callable[[Array], Array] | str, *, key: PRNGKeyArray, dtype=jnp.float32
    ):
        activation = _activation_function(activation, _ACTIVATION_NAMES, f"MLP(..., {activation!r})", "jax.nn.tanh")
        keys = jax.random.split(key, len(sizes) - 1)
        self.layers = tuple(
            Dense(n_in, n_out, key=k, dtype=dtype) for n_in, n_out, k in zip(sizes[:-1], sizes[1:], keys)
        )
        self.activation = activation  # pyright: ignore[reportAttributeAccessIssue]  (a str was mapped above)

    def __call__(self, x: Float[Array, " in"]) -> Float[Array, " out"]:
        for layer in self.layers[:-1]:
            x = self.activation(layer(x))
        return self.layers[-1](x)


def parameter_count(module) -> int:
    """Number of scalar parameters (inexact array leaves) in an Equinox module."""
    return sum(leaf.size for leaf in jax.tree.leaves(eqx.filter(module, eqx.is_inexact_array)))


# The deprecated string spellings of UNet's activation (one release).
_UNET_ACTIVATION_NAMES = {"relu": jax.nn.relu, "leaky_relu": jax.nn.leaky_relu}


def _activation_function(
    activation: Callable[[Array], Array] | str, names: dict[str, Callable[[Array], Array]], call: str, example: str
) -> Callable[[Array], Array]:
    """``activation`` itself, or the function of a deprecated name in ``names`` (MLP's and
    UNet's, one release) with a ``DeprecationWarning`` that names the ``call`` and suggests
    the function ``example``."""
    if isinstance(activation, str):
        warn_deprecated(f"{call} is deprecated; pass the function, e.g. activation={example}")
        if activation not in names:
            raise ValueError(f"unknown activation {activation!r}; valid choices: {', '.join(names)}")
        return names[activation]
    if not callable(activation):
        raise TypeError(f"activation must be a function (e.g. {example}), got {activation!r}")
    return activation


def _circular_conv(conv: eqx.nn.Conv2d, x: Float[Array, "c h w"]) -> Float[Array, "c2 h w"]:
    """3×3 convolution with periodic ("circular") padding, as PhiFlow's U-Net pads."""
    pad = conv.kernel_size[0] // 2
    return conv(jnp.pad(x, ((0, 0), (pad, pad), (pad, pad)), mode="wrap"))


def standardised_weight(weight: Float[Array, "out in *k"], eps: float = 1e-5) -> Float[Array, "out in *k"]:
    """Weight standardisation (Qiao et al. 2019) with He's gain: each output channel's
    kernel minus its mean over (in, *k), divided by its standard deviation, times
    √(2 / fan_in); so a conv's output scale does not depend on the weights' scale (as
    under batch norm) and keeps the signal's scale through a ReLU (He et al. 2015)."""
    axes = tuple(range(1, weight.ndim))
    fan_in = math.prod(weight.shape[1:])
    mean = jnp.mean(weight, axis=axes, keepdims=True)
    std = jnp.std(weight, axis=axes, keepdims=True)
    return (weight - mean) / (std + eps) * math.sqrt(2.0 / fan_in)


def _he_conv(c_in: int, c_out: int, kernel: int, *, key: PRNGKeyArray, dtype) -> eqx.nn.Conv2d:
    """Conv2d with He-normal kernel N(0, 2 / fan_in) and zero bias."""
    conv = eqx.nn.Conv2d(c_in, c_out, kernel, key=key, dtype=dtype)
    weight = jax.random.normal(key, conv.weight.shape, dtype) * math.sqrt(2.0 / math.prod(conv.weight.shape[1:]))
    assert conv.bias is not None  # use_bias defaults to True
    return eqx.tree_at(lambda c: (c.weight, c.bias), conv, (weight, jnp.zeros_like(conv.bias)))


class _DoubleConv(eqx.Module):
    """(3×3 circular conv → activation) × 2, the convs optionally weight-standardised."""

    first: eqx.nn.Conv2d
    second: eqx.nn.Conv2d
    activation: Callable[[Array], Array] = eqx.field(static=True, default=jax.nn.relu)
    standardise: bool = eqx.field(static=True, default=False)

    def __init__(self, c_in: int, c_out: int, *, key: PRNGKeyArray, dtype,
                 activation: Callable[[Array], Array] = jax.nn.relu, standardise: bool = False):  # fmt: skip
        k1, k2 = jax.random.split(key)
        make = (
            _he_conv if standardise else (lambda i, o, k, *, key, dtype: eqx.nn.Conv2d(i, o, k, key=key, dtype=dtype))
        )
        self.first = make(c_in, c_out, 3, key=k1, dtype=dtype)
        self.second = make(c_out, c_out, 3, key=k2, dtype=dtype)
        self.activation = activation
        self.standardise = standardise

    def _conv(self, conv, x):
        if self.standardise:
            conv = eqx.tree_at(lambda c: c.weight, conv, standardised_weight(conv.weight))
        return _circular_conv(conv, x)

    def __call__(self, x):
        act = self.activation
        return act(self._conv(self.second, act(self._conv(self.first, x))))


def _max_pool_2x2(x: Float[Array, "c h w"]) -> Float[Array, "c h/2 w/2"]:
    c, h, w = x.shape
    return x.reshape(c, h // 2, 2, w // 2, 2).max(axis=(2, 4))


def _upsample_2x(x: Float[Array, "c h w"]) -> Float[Array, "c 2*h 2*w"]:
    """Bilinear ×2 upsampling with half-pixel centres (PyTorch ``align_corners=False``)."""
    c, h, w = x.shape
    return jax.image.resize(x, (c, 2 * h, 2 * w), "bilinear")


class UNet(eqx.Module):
    """The SIP paper's U-Net (PhiFlow ``u_net``), per sample: (c_in, H, W) → (c_out, H, W).

    ``levels`` resolution levels with ``filters`` channels each: a double 3×3 conv at full
    resolution, then per lower level a 2×2 max-pool and a double conv; going up, bilinear
    ×2 upsampling, concatenation with the skip connection and a double conv; a 1×1 output
    conv. Convolutions pad circularly; ``activation`` (any elementwise function, ReLU by
    default; a name, ``"relu"`` or ``"leaky_relu"``, still works for one release with a
    ``DeprecationWarning``) after each conv; PyTorch's default initialisation
    (U(±1/√fan_in) for kernels and biases, which is Equinox's too). ``u_net(1, 1)``
    (4 levels × 16 filters) has 37,249 parameters here: PhiFlow's 37,697 minus the 448
    batch-norm scales and offsets. Batch norm is left out on purpose: physgrad's networks
    are per-sample functions (HIG's per-sample Jacobians and SIP's per-sample targets need
    a sample's output to depend on that sample only). H and W must be divisible by
    2^(levels − 1).

    Without batch norm, deep ReLU U-Nets with PyTorch's initialisation can die in training
    (``navier_stokes``: docs/reproductions/sip.md). Two per-sample options stand in:
    ``activation=jax.nn.leaky_relu`` (slope 0.01) and ``weight_standardisation=True``: every
    3×3 kernel is standardised per output channel at each call
    (:func:`standardised_weight`, He's gain), all kernels are drawn He-normal and all biases
    start at 0 (the 1×1 output conv is not standardised). Same parameter count. The
    defaults are the plain network above.
    """

    down: tuple[_DoubleConv, ...]
    up: tuple[_DoubleConv, ...]
    out: eqx.nn.Conv2d
    levels: int = eqx.field(static=True)

    def __init__(self, c_in: int, c_out: int, *, levels: int = 4, filters: int = 16, key: PRNGKeyArray,
                 dtype=jnp.float32, activation: Callable[[Array], Array] | str = jax.nn.relu,
                 weight_standardisation: bool = False):  # fmt: skip
        activation = _activation_function(
            activation, _UNET_ACTIVATION_NAMES, f"UNet(..., activation={activation!r})", "jax.nn.leaky_relu"
        )
        keys = jax.random.split(key, 2 * levels)
        self.levels = levels
        kw = dict(dtype=dtype, activation=activation, standardise=weight_standardisation)
        self.down = tuple(_DoubleConv(c_in if i == 0 else filters, filters, key=keys[i], **kw) for i in range(levels))
        self.up = tuple(_DoubleConv(2 * filters, filters, key=keys[levels + i], **kw) for i in range(levels - 1))
        if weight_standardisation:
            self.out = _he_conv(filters, c_out, 1, key=keys[-1], dtype=dtype)
        else:
            self.out = eqx.nn.Conv2d(filters, c_out, 1, key=keys[-1], dtype=dtype)

    def features(self, x: Float[Array, "c h w"]) -> Float[Array, "filters h w"]:
        """The last feature map (after the last double conv, before the 1×1 output conv)."""
        factor = 2 ** (self.levels - 1)
        if x.shape[1] % factor or x.shape[2] % factor:
            raise ValueError(f"UNet with {self.levels} levels needs H and W divisible by {factor}, got {x.shape[1:]}")
        x = x.astype(self.out.weight.dtype)
        skips = []
        for i, block in enumerate(self.down):
            x = block(x if i == 0 else _max_pool_2x2(x))
            skips.append(x)
        for block, skip in zip(self.up, reversed(skips[:-1])):
            x = block(jnp.concatenate([_upsample_2x(x), skip], axis=0))
        return x

    def __call__(self, x: Float[Array, "c h w"]) -> Float[Array, "c2 h w"]:
        return self.out(self.features(x))


class ConvResNet(eqx.Module):
    """A convolutional ResNet on periodic grids (List et al.'s KS network, §1.4A):

        h = conv_in(x);  h ← σ(h + conv₂(σ(conv₁(h))))  (``blocks`` times);  y = conv_out(h)

    kernel 3 with circular padding, LeakyReLU σ (slope 0.01, PyTorch's), ``width`` channels;
    no activation after the lifting convolution ``conv_in`` (as the authors' KS network;
    ``lift_activation=True`` applies σ there, the network physgrad's Kolmogorov problem uses);
    PyTorch's default initialisation U(±1/√fan_in) (Equinox's too). In 1D with 2 input
    channels (width, blocks) = (16, 10) has 15,841 parameters, (26, 8) 33,125 and (52, 12)
    196,457: the paper's counts. Input (c_in, *N), output (c_out, *N).
    """

    conv_in: eqx.nn.Conv
    blocks: tuple[tuple[eqx.nn.Conv, eqx.nn.Conv], ...]
    conv_out: eqx.nn.Conv
    lift_activation: bool = eqx.field(static=True)

    def __init__(self, num_spatial_dims: int, in_channels: int, out_channels: int, width: int, blocks: int,
                 *, key: PRNGKeyArray, kernel_size: int = 3, lift_activation: bool = False):  # fmt: skip
        def conv(c_in, c_out, k):
            return eqx.nn.Conv(num_spatial_dims, c_in, c_out, kernel_size, padding="SAME",
                               padding_mode="CIRCULAR", dtype=jnp.float32, key=k)  # fmt: skip

        keys = jax.random.split(key, 2 * blocks + 2)
        self.conv_in = conv(in_channels, width, keys[0])
        self.blocks = tuple(
            (conv(width, width, keys[1 + 2 * i]), conv(width, width, keys[2 + 2 * i])) for i in range(blocks)
        )
        self.conv_out = conv(width, out_channels, keys[-1])
        self.lift_activation = lift_activation

    def __call__(self, x: Array) -> Array:
        act = jax.nn.leaky_relu
        h = self.conv_in(x)
        if self.lift_activation:
            h = act(h)
        for first, second in self.blocks:
            h = act(h + second(act(first(h))))
        return self.conv_out(h)
