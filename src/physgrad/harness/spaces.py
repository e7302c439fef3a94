"""Each method's tuning search space, declared in one place beside the method registry.

A space maps hyperparameter names (the factories' keyword arguments in
:data:`physgrad.harness.registry.METHODS`) to dimensions. Every method gets its learning
rate, log-uniform over two decades either side of the value the run would take untuned
(the paper's for the problem, :func:`~physgrad.harness.registry.paper_defaults`, else the
factory's); the rules with a second scale get it too:

===========================  ==============================================================
method                       searched besides ``lr``
===========================  ==============================================================
``hig``, ``gn``              ``truncation`` τ (singular values σ ≤ τ σ_max dropped)
``lm``                       ``damping`` μ₀ (initial λ = μ σ_max², then Nielsen's rule)
``khig``, ``kgn``,           ``damping`` (added as damping·λ_max before the power)
``khig_half``, ``ekhig``
``kfac``, ``kfac_hig``       ``damping`` λ (initial value of K-FAC's adaptive damping); its
                             ``lr`` only with ``adaptive=false`` (the adaptive step sets its own)
``sip``                      ``eta`` η (the step towards y* in y) and the inner lr
``bptt``, ``sbptt_m``,       ``clip_threshold`` (the StableBPTT clip, value or norm)
``sbptt_c``, ``no_temporal``
===========================  ==============================================================

Every other registered method and every optax zoo name (``optax:lion``) gets ``lr`` alone.
The ranges follow the protocols the tuned comparison copies: AlgoPerf's external-tuning
rules (Dahl et al. 2023, "Benchmarking Neural Network Training Algorithms", §4: a declared
search space per submission, quasi-random points) and "Fantastic pretraining optimizers"
(Wen et al. 2025: learning rate searched on a log grid around each optimizer's default).
A user may pass their own mapping to :func:`physgrad.tune` (``spaces=``).
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from ..errors import ConfigError


class AbstractDimension(abc.ABC):
    """One searched hyperparameter: its range, resolved against the value the run would
    take untuned (``default``), as an Optuna distribution."""

    @abc.abstractmethod
    def bounds(self, default: Any) -> tuple[float, float]:
        """(low, high) of the search for a hyperparameter whose untuned value is ``default``."""

    def distribution(self, default: Any):
        """The Optuna distribution (log-uniform floats)."""
        import optuna

        low, high = self.bounds(default)
        return optuna.distributions.FloatDistribution(low, high, log=True)

    def describe(self, default: Any) -> str:
        low, high = self.bounds(default)
        return f"log-uniform [{low:.3g}, {high:.3g}]"


@dataclasses.dataclass(frozen=True)
class LogUniform(AbstractDimension):
    """Log-uniform on the fixed interval [``low``, ``high``] (both positive)."""

    low: float
    high: float

    def __post_init__(self):
        if not 0 < self.low < self.high:
            raise ConfigError(f"LogUniform needs 0 < low < high, got {self.low} and {self.high}")

    def bounds(self, default: Any) -> tuple[float, float]:
        return float(self.low), float(self.high)


@dataclasses.dataclass(frozen=True)
class AroundDefault(AbstractDimension):
    """Log-uniform over ``decades`` decades either side of the untuned value d:
    [d·10^-decades, d·10^decades] (d must be positive)."""

    decades: float = 2.0

    def bounds(self, default: Any) -> tuple[float, float]:
        d = float(default)
        if not (d > 0 and math.isfinite(d)):
            raise ConfigError(f"a search around the default needs a positive default, got {default!r}")
        return d * 10.0**-self.decades, d * 10.0**self.decades


Space = Mapping[str, AbstractDimension]

LEARNING_RATE = AroundDefault(2.0)  # every method: lr from 1/100 to 100 times its untuned value
TRUNCATION = LogUniform(1e-8, 1e-1)  # HIG's paper uses 1e-6 (oscillators) to 1e-3
CLIP = LogUniform(1e-2, 1e2)  # StableBPTT's clip thresholds 0.1-10 (per problem), widened

# The one table of declared spaces. A method not listed gets SPACES["*"] (the learning rate).
SPACES: dict[str, Space] = {
    "*": {"lr": LEARNING_RATE},
    "hig": {"lr": LEARNING_RATE, "truncation": TRUNCATION},
    "gn": {"lr": LEARNING_RATE, "truncation": TRUNCATION},
    "lm": {"lr": LEARNING_RATE, "damping": LogUniform(1e-6, 1.0)},
    **{m: {"lr": LEARNING_RATE, "damping": LogUniform(1e-8, 1e-1)} for m in ("khig", "kgn", "khig_half", "ekhig")},
    "kfac": {"lr": LEARNING_RATE, "damping": LogUniform(1e-6, 1.0)},
    "kfac_hig": {"lr": LEARNING_RATE, "damping": LogUniform(1e-6, 1.0)},
    "sip": {"lr": LEARNING_RATE, "eta": LogUniform(1e-2, 1.0)},
    **{m: {"lr": LEARNING_RATE, "clip_threshold": CLIP} for m in ("bptt", "sbptt_m", "sbptt_c", "no_temporal")},
}
# (method, hyperparameter) -> (setting, value): the dimension is searched only while the run's
# setting has that value. K-FAC's adaptive step (the default) sets its own rate: lr is unused.
ONLY_WHEN: dict[tuple[str, str], tuple[str, Any]] = {
    ("kfac", "lr"): ("adaptive", False),
    ("kfac_hig", "lr"): ("adaptive", False),
}


def space_of(method: str, spaces: Mapping[str, Space] | None = None) -> Space:
    """The declared search space of a registered method (or an optax zoo name): its entry
    in ``spaces`` (default :data:`SPACES`), else the learning rate alone. A sequence such as
    ``adam:2000,hig`` cannot be tuned as one method (tune its stages)."""
    if "," in method:
        raise ConfigError(f"tune takes single methods, not the sequence {method!r}: tune its stages one by one")
    table = SPACES if spaces is None else {**SPACES, **spaces}
    return table.get(method, table["*"])


def active_space(method: str, defaults: Mapping[str, Any], spaces: Mapping[str, Space] | None = None) -> Space:
    """:func:`space_of` less the dimensions that :data:`ONLY_WHEN` switches off for these
    untuned ``defaults`` (K-FAC's lr while its step is adaptive)."""
    out = {}
    for name, dimension in space_of(method, spaces).items():
        setting, value = ONLY_WHEN.get((method, name), (None, None))
        if setting is None or defaults.get(setting) == value:
            out[name] = dimension
    return out


def distributions(method: str, defaults: Mapping[str, Any], spaces: Mapping[str, Space] | None = None) -> dict:
    """``{name: optuna distribution}`` of a method, each range resolved against ``defaults``
    (the untuned hyperparameters of the run); a dimension naming no hyperparameter of the
    method is a one-line error listing the valid ones."""
    out = {}
    for name, dimension in active_space(method, defaults, spaces).items():
        if name not in defaults:
            raise ConfigError(f"search space of {method}: no hyperparameter {name!r}; valid choices: "
                              f"{', '.join(sorted(defaults))}")  # fmt: skip
        out[name] = dimension.distribution(defaults[name])
    return out


def describe_space(method: str, defaults: Mapping[str, Any], spaces: Mapping[str, Space] | None = None) -> dict:
    """``{name: "log-uniform [low, high]"}``: what ``tune.json`` records of a method's space."""
    return {name: dim.describe(defaults[name]) for name, dim in active_space(method, defaults, spaces).items()}


__all__ = [
    "ONLY_WHEN",
    "SPACES",
    "AbstractDimension",
    "AroundDefault",
    "LogUniform",
    "active_space",
    "describe_space",
    "distributions",
    "space_of",
]
