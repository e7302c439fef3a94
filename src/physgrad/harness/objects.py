"""The command line's words for the core's strategy objects, translated at the edge.

The library takes objects (a stepper composition, a lineax solver, an activation function);
the command line and ``config.json`` keep their strings. This module is the one place that
maps one to the other, so a run directory written before the objects existed keeps its
``config.json`` and its identity:

- the time-stepper problems' ``setup=prediction|correction`` and
  ``composition=full|residual|parallel|sequential|bypass`` (``""``: the setup's default) →
  :mod:`physgrad.problems.sim.steppers`' :class:`~physgrad.problems.sim.steppers.Prediction`,
  :class:`~physgrad.problems.sim.steppers.Residual`, :class:`~physgrad.problems.sim.steppers.Parallel`,
  :class:`~physgrad.problems.sim.steppers.Sequential`, :class:`~physgrad.problems.sim.steppers.Bypass`, with α the
  problem's ``network_scale``;
- problem settings that hold an activation function (the oscillators' and Navier–Stokes'
  ``activation``) → ``jax.nn.relu``, ``jax.nn.tanh``, ... (:data:`ACTIVATIONS`);
- problem settings that hold another strategy object, by its kind (:data:`STRATEGIES`):
  Navier–Stokes' ``projection=fft|cg``, ``limiter=faces|cells`` and
  ``simulator=jax|phiflow`` → :mod:`physgrad.problems.sim.fluid`'s
  :class:`~physgrad.problems.sim.fluid.FFTProjection`, :class:`~physgrad.problems.sim.fluid.CGProjection`,
  :class:`~physgrad.problems.sim.fluid.FaceLimiter`, :class:`~physgrad.problems.sim.fluid.CellLimiter`,
  :class:`~physgrad.problems.sim.fluid.JaxFluid`, :class:`~physgrad.problems.sim.phiflow.PhiFlowFluid`;
- ``--devices N|all`` → ``devices=N`` or ``devices=None`` (every device), as
  :func:`physgrad.fit` takes it (:func:`devices`);
- SIP's ``krylov=cg|cg_negative|gmres|bicgstab|normal_cg`` → a lineax solver object and the
  operator tags it assumes (:class:`~physgrad.inverse.LinearSolve`).
"""

from __future__ import annotations

from typing import Any

import jax
import lineax as lx

from ..errors import ConfigError
from ..nets import identity
from ..problems.base import AbstractProblem
from ..problems.sim import fluid
from ..problems.sim.phiflow import PhiFlowFluid
from ..problems.sim.steppers import AbstractComposition, Bypass, Parallel, Prediction, Residual, Sequential

# setup -> composition name -> (problem's network scale α) -> composition object
COMPOSITIONS = {
    "prediction": {"full": lambda scale: Prediction(), "residual": lambda scale: Residual()},
    "correction": {"parallel": Parallel, "sequential": lambda scale: Sequential(), "bypass": Bypass},
}


# activation name -> function (physgrad.MLP's activation)
ACTIVATIONS = {
    "relu": jax.nn.relu,
    "tanh": jax.nn.tanh,
    "sigmoid": jax.nn.sigmoid,
    "gelu": jax.nn.gelu,
    "identity": identity,
    "leaky_relu": jax.nn.leaky_relu,
}
_ACTIVATION_NAMES = {id(f): name for name, f in ACTIVATIONS.items()}


def activation(name: str):
    """The activation function of a command-line name."""
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown activation {name!r}; valid choices: {', '.join(ACTIVATIONS)}")
    return ACTIVATIONS[name]


# the kind of a problem setting's object -> its command-line name -> the object
STRATEGIES: dict[type, dict[str, Any]] = {
    fluid.AbstractPressureSolver: {"fft": fluid.FFTProjection(), "cg": fluid.CGProjection()},
    fluid.AbstractLimiter: {"faces": fluid.FaceLimiter(), "cells": fluid.CellLimiter()},
    fluid.AbstractFluid: {"jax": fluid.JaxFluid(), "phiflow": PhiFlowFluid()},
}


def _strategy_names(value: Any) -> dict[str, Any] | None:
    """The names of the objects of ``value``'s kind (:data:`STRATEGIES`), or None."""
    return next((names for kind, names in STRATEGIES.items() if isinstance(value, kind)), None)


def _setting_name(value: Any) -> Any:
    """A problem setting's value as the command line spells it: an activation's or a strategy
    object's name; any other value (or an object the command line has no name for) as it is."""
    names = _strategy_names(value)
    if names is not None:
        return next((name for name, known in names.items() if type(known) is type(value) and known == value), value)
    return _ACTIVATION_NAMES.get(id(value), value) if callable(value) else value


def _setting_value(setting: str, default: Any, value: Any) -> Any:
    """The object of a command-line name ``value`` for a setting whose ``default`` is an
    activation or a strategy object; any other value as it is."""
    if not isinstance(value, str):
        return value
    if callable(default) and id(default) in _ACTIVATION_NAMES:
        return activation(value)
    names = _strategy_names(default)
    if names is None:
        return value
    if value not in names:
        raise ValueError(f"unknown {setting} {value!r}; valid choices: {', '.join(names)}")
    return names[value]


def devices(value: int | str | None) -> int | None:
    """``fit``'s ``devices=`` from the command line's ``--devices``: a number, or ``"all"``
    (also ``"auto"``) for every device (None). Anything else passes through to the library,
    which names what it takes."""
    if isinstance(value, str):
        text = value.strip()
        if text in ("all", "auto"):
            return None
        if text.isdigit():
            return int(text)
        raise ConfigError(f"devices must be a number or 'all', got {value!r}")
    return value


# krylov name -> (lineax solver, operator tags); LinearSolve sets the tolerances and the limit.
KRYLOV = {
    "cg": (lx.CG(rtol=0.0, atol=0.0, max_steps=1000), (lx.symmetric_tag, lx.positive_semidefinite_tag)),
    "cg_negative": (lx.CG(rtol=0.0, atol=0.0, max_steps=1000), (lx.symmetric_tag, lx.negative_semidefinite_tag)),
    "gmres": (lx.GMRES(rtol=0.0, atol=0.0, max_steps=1000), ()),
    "bicgstab": (lx.BiCGStab(rtol=0.0, atol=0.0, max_steps=1000), ()),
    "normal_cg": (lx.Normal(lx.CG(rtol=0.0, atol=0.0, max_steps=1000)), ()),
}


def krylov(name: str) -> dict[str, Any]:
    """``LinearSolve``'s ``solver`` and ``tags`` for a command-line Krylov name."""
    if name not in KRYLOV:
        raise ValueError(f"unknown krylov {name!r}; valid choices: {', '.join(KRYLOV)}")
    solver, tags = KRYLOV[name]
    return {"solver": solver, "tags": tags}


def _composition_default(cls: type[AbstractProblem]) -> AbstractComposition | None:
    default = cls.settings().get("composition")
    return default if isinstance(default, AbstractComposition) else None


def problem_defaults(cls: type[AbstractProblem]) -> dict[str, Any]:
    """``cls``'s settings and their defaults as the command line spells them (the strings
    ``config.json`` records): a time-stepper's ``composition`` object becomes ``setup`` (its
    setup) and ``composition=""`` (the problem's default composition of that setup)."""
    settings = {k: _setting_name(v) for k, v in cls.settings().items()}
    default = _composition_default(cls)
    if default is None:
        return settings
    out: dict[str, Any] = {"setup": "correction" if default.uses_solver else "prediction", "composition": ""}
    out.update({k: v for k, v in settings.items() if k != "composition"})
    return out


def composition(cls: type[AbstractProblem], setup: str, name: str) -> AbstractComposition:
    """The composition object of a setup and composition name on problem ``cls`` (module
    docstring); a one-line ``ValueError`` listing the valid choices otherwise."""
    if setup not in COMPOSITIONS:
        raise ValueError(f"unknown setup {setup!r}; valid choices: {', '.join(COMPOSITIONS)}")
    default = _composition_default(cls)
    if not name:
        if default is not None and default.uses_solver == (setup == "correction"):
            return default
        name = "full" if setup == "prediction" else "parallel"
    if name not in COMPOSITIONS[setup]:
        raise ValueError(
            f"unknown composition {name!r} for the {setup} setup; valid choices: {', '.join(COMPOSITIONS[setup])}"
        )
    return COMPOSITIONS[setup][name](getattr(cls, "network_scale", 1.0))


def problem_arguments(cls: type[AbstractProblem], settings: dict[str, Any]) -> dict[str, Any]:
    """The constructor's arguments of ``cls`` from settings spelt as the command line spells
    them (:func:`problem_defaults`)."""
    defaults = cls.settings()
    out = {k: _setting_value(k, defaults[k], v) if k in defaults else v for k, v in settings.items()}
    if _composition_default(cls) is None:
        return out
    out = {k: v for k, v in out.items() if k not in ("setup", "composition")}
    defaults = problem_defaults(cls)
    out["composition"] = composition(
        cls, settings.get("setup", defaults["setup"]), settings.get("composition", defaults["composition"])
    )
    return out


def make_problem(cls: type[AbstractProblem], settings: dict[str, Any] | None = None) -> AbstractProblem:
    """``cls`` built from command-line settings (:func:`problem_arguments`)."""
    return cls(**problem_arguments(cls, settings or {}))
