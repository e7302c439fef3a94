"""The optax zoo: any optax optimizer by name (``optax:lion``, ``optax.contrib:muon``) as a
physgrad method on DP gradients, its factory built from the optimizer's own signature
(the command line's names; :data:`physgrad.harness.registry.METHODS` looks them up here)."""

from __future__ import annotations

import inspect
from collections.abc import Callable

import optax
import optax.contrib

from ..methods import AbstractMethod, Gradient, LossAwareDP

# --- The optax zoo: any optax optimizer by name, on DP gradients ----------------------------
# "optax:lion", "optax.contrib:muon": the function's hyperparameters with plain defaults
# (numbers, flags, strings) become settings; learning_rate is `lr`. Names are looked up on
# demand, so a new optax release brings its optimizers without a change here.
OPTAX_MODULES = {"optax": optax, "optax.contrib": optax.contrib}
# Not optimizers of a parameter vector from its gradient: per-example-gradient privacy
# (dpsgd), bare scalings, and optax's deprecated aliases.
_OPTAX_EXCLUDED = ("dpsgd", "scale_by_rprop", "scale_by_madgrad")
# What an optimizer's update needs besides the gradient (physgrad.methods.LossAwareDP);
# every other optimizer gets the batch loss as value= (used by momo, ignored by most).
_OPTAX_EXTRAS = {"optax:lbfgs": ("value", "grad", "value_fn"), "optax.contrib:sophia": ("obj_fn",)}


def optax_names() -> list[str]:
    """Every ``module:function`` of :data:`OPTAX_MODULES` that builds an optimizer from a
    ``learning_rate`` (its first parameter)."""
    names = []
    for module_name, module in OPTAX_MODULES.items():
        for name in sorted(getattr(module, "__all__", None) or (n for n in vars(module) if not n.startswith("_"))):
            fn = vars(module).get(name)  # vars: no deprecation warnings from module __getattr__
            if name in _OPTAX_EXCLUDED or not inspect.isfunction(fn):
                continue
            first = next(iter(inspect.signature(fn).parameters), None)
            if first == "learning_rate":
                names.append(f"{module_name}:{name}")
    return names


def is_optax_name(name: str) -> bool:
    """Whether ``name`` is spelled as an optax zoo entry (``optax:…``, ``optax.contrib:…``)."""
    return any(name.startswith(f"{module}:") for module in OPTAX_MODULES)


def optax_method(name: str) -> Callable[..., AbstractMethod]:
    """The factory of an optax zoo entry: keyword-only ``lr`` plus the optimizer's own
    hyperparameters with number, flag or string defaults; a one-line error listing the
    valid names otherwise."""
    valid = optax_names()
    if name not in valid:
        raise ValueError(f"unknown optax optimizer {name!r}; valid choices: {', '.join(valid)}")
    module_name, _, function_name = name.partition(":")
    fn = vars(OPTAX_MODULES[module_name])[function_name]
    rate, *own = inspect.signature(fn).parameters.values()
    plain = [p for p in own if type(p.default) in (bool, int, float, str)]
    # Learning-rate-free and line-search methods (prodigy, dog, momo, lbfgs) default to 1.
    lr = rate.default if type(rate.default) is float else 1.0 if rate.default is None else 1e-3
    kw = inspect.Parameter.KEYWORD_ONLY
    signature = inspect.Signature([inspect.Parameter("lr", kw, default=lr)] +
                                  [inspect.Parameter(p.name, kw, default=p.default) for p in plain])  # fmt: skip

    def factory(**hyperparameters):
        values = signature.bind(**hyperparameters)
        values.apply_defaults()
        settings = dict(values.arguments)
        return LossAwareDP(Gradient(), fn(settings.pop("lr"), **settings), _OPTAX_EXTRAS.get(name, ("value",)))

    summary = (fn.__doc__ or "").strip().splitlines()
    factory.__signature__ = signature
    factory.lr_required = rate.default is inspect.Parameter.empty
    factory.__name__ = factory.__qualname__ = name
    factory.__doc__ = f"{name} on DP gradients: {summary[0].rstrip('.') if summary else function_name}."
    return factory


__all__ = ["OPTAX_MODULES", "is_optax_name", "optax_method", "optax_names"]
