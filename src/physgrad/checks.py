"""Ranges of settings and budgets: one small validator per kind of value.

Every setting is checked by type and range where it enters (the command line's ``--set``,
:func:`physgrad.harness.config.make_config`, :class:`physgrad.TrainSettings`, :class:`physgrad.Budget`,
:func:`physgrad.fit`), before any data are generated; a value out of range is one
:class:`~physgrad.ConfigError` line that names the valid range or choices::

    setting 'lr' must be a finite number > 0, got nan

A dataclass field declares its own range (:func:`declared`, read by :func:`check_fields`):
:class:`physgrad.TrainSettings`' fields do, and a :class:`physgrad.Budget` class holds its
amount's. :data:`SHARED` holds the ranges of the problems' and methods' settings that mean the
same wherever a problem or method declares them (sizes, learning rates, dtypes); a setting
not listed there is held to its default's kind: a finite number for a float, an integer >= 0
for an integer.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
from pathlib import Path
from typing import Any

from .errors import ConfigError, PathRefused


class Check:
    """A validator: ``check(name, value)`` returns the value or raises a one-line
    :class:`ConfigError`; ``text`` describes the valid values ("an integer >= 1")."""

    text = "a value"
    kinds: tuple[type, ...] = ()  # the defaults' types this check applies to (in SHARED)

    def valid(self, value: Any) -> bool:
        return True  # the base accepts anything (a setting whose owner checks it)

    def __call__(self, name: str, value: Any, what: str = "setting") -> Any:
        if not self.valid(value):
            raise ConfigError(f"{what} {name!r} must be {self.text}, got {value!r}")
        return value

    def applies_to(self, default: Any) -> bool:
        """Whether this check fits a setting with this default (None: any)."""
        return default is None or (isinstance(default, self.kinds) and not isinstance(default, bool))


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


@dataclasses.dataclass(frozen=True)
class Integer(Check):
    """An integer at least ``minimum``."""

    minimum: int = 0
    kinds = (int,)

    @property
    def text(self) -> str:  # pyright: ignore[reportIncompatibleVariableOverride]
        return "a positive integer" if self.minimum == 1 else f"an integer >= {self.minimum}"

    def valid(self, value):
        return _is_int(value) and value >= self.minimum


@dataclasses.dataclass(frozen=True)
class Number(Check):
    """A finite number within ``low``..``high`` (each open or closed; None: unbounded)."""

    low: float | None = None
    low_open: bool = False
    high: float | None = None
    high_open: bool = False
    kinds = (float, int)

    @property
    def text(self) -> str:  # pyright: ignore[reportIncompatibleVariableOverride]
        if self.low is not None and self.high is not None:
            return f"a number in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}{')' if self.high_open else ']'}"
        if self.low is not None:
            return f"a finite number {'>' if self.low_open else '>='} {self.low:g}"
        if self.high is not None:
            return f"a finite number {'<' if self.high_open else '<='} {self.high:g}"
        return "a finite number"

    def valid(self, value):
        if not _is_number(value) or not math.isfinite(value):
            return False
        low_ok = self.low is None or (value > self.low if self.low_open else value >= self.low)
        high_ok = self.high is None or (value < self.high if self.high_open else value <= self.high)
        return low_ok and high_ok


@dataclasses.dataclass(frozen=True)
class OneOf(Check):
    """One of ``choices``."""

    choices: tuple[str, ...] = ()
    kinds = (str,)

    @property
    def text(self) -> str:  # pyright: ignore[reportIncompatibleVariableOverride]
        return f"one of {', '.join(self.choices)}"

    def valid(self, value):
        return isinstance(value, str) and value in self.choices


class Flag(Check):
    """True or False."""

    text = "true or false"
    kinds = (bool,)

    def valid(self, value):
        return isinstance(value, bool)

    def applies_to(self, default):
        return default is None or isinstance(default, bool)


class Text(Check):
    """Any string (a problem or method checks its meaning)."""

    text = "a string"
    kinds = (str,)

    def valid(self, value):
        return isinstance(value, str)


POSITIVE_INT = Integer(1)
NON_NEGATIVE_INT = Integer(0)
POSITIVE = Number(0.0, low_open=True)
NON_NEGATIVE = Number(0.0)
FINITE = Number()
UNIT = Number(0.0, low_open=True, high=1.0)  # (0, 1]
FRACTION = Number(0.0, high=1.0, high_open=True)  # [0, 1)
FLAG = Flag()
TEXT = Text()

# Problem and method settings that mean the same wherever a problem or a method declares them
# (the engine's TrainSettings declare their ranges on their own fields: declared). A check applies
# where the setting's default is of its kind (``blocks`` is K-FAC's block type, a string,
# and HIG's number of sample groups, an integer).
# fmt: off
SHARED: dict[str, Check] = {
    **dict.fromkeys(("batch_size", "hidden", "width", "filters", "levels", "n_train", "n_test", "resolution",
                     "n_steps", "n_oscillators", "n_grid", "blocks", "lanczos_steps", "steps", "n", "n_ics", "frames",
                     "substeps", "poles", "drivers", "evaders", "nx", "max_steps", "inverse_every", "curvature_every",
                     "damping_interval", "eval_horizon", "long_horizon", "iterations", "refinement", "horizon"), POSITIVE_INT),
    **dict.fromkeys(("lr", "dt", "tol", "clip_threshold", "length", "size", "time", "amount", "pole_mass",
                     "total_mass", "half_length", "eta", "stage_epochs", "box", "swirl_sigma", "falloff", "rc",
                     "min_damping"), POSITIVE),
    **dict.fromkeys(("truncation", "eps", "damping", "momentum", "clip", "l2_reg", "rcond", "uncertainty",
                     "noise_scale", "noise_smoothness", "fluctuations", "lam", "initial_accumulator", "decay",
                     "gravity"), NON_NEGATIVE),
    **dict.fromkeys(("b1", "b2", "rho", "damping_decay", "curvature_ema"), FRACTION),
    "dataset_fraction": UNIT,
    "dtype": OneOf(("float32", "float64")),
}
# fmt: on


def check_for(name: str, default: Any) -> Check:
    """The check of a setting named ``name`` whose default is ``default``: its :data:`SHARED`
    range where that fits the default's kind, else the default's kind (a float: finite; an
    integer: >= 0; a flag; a string)."""
    shared = SHARED.get(name)
    if shared is not None and shared.applies_to(default):
        return shared
    if isinstance(default, bool):
        return FLAG
    if isinstance(default, int):
        return NON_NEGATIVE_INT
    if isinstance(default, float):
        return FINITE
    if isinstance(default, str):
        return TEXT
    return Check()  # anything else (a tuple such as toy2d's start) is the owner's to check


def check_setting(name: str, value: Any, default: Any, what: str = "setting", check: Check | None = None) -> Any:
    """``value`` if it is valid for the setting ``name`` (default ``default``), else a one-line
    :class:`ConfigError` naming the valid range. ``check`` is the setting's declared range
    (:func:`declared`); without one, :func:`check_for` finds it by name and default. An
    integer is accepted for a float setting (and returned as a float)."""
    check = check or check_for(name, default)
    value = check(name, value, what)
    if isinstance(default, float) and _is_int(value):
        return float(value)
    return value


_UNSET = object()


def declared(default: Any, check: Check, *, earlier: Any = _UNSET, guards: bool = False) -> Any:
    """A dataclass field that carries its range: ``name: int = declared(0, NON_NEGATIVE_INT)``.

    ``check`` is the field's :class:`Check` (read by :func:`check_fields` and by
    :func:`check_of`); ``earlier`` is the value that runs recorded before the setting existed
    had (a recorded run without it resumes while it holds that value); ``guards`` marks a
    setting that changes how a run is guarded, not what it computes (not part of a run's
    identity)."""
    metadata = {"check": check, "guards": guards}
    if earlier is not _UNSET:
        metadata["earlier"] = earlier
    return dataclasses.field(default=default, metadata=metadata)


def check_of(cls: Any, name: str) -> Check | None:
    """The :class:`Check` that field ``name`` of the dataclass ``cls`` declares (None: it
    declares none, or ``cls`` has no such field)."""
    field = next((f for f in dataclasses.fields(cls) if f.name == name), None)
    return None if field is None else field.metadata.get("check")


def check_fields(obj: Any, what: str) -> None:
    """Check every field of a dataclass ``obj`` by its ``metadata["check"]`` (or, without
    one, by its default's kind)."""
    for field in dataclasses.fields(obj):
        value = getattr(obj, field.name)
        if value is None and field.default is None:
            continue  # None: the documented default (e.g. the problem's own shuffle)
        check = field.metadata.get("check") or check_for(field.name, field.default)
        check(field.name, value, what)


def check_directory(path: str | Path, what: str = "out") -> Path:
    """``path`` if a directory can be used or created there; a one-line :class:`ConfigError`
    if it names a file, lies under a file or cannot be written."""
    if not str(path).strip():
        raise ConfigError(f"{what} is empty; give a directory")
    path = Path(path)
    long = [part for part in path.parts if len(os.fsencode(part)) > 255]
    if long:  # the file systems' NAME_MAX: refused before any work, not as ENAMETOOLONG after it
        raise ConfigError(f"{what} has a name of {len(os.fsencode(long[0]))} bytes, over the 255 a file system "
                          f"allows; choose a shorter {what}")  # fmt: skip
    if path.exists() and not path.is_dir():
        raise PathRefused(
            what, "{argument} {path!r} is a file, not a directory; choose another {argument}", path=str(path)
        )
    parent = path
    while not parent.exists():
        if parent.parent == parent:
            break
        parent = parent.parent
    if parent.exists() and not parent.is_dir():
        raise PathRefused(what, "{argument} {path!r} cannot be created: {parent!r} is a file; choose another {argument}",
                          path=str(path), parent=str(parent))  # fmt: skip
    if parent.exists() and not os.access(parent, os.W_OK | os.X_OK):
        raise PathRefused(what, "{argument} {path!r} cannot be written: {parent!r} is not writable; choose another "
                          "{argument}", path=str(path), parent=str(parent))  # fmt: skip
    return path
