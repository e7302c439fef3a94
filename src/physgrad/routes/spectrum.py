"""Spectral filters of the κ-power, what a truncation keeps, and the Gram-power algebra.

Source: Schnell, Holl, Thuerey, *Half-Inverse Gradients for Physical Deep Learning*,
ICLR 2022, eq. for Δθ_HIG; the authors' ``gpinv``; PBDL book, chapter "Half-inverse
gradients".

For a Jacobian ``J`` (m × P) with thin SVD ``J = U Σ Vᵀ`` and a gradient ``g`` (m,),

    J^κ g := V Σ^κ Uᵀ g,

keeping only singular values ``σ > truncation · σ_max`` (strict) and *dropping* the
others (not clamping them). κ = +1 gives ``Jᵀ g`` (gradient descent), κ = −1 the
Gauss–Newton / pseudo-inverse step, κ = −½ the half-inverse gradient. In place of the
number κ every route also takes a :class:`Damped` filter, ``σ ↦ σ / (σ² + λ)``, which
gives the Levenberg–Marquardt direction ``Jᵀ (J Jᵀ + λ I)⁻¹ g`` by the same routes.

The Gram routes never form the large SVD factor: for a Gram matrix ``U Σ² Uᵀ`` (``J Jᵀ``
or ``Jᵀ J``) :func:`gram_power` gives ``U Σ^{κ−1} Uᵀ v`` — one ``eigh``, σ = √λ.

Internal module: the public names are those :mod:`physgrad.routes` exports (its
``__all__``); import them from there.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

Spectrum = dict[str, Array]


class Damped(eqx.Module):
    """The Levenberg–Marquardt filter ``f(σ) = σ / (σ² + λ)`` in place of ``σ^κ``.

    ``V f(Σ) Uᵀ g = Jᵀ (J Jᵀ + λ I)⁻¹ g = (Jᵀ J + λ I)⁻¹ Jᵀ g`` (Levenberg 1944,
    Marquardt 1963). λ → 0 gives the Gauss–Newton filter σ⁻¹ on the kept singular values,
    λ → ∞ the scaled gradient ``Jᵀ g / λ``. With ``relative`` (the default) the damping is
    measured in units of the largest squared singular value, ``λ = damping · σ_max²``, so
    one value means the same on problems whose physics differ by orders of magnitude in
    scale. ``damping`` may be a traced scalar (an adaptive rule's state).
    """

    damping: ArrayLike
    relative: bool = eqx.field(static=True, default=True)


def kept_powers(s: Array, exponent: float | Damped, truncation: float, divided: bool = False) -> Array:
    """``f(s)`` (or ``f(s)/s`` with ``divided``) where ``s > truncation·max(s)``, else 0
    (dropped, not clamped); ``f(s) = s**exponent`` for a number, σ/(σ² + λ) for :class:`Damped`."""
    s_max = jnp.max(s)
    keep = s > truncation * s_max
    # Guard the power before the `where`: 0**negative would leak inf/NaN into gradients.
    safe = jnp.where(keep, s, jnp.ones_like(s))
    if isinstance(exponent, Damped):
        lam = exponent.damping * s_max**2 if exponent.relative else exponent.damping
        values = (1.0 if divided else safe) / (safe**2 + lam)
    else:
        values = safe ** (exponent - 1.0 if divided else exponent)
    return jnp.where(keep, values, jnp.zeros_like(s)).astype(s.dtype)


def spectrum_stats(s: Array, truncation: float) -> Spectrum:
    """What the truncation kept of the singular values ``s`` (any order, ≥ 0):

    - ``rank``: the number kept, ``#{σ > τ σ_max}`` (int32);
    - ``sigma_max``: σ_max;
    - ``sigma_min_kept``: the smallest kept σ (``inf`` when none is kept, ``s`` all 0).

    With κ = −½ the kept range sets the spread of the step's scaling, σ_max^{−½} to
    σ_min_kept^{−½}."""
    s_max = jnp.max(s)
    keep = s > truncation * s_max
    return {"rank": jnp.sum(keep).astype(jnp.int32), "sigma_max": s_max,
            "sigma_min_kept": jnp.min(jnp.where(keep, s, jnp.inf))}  # fmt: skip


def cast_spectrum(spectrum: Spectrum, dtype) -> Spectrum:
    """The σ's of :func:`spectrum_stats` in ``dtype`` (a float64 scope's way out)."""
    return {k: v if k == "rank" else v.astype(dtype) for k, v in spectrum.items()}


def gram_power(gram: Array, vector: Array, exponent: float | Damped, truncation: float) -> tuple[Array, Spectrum]:
    """``U Σ^{κ−1} Uᵀ v`` for a Gram matrix ``U Σ² Uᵀ`` (``J Jᵀ`` or ``Jᵀ J``), singular
    values ``σ ≤ τ σ_max`` dropped, and the :func:`spectrum_stats` of σ = √(eigenvalues).
    The one extra Σ⁻¹ turns the Gram eigenvectors into the missing SVD factor:
    ``J^κ g = Jᵀ·gram_power(J Jᵀ, g)`` = ``gram_power(Jᵀ J, Jᵀ g)``. With a :class:`Damped`
    filter: ``U (Σ² + λ)⁻¹ Uᵀ v``.

    Computes in the inputs' dtype; the Gram routes call it on float64 inside their scope."""
    eigenvalues, vectors = jnp.linalg.eigh(gram)
    s = jnp.sqrt(jnp.clip(eigenvalues, 0.0, None))
    powers = kept_powers(s, exponent, truncation, divided=True)
    return vectors @ (powers * (vectors.T @ vector)), spectrum_stats(s, truncation)
