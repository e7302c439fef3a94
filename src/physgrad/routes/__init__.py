"""How the κ-power of the joint Jacobian is computed: interchangeable route objects.

Gauss–Newton and half-inverse gradients need ``J^κ g = V Σ^κ Uᵀ g`` for the joint
per-sample Jacobian ``J = ∂y/∂θ`` (rows = batch × output size, columns = parameters) and
the output gradient ``g = ∂L/∂y``. A route decides how, like lineax's solvers decide how a
linear system is solved; each is handed the step's :class:`JointJacobian`, built once:

- :class:`SVD`: thin SVD of J in its own dtype (the paper's way);
- :class:`Gram`: eigendecomposition of the smaller Gram matrix in float64 (exact, far
  cheaper whenever J is clearly wide or tall); under a device mesh each device forms the
  Jacobian rows of its own samples and the Gram matrix is assembled by collectives;
- :class:`BlockGram`: the exact Gram matrix from sample groups' Jacobians, recomputed pair
  by pair, so only two groups' rows are ever held (J too large for memory);
- :class:`Lanczos`: a Krylov approximation from Jacobian–vector products (never forms J;
  accurate only for well-conditioned spectra);
- :class:`Structured`: the exact Gram matrix from each dense layer's back-propagated
  signals and inputs, explicit rows only for the other parameters: never holds J, and
  costs ``rows² · (Σ d_out + P_other)`` instead of ``rows² · P``;
- :class:`Auto`: :class:`Structured` when the network has dense layers and J is wide,
  else :class:`Gram` or :class:`SVD` by the shape of J (the default).

Every route also estimates the memory of its own large arrays (``footprint``), which the
training engine checks against the device before the first step.

Every route returns ``(direction, loss, stats)``: the flat direction (P,), the batch-mean
loss and statistics of the step, numbers the training engine averages into
``metrics.csv`` (``step_<name>``):

- ``route``: the route that ran, as its index in :data:`ROUTE_NAMES` (``Auto()`` decides
  at trace time from shapes; :meth:`AbstractRoute.resolve` names it without computing);
- ``rank``: the number of singular values kept, ``#{σ > τ σ_max}``;
- ``sigma_max`` and ``sigma_min_kept``: the largest and the smallest kept singular value of
  J (Lanczos: of its Ritz approximation, which resolves the top of the spectrum first);
- Lanczos also logs ``lanczos_change``.

Layout: ``base`` (the protocol, the value, the traced structure), ``spectrum`` (filters,
statistics, Gram power), one module per route, ``auto`` (the default, :func:`half_inverse`
of an explicit J, the routes by memory).
"""

from .auto import Auto, alternatives, by_shape, half_inverse
from .base import AbstractRoute, JointJacobian, find_structure
from .blockgram import BlockGram, blockgram_half_inverse
from .gram import Gram, sharded_gram_route
from .lanczos import Lanczos, lanczos_half_inverse
from .spectrum import Damped, Spectrum, spectrum_stats
from .structured import Structured
from .svd import SVD

ROUTE_NAMES = tuple(route.name() for route in sorted((SVD, Gram, Structured, BlockGram, Lanczos), key=lambda r: r.code))
"""The routes by the code a step's ``stats["route"]`` holds: ``ROUTE_NAMES[code]``."""

__all__ = ["ROUTE_NAMES", "SVD", "AbstractRoute", "Auto", "BlockGram", "Damped", "Gram", "JointJacobian", "Lanczos",
           "Spectrum", "Structured", "alternatives", "blockgram_half_inverse", "by_shape", "find_structure",
           "half_inverse", "lanczos_half_inverse", "sharded_gram_route", "spectrum_stats"]  # fmt: skip
