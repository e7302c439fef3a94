"""PRDP: progressively refined differentiable physics (Bhatia, Koehler & Thuerey, ICLR 2025).

A solver inside the training loop that iterates (Jacobi sweeps, Krylov steps) costs in
proportion to its inner iteration count K, forward and backward. PRDP starts training with
a small K and raises it only when the validation error stops improving
(the rule of the paper's Algorithm 1, as in the authors' code):

- smooth the per-check validation error with an exponential moving average (window 6,
  α = 2/7);
- **plateau**: EMA_now / EMA_{3 checks ago} > τ_step (0.98);
- on a plateau, **refine** (K ← K + increment, up to the problem's full-fidelity K) if
  EMA_now / E_ref < τ_stop (0.9: at least 10 % better than at the last refinement;
  E_ref starts at 100) and remember E_ref = EMA_now; otherwise **stop** refining for good.

The savings are PR (few iterations early) plus IC (the final K stays below full fidelity).
The controller is a pure state machine over a JSON-able dict, so a resumed run continues
its schedule.

Internal module: the public names are those :mod:`physgrad.engine` and ``physgrad``
export (their ``__all__``); import them from there.
"""

from __future__ import annotations

from typing import Any


def initial_state(start: int) -> dict[str, Any]:
    return {"K": int(start), "ema": [], "reference": 100.0, "stopped": False, "refinements": []}


def update(state: dict[str, Any], error: float, step: int, *, increment: int, maximum: int,
           tau_step: float = 0.98, tau_stop: float = 0.9, window: int = 6) -> dict[str, Any]:  # fmt: skip
    """The controller after one validation check with ``error``; returns the new state."""
    state = {**state, "ema": list(state["ema"]), "refinements": list(state["refinements"])}
    alpha = 2.0 / (window + 1)
    ema = error if not state["ema"] else alpha * error + (1 - alpha) * state["ema"][-1]
    state["ema"].append(ema)
    if state["stopped"] or state["K"] >= maximum or len(state["ema"]) < 4:
        return state
    if ema / state["ema"][-4] > tau_step:  # plateau
        if ema / state["reference"] < tau_stop:
            state["K"] = min(state["K"] + increment, maximum)
            state["reference"] = ema
            state["refinements"].append([step, state["K"]])
            state["ema"] = state["ema"][-1:]  # a fresh plateau test at the new fidelity
        else:
            state["stopped"] = True
    return state
