"""Update rules, one file each, and the ``METHODS`` registry (name → factory).

A factory takes the method's hyperparameters as keyword-only arguments with defaults and
returns an ``AbstractMethod``; its docstring's first line describes it. The batch size is
a training setting (per-method defaults come from the problem).
"""

import inspect
from collections.abc import Callable
from typing import Any

from .base import AbstractMethod, Objective
from .dp import DifferentiablePhysics, adadelta, adagrad, adam, rmsprop, sgd
from .hig import JacobianPower, gn, hig
from .newton import Newton, newton
from .sip import ScaleInvariantPhysics, sip
from .stable_bptt import RolloutGradient, bptt, no_temporal, sbptt_c, sbptt_m
from .unrolling import Unrolled, nog, one, wig

METHODS: dict[str, Callable[..., AbstractMethod]] = {
    "adam": adam,
    "sgd": sgd,
    "rmsprop": rmsprop,
    "adagrad": adagrad,
    "adadelta": adadelta,
    "gn": gn,
    "hig": hig,
    "sip": sip,
    "newton": newton,
    "bptt": bptt,
    "sbptt_m": sbptt_m,
    "sbptt_c": sbptt_c,
    "no_temporal": no_temporal,
    "one": one,
    "nog": nog,
    "wig": wig,
}


def hyperparameters(method: str) -> dict[str, Any]:
    """A registered method's hyperparameters and their generic defaults."""
    params = inspect.signature(METHODS[method]).parameters
    return {name: p.default for name, p in params.items()}


def describe(method: str) -> str:
    """The one-line description of a registered method."""
    return (METHODS[method].__doc__ or "").strip().splitlines()[0]


__all__ = [
    "METHODS",
    "AbstractMethod",
    "DifferentiablePhysics",
    "JacobianPower",
    "Newton",
    "ScaleInvariantPhysics",
    "Objective",
    "RolloutGradient",
    "Unrolled",
    "describe",
    "hyperparameters",
]
