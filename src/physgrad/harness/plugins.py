"""Problems and methods from outside physgrad: import paths and entry points.

The command line names a problem or a method by its name in
:mod:`physgrad.harness.registry`, by an import path ``package.module:Name`` (a module that
is installed, on ``PYTHONPATH`` or in the working directory), or by the name an installed
package declares in one of two entry-point groups (its ``pyproject.toml``)::

    [project.entry-points."physgrad.problems"]
    burgers_inverse = "mypkg.problems:BurgersInverse"

    [project.entry-points."physgrad.methods"]
    my_rule = "mypkg.methods:my_rule"

What a problem's import path or entry point names (:func:`problem_class`):

- a :class:`~physgrad.AbstractProblem` subclass, whose fields with defaults are its
  settings (``--set field=value``), as the built-in problems';
- an instance of one: its field values become the settings' defaults;
- a function of no arguments that returns an instance (likewise).

What a method's names (:func:`method_factory`): a factory whose parameters all have
defaults (a number, flag or string: its hyperparameters, ``--set name=value``) and which
returns a :class:`~physgrad.methods.AbstractMethod`, as the registry's own factories; its
docstring's first line describes it in ``physgrad list``. A method object itself is a
method without hyperparameters.

The entry points are read when a table is first listed or misses a name, never at import:
``physgrad --help`` stays fast and importing physgrad runs nobody's code. A plugin that
fails to load, or takes a name physgrad has already, is one :class:`PluginWarning` line
naming it and is left out; the built-in names are unaffected.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import os
import re
import sys
import warnings
from collections.abc import Callable, Iterator
from importlib.metadata import entry_points
from typing import Any, TypeVar

from ..errors import ConfigError

PROBLEM_GROUP = "physgrad.problems"
METHOD_GROUP = "physgrad.methods"

_IDENTIFIER = r"[A-Za-z_]\w*"
_DOTTED = rf"{_IDENTIFIER}(?:\.{_IDENTIFIER})*"
# ``package.module:Name`` (``Name`` may be dotted: ``module:Class.attribute``)
IMPORT_PATH = re.compile(rf"{_DOTTED}:{_DOTTED}")
# An entry point's name as the command line can spell it: no ':' (import paths, method
# stages) and no ',' (lists, sweeps).
PLUGIN_NAME = re.compile(r"[A-Za-z_][\w.\-]*")
_SETTING_TYPES = (bool, int, float, str)
V = TypeVar("V")


class PluginWarning(UserWarning):
    """A plugin (an entry point of :data:`PROBLEM_GROUP` or :data:`METHOD_GROUP`) that was
    left out; the message is one line naming it and why."""


def is_import_path(name: object) -> bool:
    """Whether ``name`` is spelled ``package.module:Name``."""
    return isinstance(name, str) and IMPORT_PATH.fullmatch(name) is not None


def _first_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return f"{type(error).__name__}: {text[0]}" if text else type(error).__name__


def _import(module_name: str):
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        missing_itself = e.name is not None and (module_name == e.name or module_name.startswith(e.name + "."))
        here = os.getcwd()
        # The ``physgrad`` script's sys.path starts at its own bin/, not the working directory
        # (``python -m`` adds it): a module beside the user is found as ``python -m`` finds it,
        # after the installed ones.
        if not missing_itself or here in sys.path:
            raise
        sys.path.append(here)
        importlib.invalidate_caches()
        return importlib.import_module(module_name)


def load(path: str, label: str) -> Any:
    """The object an import path ``module:Name`` names; a one-line :class:`ConfigError`
    (``label`` names what it was for) for a missing module, a module that fails to import
    or a missing attribute."""
    module_name, _, attribute = path.partition(":")
    try:
        module = _import(module_name)
    except ModuleNotFoundError as e:
        if e.name is not None and (module_name == e.name or module_name.startswith(e.name + ".")):
            raise ConfigError(f"{label}: no module named {e.name!r}; install its package, or run from the directory "
                              "that holds it, or add that directory to PYTHONPATH") from None  # fmt: skip
        raise ConfigError(f"{label}: importing {module_name} failed ({_first_line(e)})") from None
    except Exception as e:  # the user's module raised while importing: its line, not our traceback
        raise ConfigError(f"{label}: importing {module_name} failed ({_first_line(e)})") from None
    value: Any = module
    for part in attribute.split("."):
        try:
            value = getattr(value, part)
        except AttributeError:
            raise ConfigError(f"{label}: module {module_name!r} has no attribute {attribute!r}") from None
    return value


# --- problems ---------------------------------------------------------------------------------
def _subclass(cls: type, name: str, fields: dict[str, Any] | None = None) -> type:
    """``cls`` under the registry's ``name`` (its class attribute ``name``: the run records'
    and the paper protocols' key), with ``fields``' values as its fields' defaults."""
    namespace: dict[str, Any] = {"name": name, "__module__": cls.__module__, "__doc__": cls.__doc__,
                                 "__qualname__": cls.__qualname__, "__annotations__": {}}  # fmt: skip
    for field in dataclasses.fields(cls):
        if fields is None or field.name not in fields or not field.init:
            continue
        value = fields[field.name]
        namespace["__annotations__"][field.name] = field.type
        if value is None or type(value) in (*_SETTING_TYPES, tuple):  # a setting (--set): a plain default
            namespace[field.name] = dataclasses.field(default=value, metadata=field.metadata)
        else:  # an array, a function, a network: kept as the instance held it, not a --set setting
            namespace[field.name] = dataclasses.field(default_factory=lambda v=value: v, metadata=field.metadata)
    return type(cls.__name__, (cls,), namespace)


def problem_class(value: Any, name: str) -> type:
    """The registry's problem class for what an import path or entry point ``name`` names:
    an :class:`~physgrad.AbstractProblem` subclass, an instance (its field values as the
    defaults) or a function of no arguments returning one; a one-line :class:`ConfigError`
    otherwise."""
    from ..problems.base import AbstractProblem

    if isinstance(value, type) and issubclass(value, AbstractProblem):
        if inspect.isabstract(value):
            missing = ", ".join(sorted(getattr(value, "__abstractmethods__", ())))
            raise ConfigError(f"problem {name!r}: {value.__name__} is abstract (it does not define {missing})")
        # a class without a name of its own is known by the name the user gave
        return value if isinstance(getattr(value, "name", None), str) else _subclass(value, name)
    if not isinstance(value, AbstractProblem) and callable(value) and not isinstance(value, type):
        try:
            value = value()
        except Exception as e:
            raise ConfigError(f"problem {name!r}: calling it with no arguments failed ({_first_line(e)})") from None
        if not isinstance(value, AbstractProblem):
            raise ConfigError(f"problem {name!r}: the function returned a {type(value).__name__}, not a "
                              "physgrad.AbstractProblem")  # fmt: skip
    if isinstance(value, AbstractProblem):
        fields = {f.name: getattr(value, f.name) for f in dataclasses.fields(value) if f.init}
        return _subclass(type(value), getattr(value, "name", name), fields)
    raise ConfigError(f"problem {name!r} is a {type(value).__name__}, not a physgrad.AbstractProblem subclass, "
                      "an instance of one or a function returning one")  # fmt: skip


# --- methods ----------------------------------------------------------------------------------
def method_factory(value: Any, name: str) -> Callable[..., Any]:
    """The registry's factory for what an import path or entry point ``name`` names: a
    factory of keyword hyperparameters with number, flag or string defaults returning an
    :class:`~physgrad.methods.AbstractMethod`, or a method object (no hyperparameters); a
    one-line :class:`ConfigError` otherwise."""
    from ..methods import AbstractMethod

    if isinstance(value, AbstractMethod):
        method = value
        value = lambda: method  # noqa: E731
        value.__module__ = type(method).__module__
        value.__doc__ = f"{type(method).__name__} ({name}; a method object, no hyperparameters)"
    if not callable(value):
        raise ConfigError(f"method {name!r} is a {type(value).__name__}, not a physgrad.methods.AbstractMethod "
                          "or a function returning one")  # fmt: skip
    try:
        parameters = list(inspect.signature(value).parameters.values())
    except (TypeError, ValueError):
        raise ConfigError(f"method {name!r}: its signature cannot be read") from None
    for p in parameters:
        if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD) or p.default is p.empty:
            raise ConfigError(f"method {name!r}: parameter {p.name!r} needs a default (a method's parameters "
                              "are its hyperparameters, --set name=value)")  # fmt: skip
        if type(p.default) not in _SETTING_TYPES:
            raise ConfigError(f"method {name!r}: hyperparameter {p.name!r} defaults to a {type(p.default).__name__}; "
                              "give it a number, flag or string default")  # fmt: skip
    build = value

    def factory(**hyperparameters):
        method = build(**hyperparameters)
        if not isinstance(method, AbstractMethod):
            raise ConfigError(f"method {name!r} returned a {type(method).__name__}, not a "
                              "physgrad.methods.AbstractMethod (e.g. physgrad.methods.Method(rule, optax.sgd(lr)))")  # fmt: skip
        return method

    kw = inspect.Parameter.KEYWORD_ONLY
    factory.__signature__ = inspect.Signature([p.replace(kind=kw) for p in parameters])  # pyright: ignore[reportFunctionMemberAccess]
    factory.__doc__ = build.__doc__ or f"{name} (no description: the factory has no docstring)"
    factory.__name__ = factory.__qualname__ = name
    factory.__module__ = getattr(build, "__module__", None) or factory.__module__  # where it comes from, for listings
    return factory


# --- the tables -------------------------------------------------------------------------------
class Registry(dict[str, V]):
    """A command-line table: the built-in entries, an entry-point ``group``'s plugins (read
    on first listing or on a miss) and import paths (resolved on lookup, kept out of the
    listing). ``coerce(value, name)`` turns what a plugin or path names into an entry.

    Membership never raises: ``name in table`` is False for a path that does not resolve or
    a plugin that was left out, and :meth:`why_not` gives that name's one line."""

    def __init__(self, kind: str, builtins: dict[str, V], group: str, coerce: Callable[[Any, str], V]):
        super().__init__(builtins)
        self.kind, self.group, self.coerce = kind, group, coerce
        self.builtin = frozenset(builtins)
        self.left_out: dict[str, str] = {}  # plugin name -> the line saying why
        self._loaded = False
        self._paths: dict[str, V] = {}
        self._failed: dict[str, str] = {}  # import path -> its ConfigError's line

    def load_plugins(self) -> None:
        """Read the group's entry points, once; a failing one is a :class:`PluginWarning`."""
        if self._loaded:
            return
        self._loaded = True
        for point in entry_points(group=self.group):
            line = self._plugin(point)
            if line is not None:
                self.left_out.setdefault(point.name, line)
                warnings.warn(line, PluginWarning, stacklevel=3)

    def _plugin(self, point) -> str | None:
        dist = getattr(point, "dist", None)
        where = f"plugin {point.name!r} ({point.value}" + (f", from {dist.name}" if dist is not None else "") + ")"
        if not PLUGIN_NAME.fullmatch(point.name):
            return f"{where}: a plugin's name is letters, digits, '_', '.' and '-'; left out"
        if dict.__contains__(self, point.name):
            whose = "a built-in name" if point.name in self.builtin else "another plugin's name"
            return f"{where}: {point.name!r} is {whose}; left out"
        try:
            value = self.coerce(point.load(), point.name)
        except ConfigError as e:
            return f"{where}: {e}; left out"
        except Exception as e:  # the plugin's own import failed: its line, not a traceback
            return f"{where} failed to load ({_first_line(e)}); left out"
        dict.__setitem__(self, point.name, value)
        return None

    def reload_plugins(self) -> None:
        """Forget the plugins and import paths read so far (the next listing or miss reads
        the entry points again): for a session that installs a package after its first use."""
        for name in [n for n in dict.keys(self) if n not in self.builtin]:
            dict.__delitem__(self, name)
        self.left_out.clear()
        self._paths.clear()
        self._failed.clear()
        self._loaded = False

    def resolve(self, name: str) -> V:
        """The entry for ``name`` (a built-in or plugin name, or an import path); the one-line
        :class:`ConfigError` of a path that does not resolve or a plugin left out."""
        if dict.__contains__(self, name):
            return dict.__getitem__(self, name)
        self.load_plugins()
        if dict.__contains__(self, name):
            return dict.__getitem__(self, name)
        if name in self.left_out:
            raise ConfigError(self.left_out[name])
        if not is_import_path(name):
            raise KeyError(name)
        if name in self._failed:
            raise ConfigError(self._failed[name])
        if name not in self._paths:
            try:
                self._paths[name] = self.coerce(load(name, f"{self.kind} {name!r}"), name)
            except ConfigError as e:
                self._failed[name] = str(e)
                raise
        return self._paths[name]

    def why_not(self, name: str) -> str | None:
        """The one line of an import path that does not resolve or a plugin left out (None
        for a name that is simply unknown)."""
        try:
            self.resolve(name)
        except KeyError:
            return None
        except ConfigError as e:
            return str(e)
        return None

    def __missing__(self, name):
        return self.resolve(name)

    def __contains__(self, name) -> bool:
        if dict.__contains__(self, name):
            return True
        if not isinstance(name, str):
            return False
        try:
            self.resolve(name)
        except (KeyError, ConfigError):
            return False
        return True

    def get(self, name, default=None):  # pyright: ignore[reportIncompatibleMethodOverride]
        return self[name] if name in self else default

    # Listing reads the plugins first.
    def __iter__(self) -> Iterator[str]:
        self.load_plugins()
        return super().__iter__()

    def __len__(self) -> int:
        self.load_plugins()
        return super().__len__()

    def keys(self):
        self.load_plugins()
        return super().keys()

    def values(self):
        self.load_plugins()
        return super().values()

    def items(self):
        self.load_plugins()
        return super().items()


__all__ = ["IMPORT_PATH", "METHOD_GROUP", "PROBLEM_GROUP", "PluginWarning", "Registry", "is_import_path", "load",
           "method_factory", "problem_class"]  # fmt: skip
