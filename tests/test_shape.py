"""The library's classes keep optimistix's shape: an abstract base implements a concrete
method once, and at most one subclass overrides it.

An abstract base (a class with abstract methods or ``AbstractVar`` fields, or named
``Abstract…``) declares what its final classes must fill; a concrete method on it is shared
code. Where several subclasses override the same concrete method the base's version is a
default in disguise, and the variation belongs in an abstract method (each final class
implements it) or in a field (an object doing the varying part). Counted over every class
defined in ``src/physgrad``: for each abstract base and each concrete method (function,
property, class or static method; ``__call__`` included, the other dunders left out:
Equinox writes ``__init__`` and runs every ``__check_init__`` of the hierarchy), the
subclasses whose own body defines it over the base's (an intermediate abstract base that
re-declares the method abstract counts once, and its final classes implement its version).
"""

from __future__ import annotations

import abc
import importlib
import inspect
import pkgutil

import physgrad


def _classes() -> dict[str, type]:
    """Every class defined in a module of ``physgrad`` (``__main__`` left out: it runs the CLI)."""
    found = {}
    for info in pkgutil.walk_packages(physgrad.__path__, "physgrad."):
        if info.name.endswith("__main__"):
            continue
        module = importlib.import_module(info.name)
        for value in vars(module).values():
            if inspect.isclass(value) and value.__module__ == module.__name__:
                found[f"{value.__module__}.{value.__qualname__}"] = value
    return found


def _is_abstract(cls: type) -> bool:
    return (
        inspect.isabstract(cls)
        or cls.__name__.startswith("Abstract")
        or bool(getattr(cls, "__abstractvars__", None))
        or bool(getattr(cls, "__abstractclassvars__", None))
    )


def _concrete_methods(cls: type) -> list[str]:
    names = []
    for name, value in vars(cls).items():
        if name.startswith("__") and name != "__call__":
            continue
        if isinstance(value, staticmethod | classmethod):
            value = value.__func__
        function = value.fget if isinstance(value, property) else value
        if inspect.isfunction(function) and not getattr(function, "__isabstractmethod__", False):
            names.append(name)
    return names


def _overrides(cls: type, base: type, method: str) -> bool:
    """Whether ``cls`` defines ``method`` over ``base``'s own: the next definition up its
    MRO is ``base``'s (an intermediate base that re-declares it abstract takes the
    overrides below it)."""
    if cls is base or not issubclass(cls, base) or method not in vars(cls):
        return False
    return next(c for c in cls.__mro__[1:] if method in vars(c)) is base


def overridden_defaults(classes: dict[str, type]) -> list[str]:
    """``base.method: overridden by A, B, …`` for each concrete method of an abstract base
    that more than one subclass overrides."""
    offenders = []
    for name, base in sorted(classes.items()):
        if not _is_abstract(base):
            continue
        for method in _concrete_methods(base):
            subclasses = sorted(other.__qualname__ for other in classes.values() if _overrides(other, base, method))
            if len(subclasses) > 1:
                offenders.append(f"{name}.{method}: overridden by {', '.join(subclasses)}")
    return offenders


def test_the_walk_sees_the_library():
    classes = _classes()
    assert "physgrad.methods.method.AbstractOptaxMethod" in classes
    assert "physgrad.problems.oscillators.AbstractOscillators" in classes


def test_the_count_finds_a_default_overridden_twice():
    class AbstractBase:
        def shared(self): ...

    class A(AbstractBase):
        def shared(self): ...

    class B(AbstractBase):
        def shared(self): ...

    class AbstractMiddle(AbstractBase):
        @abc.abstractmethod
        def shared(self): ...

    class C(AbstractMiddle):
        def shared(self): ...

    class D(AbstractMiddle):
        def shared(self): ...

    assert overridden_defaults({"AbstractBase": AbstractBase, "A": A, "B": B}) == [
        "AbstractBase.shared: overridden by " + ", ".join(sorted([A.__qualname__, B.__qualname__]))
    ]
    assert overridden_defaults({"AbstractBase": AbstractBase, "AbstractMiddle": AbstractMiddle, "C": C, "D": D}) == []


# Defaults still overridden more than once, each with what keeps it. The list may only
# shrink: a new offender fails, and so does an entry that no longer offends (delete it).
# (Empty since AbstractProblem's optional pieces became None-or-a-method, as target and
# inverse were: metrics, rollout_pieces; its zero_init a declared flag.)
KNOWN: set[str] = set()


def test_no_concrete_method_of_an_abstract_base_is_overridden_by_more_than_one_subclass():
    offenders = overridden_defaults(_classes())
    new = [o for o in offenders if o.split(":")[0] not in KNOWN]
    assert not new, "concrete methods of abstract bases overridden more than once:\n" + "\n".join(new)
    gone = KNOWN - {o.split(":")[0] for o in offenders}
    assert not gone, f"no longer overridden more than once (delete from KNOWN): {sorted(gone)}"


def test_declared_flags_stand_for_the_hooks_they_replaced():
    """``needs_float64`` and ``batch_group_key`` are declared (a class variable, or a property
    where a setting decides), so no problem overrides a hook for them."""
    import numpy as np

    from physgrad.problems import HigToy, KuramotoSivashinsky, Toy2d

    train = {"index": np.array([0, 1, 1])}
    assert list(KuramotoSivashinsky().batch_groups(train)) == [0, 1, 1]  # type: ignore[arg-type]
    assert HigToy().batch_groups(train) is None
    assert Toy2d().needs_float64
    assert HigToy(dtype="float64").needs_float64 and not HigToy().needs_float64


# Packages whose implementation modules say they are internal (docs/architecture.md, "Private
# modules"), and the modules not yet marked, with why. The list of exceptions may only shrink.
INTERNAL_PACKAGES = ("engine", "routes", "inverse", "rollout")
UNMARKED = {
    "physgrad.engine.progress",  # the fit progress display is being reworked
    "physgrad.engine.tensorboard",  # TensorBoard is public at its module path (an optional extra)
}


def test_implementation_modules_say_they_are_internal():
    unmarked = set()
    for package in INTERNAL_PACKAGES:
        module = importlib.import_module(f"physgrad.{package}")
        assert module.__all__, package
        for info in pkgutil.iter_modules(module.__path__):
            name = f"physgrad.{package}.{info.name}"
            doc = importlib.import_module(name).__doc__ or ""
            if f"Internal module: the public names are those :mod:`physgrad.{package}`" not in doc:
                unmarked.add(name)
    assert unmarked == UNMARKED
