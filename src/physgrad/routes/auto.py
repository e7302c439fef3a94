"""The default route, the κ-power of an explicit matrix, and the routes by memory.

:class:`Auto` decides at trace time from the shape facts of the step's
:class:`~.base.JointJacobian` (no computation, no extra trace of ``predict``):

- :class:`~.structured.Structured` when J is wide (rows ≤ P/2) and the network has dense
  layers (the Gram matrix from each layer's factors, never holding J);
- else :class:`~.gram.Gram` when one side of J is at least twice the other: a matrix
  product and a small symmetric eigensolve are far cheaper than a bidiagonalisation
  (every physgrad problem: rows = batch × output size ≪ parameters);
- else :class:`~.svd.SVD`: for nearly square matrices the SVD avoids squaring the
  condition number at no extra cost. Measured in ``benchmarks/hig_step.py``.

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

from jaxtyping import Array, Float

from .base import AbstractRoute, JointJacobian
from .blockgram import BlockGram
from .gram import Gram
from .lanczos import Lanczos
from .spectrum import Damped
from .structured import Structured
from .svd import SVD


def by_shape(shape: tuple[int, int]) -> SVD | Gram:
    """The cheaper exact route for an explicit J of this shape (rows, P): :class:`Gram`
    when one side is at least twice the other, else :class:`SVD`."""
    m, p = shape
    return Gram() if max(m, p) >= 2 * min(m, p) else SVD()


class Auto(AbstractRoute):
    """:class:`Structured` when J is wide (rows ≤ P/2) and the network has dense layers;
    otherwise :class:`Gram` when one side of J is at least twice the other, else
    :class:`SVD`; decided on the shape of the whole J (as on one device)."""

    def resolve(self, jacobian: JointJacobian) -> AbstractRoute:
        exact, structured = by_shape(jacobian.shape), Structured()
        # Structured says itself which shapes it takes (a wide J); Auto adds the dense layers.
        if isinstance(exact, Gram) and jacobian.structure.dense and structured.instead(jacobian) is None:
            return structured
        return exact

    def choose(self, objective, params, batch) -> AbstractRoute:
        """The route Auto takes for these shapes (nothing is computed)."""
        return self.resolve(JointJacobian.of(objective, params, batch))

    def compute(self, jacobian, exponent, truncation):
        return self.resolve(jacobian).compute(jacobian, exponent, truncation)

    def footprint_of(self, jacobian, devices=1):
        return self.resolve(jacobian).footprint_of(jacobian, devices)


def half_inverse(
    jacobian: Float[Array, "m p"],
    grad: Float[Array, " m"],
    *,
    exponent: float | Damped = -0.5,
    truncation: float = 1e-6,
    route: SVD | Gram | None = None,
) -> Float[Array, " p"]:
    """Return ``V · diag(σ^exponent) · Uᵀ · grad`` over the retained singular values.

    Arguments:
        jacobian: ``J``, shape (m, P); for HIG the per-sample Jacobians of the simulator
            output stacked sample-major (m = batch × output size).
        grad: ``g``, shape (m,); the gradient of the batch-mean loss w.r.t. the outputs.
        exponent: κ; −0.5 half-inverse (HIG), −1 Gauss–Newton, +1 gives ``Jᵀ g``; or a
            :class:`~.spectrum.Damped` filter (Levenberg–Marquardt).
        truncation: τ; singular values ``σ ≤ τ·σ_max`` are dropped.
        route: :class:`SVD` (differentiable), :class:`Gram` (float64 Gram + ``eigh``,
            scoped; not differentiable) or ``None``: :func:`by_shape`.

    Returns:
        The update direction, shape (P,), in the dtype of ``jacobian``. The caller takes
        the step ``θ ← θ − η · half_inverse(J, g)``.
    """
    if jacobian.ndim != 2 or grad.shape != jacobian.shape[:1]:
        raise ValueError(f"half_inverse needs jacobian (m, P) and grad (m,); got {jacobian.shape} and {grad.shape}")
    if route is None:
        rows, size = jacobian.shape
        route = by_shape((rows, size))
    if not isinstance(route, (SVD, Gram)):
        raise ValueError(f"half_inverse takes an explicit J: route SVD(), Gram() or None (by shape); got {route!r}")
    return route.power(jacobian, grad, exponent, truncation)[0]


def alternatives(route: AbstractRoute, batch_size: int) -> list[AbstractRoute]:
    """The routes other than ``route`` that may need less memory at ``batch_size``, the
    most faithful first: the exact ones by speed (structured, gram, svd), then blockgram
    with ever more sample groups, then lanczos (approximate)."""
    groups = [BlockGram(k) for k in range(2, batch_size + 1) if batch_size % k == 0]
    variants = [Structured(), Gram(), SVD(), *groups, Lanczos()]
    return [r for r in variants if r != route]
