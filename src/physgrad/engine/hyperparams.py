"""A method's optimizer hyperparameters as :func:`physgrad.fit` records them in
``config.json`` (:func:`optimizer_record`).

An optax transformation is a pair of closures: ``optax.adam(1e-3)`` keeps its learning rate
where no one can read it, so its ``repr`` (``chain.<locals>.init_fn``) is all a record could
say. ``optax.inject_hyperparams(optax.adam)(learning_rate=1e-3)`` keeps them in its state
(``state.hyperparams``), which is read here from the state of a stand-in parameter; a
schedule shows there as its value at step 0, and is recorded as a schedule with that value
(its form is not recorded). Where nothing can be read the record says so, and how to fix it.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax

UNKNOWN = "unknown: pass optax.inject_hyperparams(...) to record hyperparameters"
_INJECTED = tuple(  # optax's states of inject_hyperparams (the stateful one is in newer optax only)
    getattr(optax, name)
    for name in ("InjectHyperparamsState", "InjectStatefulHyperparamsState")
    if hasattr(optax, name)
)


def optimizer_record(method: Any) -> list[dict[str, Any]] | str:
    """The hyperparameters of ``method``'s optax transformation (``method.optimizer``): one
    dict per ``optax.inject_hyperparams`` state in it, in the order of its state tree (a
    chain's order), each ``{name: number}`` with schedules as ``"schedule (V at step 0;
    its form is not recorded)"``; else :data:`UNKNOWN` (no optimizer, none injected, or an
    optimizer whose state cannot be made for a stand-in scalar parameter)."""
    optimizer = getattr(method, "optimizer", None)
    if not isinstance(optimizer, optax.GradientTransformation):
        return UNKNOWN
    try:
        state = optimizer.init(jnp.zeros((), jnp.float32))
    except Exception:  # noqa: BLE001 — an optimizer that needs the real parameters' structure
        return UNKNOWN
    found = [_hyperparameters(s) for s in _injected(state)]
    return found or UNKNOWN


def _injected(state: Any) -> list[Any]:
    """Every inject_hyperparams state in ``state``, outer before inner."""
    found = []
    for node in jax.tree.leaves(state, is_leaf=lambda x: isinstance(x, _INJECTED)):
        if isinstance(node, _INJECTED):
            found.append(node)
            found.extend(_injected(node.inner_state))
    return found


def _hyperparameters(state: Any) -> dict[str, Any]:
    scheduled = set(getattr(state, "hyperparams_states", None) or ())
    out: dict[str, Any] = {}
    for name, value in sorted(state.hyperparams.items()):
        number = _number(value)
        out[name] = f"schedule ({number!r} at step 0; its form is not recorded)" if name in scheduled else number
    return out


def _number(value: Any) -> Any:
    """A scalar array as a Python number (a float32 one by its shortest decimal, so the
    ``1e-3`` passed reads 0.001, not 0.0010000000474974513); anything else as its repr."""
    try:
        array = np.asarray(value)
    except Exception:  # noqa: BLE001
        return repr(value)
    if array.shape != ():
        return array.tolist()
    if np.issubdtype(array.dtype, np.floating):
        return float(str(array[()]))
    return array.item()
