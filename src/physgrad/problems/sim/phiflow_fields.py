"""The PhiFlow adapter's grids: a :class:`Domain` and its boundary, and the kinds of arrays
that stand for PhiFlow fields (the ``inputs`` and ``outputs`` of
:func:`physgrad.problems.sim.phiflow.wrap`).

Each kind is an object that converts one per-sample JAX array to the PhiFlow value it
stands for and back; each boundary an object that gives PhiFlow's extrapolation. Layouts
are PhiFlow's own (checked in ``tests/test_phiflow.py``): axis 0 is x, axis 1 is y; with
``n`` the domain's resolution and ``d`` its number of axes,

- :class:`Centered`: a scalar ``CenteredGrid``, array ``(*n)``;
- :class:`Vector`: a centred vector ``CenteredGrid``, array ``(d, *n)``;
- :class:`Staggered`: a ``StaggeredGrid``, array ``(d, *n)``, component a on the *lower*
  a-faces of the cells (on a :class:`Periodic` domain only: other boundaries add a face
  per axis);
- :class:`Plain`: any JAX array, passed to the PhiFlow function as it is (a PhiML tensor
  result is turned back into its native array).

The strings of physgrad 0.1.0 (``"centered"``, ``"staggered"``, ``"vector"``, ``"array"``;
``boundary="periodic"``, ``"zero"``, ``"zero_gradient"``) still work for one release with a
``DeprecationWarning`` (:data:`KINDS`, :data:`BOUNDARIES`).

Internal module: the public names are those :mod:`physgrad.problems.sim.phiflow` exports.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp

from ...errors import warn_deprecated

AXES = "xyz"


# --- boundaries ---------------------------------------------------------------------------------
class AbstractBoundary(eqx.Module):
    """What a :class:`Domain`'s fields are beyond its edges (PhiFlow's extrapolation)."""

    staggered: ClassVar[bool] = False  # whether a staggered field fits the grid (one face per cell and axis)

    @abc.abstractmethod
    def extrapolation(self, flow) -> Any:
        """PhiFlow's extrapolation object (``flow`` is ``phi.jax.flow``)."""


class Periodic(AbstractBoundary):
    """The grid wraps around (the only boundary staggered fields take)."""

    staggered: ClassVar[bool] = True

    def extrapolation(self, flow):
        return flow.extrapolation.PERIODIC


class Zero(AbstractBoundary):
    """Zero beyond the edges (centred fields only)."""

    def extrapolation(self, flow):
        return flow.extrapolation.ZERO


class ZeroGradient(AbstractBoundary):
    """The edge values continued outwards (centred fields only)."""

    def extrapolation(self, flow):
        return flow.extrapolation.ZERO_GRADIENT


# the deprecated spellings (physgrad 0.1.0) -> the objects
BOUNDARIES: dict[str, AbstractBoundary] = {"periodic": Periodic(), "zero": Zero(), "zero_gradient": ZeroGradient()}


def _deprecated(what: str, spelling: str, instead: Any) -> None:
    warn_deprecated(f"{what}={spelling!r} is deprecated; pass physgrad.problems.sim.phiflow.{instead!r}")


class Domain(eqx.Module):
    """A uniform grid of ``resolution`` cells of size ``dx`` with origin 0, axes x, y(, z),
    and its ``boundary`` (:class:`Periodic`, the default, :class:`Zero` or :class:`ZeroGradient`)."""

    resolution: tuple[int, ...] = eqx.field(static=True)
    dx: float = eqx.field(static=True)
    boundary: AbstractBoundary = eqx.field(static=True, default=Periodic())

    def __post_init__(self):
        if isinstance(self.boundary, str):  # deprecated for one release
            if self.boundary not in BOUNDARIES:
                raise ValueError(
                    f"unknown boundary {self.boundary!r}; valid choices: Periodic(), Zero(), ZeroGradient()"
                )
            _deprecated("boundary", self.boundary, BOUNDARIES[self.boundary])
            self.boundary = BOUNDARIES[self.boundary]

    def __check_init__(self):
        if not 1 <= len(self.resolution) <= 3:
            raise ValueError(f"a Domain has 1 to 3 axes, got resolution {self.resolution}")
        if not isinstance(self.boundary, AbstractBoundary):
            raise ValueError(f"boundary must be Periodic(), Zero() or ZeroGradient(), got {self.boundary!r}")

    @property
    def axes(self) -> str:
        return AXES[: len(self.resolution)]

    def grid_kwargs(self, flow) -> dict:
        """PhiFlow's keywords for ``CenteredGrid(values, **kwargs)`` / ``StaggeredGrid``."""
        sizes = dict(zip(self.axes, self.resolution))
        bounds = flow.Box(**{a: n * self.dx for a, n in sizes.items()})
        return dict(extrapolation=self.boundary.extrapolation(flow), bounds=bounds, **sizes)


# --- array kinds --------------------------------------------------------------------------------
class AbstractKind(eqx.Module):
    """How one per-sample array stands for a PhiFlow value (``flow`` is ``phi.jax.flow``)."""

    @abc.abstractmethod
    def to_field(self, flow, array, domain: Domain) -> Any:
        """The PhiFlow value of ``array`` on ``domain``."""

    @abc.abstractmethod
    def from_field(self, flow, value, domain: Domain) -> Any:
        """The per-sample JAX array of a PhiFlow result ``value``."""


def _check_shape(array, shape, kind: AbstractKind) -> None:
    if tuple(array.shape) != tuple(shape):
        raise ValueError(f"a {kind!r} array on this domain has shape {tuple(shape)}, got {tuple(array.shape)}")


def _field(flow, value, kind: AbstractKind, staggered: bool):
    """``value`` checked to be a PhiFlow Field of the grid type ``kind`` reads."""
    if not isinstance(value, flow.Field):
        raise ValueError(f"expected a PhiFlow Field for output kind {kind!r}, got {type(value).__name__}")
    if value.is_staggered != staggered:
        grid, got = ("StaggeredGrid", "a centred field") if staggered else ("CenteredGrid", "a StaggeredGrid")
        raise ValueError(f"output kind {kind!r} needs a {grid}; got {got}")
    return value


class Plain(AbstractKind):
    """Any array, as it is (``"array"`` in physgrad 0.1.0)."""

    def to_field(self, flow, array, domain):
        return array

    def from_field(self, flow, value, domain):
        if isinstance(value, flow.math.Tensor):
            return value.native(value.shape.names)
        return jnp.asarray(value)


class Centered(AbstractKind):
    """A scalar ``CenteredGrid``, array ``(*n)``."""

    def to_field(self, flow, array, domain):
        _check_shape(array, domain.resolution, self)
        tensor = flow.math.tensor(array, flow.spatial(",".join(domain.axes)))
        return flow.CenteredGrid(tensor, **domain.grid_kwargs(flow))

    def from_field(self, flow, value, domain):
        return _field(flow, value, self, staggered=False).values.native(list(domain.axes))


def _vector_values(flow, array, domain: Domain, kind: AbstractKind):
    _check_shape(array, (len(domain.axes), *domain.resolution), kind)
    axes = ",".join(domain.axes)
    return flow.math.tensor(array, flow.channel(vector=axes), flow.spatial(axes))


class Vector(AbstractKind):
    """A centred vector ``CenteredGrid``, array ``(d, *n)``."""

    def to_field(self, flow, array, domain):
        return flow.CenteredGrid(_vector_values(flow, array, domain, self), **domain.grid_kwargs(flow))

    def from_field(self, flow, value, domain):
        return _field(flow, value, self, staggered=False).values.native(["vector", *domain.axes])


class Staggered(AbstractKind):
    """A ``StaggeredGrid``, array ``(d, *n)`` on the lower faces (periodic domains only)."""

    def to_field(self, flow, array, domain):
        values = _vector_values(flow, array, domain, self)
        if not domain.boundary.staggered:
            raise ValueError(
                "staggered arrays are supported on periodic domains only (other boundaries add a face per axis)"
            )
        return flow.StaggeredGrid(values, **domain.grid_kwargs(flow))

    def from_field(self, flow, value, domain):
        return _field(flow, value, self, staggered=True).values.native(["~vector", *domain.axes])


# the deprecated spellings (physgrad 0.1.0) -> the objects
KINDS: dict[str, AbstractKind] = {
    "centered": Centered(),
    "staggered": Staggered(),
    "vector": Vector(),
    "array": Plain(),
}


def kind_of(kind: AbstractKind | str) -> AbstractKind:
    """``kind`` itself, or the object of a deprecated string spelling (with its warning)."""
    if isinstance(kind, AbstractKind):
        return kind
    if isinstance(kind, str) and kind in KINDS:
        _deprecated("kind", kind, KINDS[kind])
        return KINDS[kind]
    raise ValueError(f"unknown array kind {kind!r}; valid choices: Centered(), Staggered(), Vector(), Plain()")
