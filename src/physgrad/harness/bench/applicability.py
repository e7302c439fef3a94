"""Which candidate method runs on which problem in a bench, decided from shapes alone.

A candidate method is applicable to a problem when the run's configuration resolves and
the method's own ``check`` accepts the problem's :class:`~physgrad.methods.Objective` (and
its batch size fits the training set): the Jacobian methods need ``predict``/``loss`` and
a differentiable simulator, SIP the network/simulate split and a target, the BPTT variants
a rollout (closed-loop problems), ONE/NOG/WIG an unrolled time-stepper. It is decided from
shapes alone (``equinox.filter_eval_shape``), without generating data or training. On top
of that :data:`POLICY` skips a few pairings that make no sense as a bench entry
(``newton``'s dense Hessian on networks of more than :data:`NEWTON_MAX_PARAMS`
parameters); they are listed with the reason.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Sequence
from typing import Any

from ...engine.types import Steps
from ...extras import MissingExtra
from ..config import make_config, phase_methods
from ..failures import one_line
from ..words import command_line_words
from .choices import check_settings, problem_settings

# newton builds the dense Hessian of the batch loss: dim θ² memory and dim θ Hessian-vector
# products per step. Meant for direct optimisation of a few variables (methods/newton.py);
# on a network of tens of thousands of weights one step takes minutes and the memory guard
# cannot tell (Newton declares no footprint), so a bench would spend its budget compiling.
NEWTON_MAX_PARAMS = 5000


@dataclasses.dataclass(frozen=True)
class Verdict:
    """Whether a method runs on a problem in the bench: ``status`` is ``"applicable"``,
    ``"not applicable"`` (the method's check refused the problem), ``"skipped"`` (by
    :data:`POLICY`) or ``"error"`` (the check itself failed: recorded as a failure)."""

    method: str
    status: str
    reason: str = ""

    @property
    def runs(self) -> bool:
        return self.status == "applicable"


def _newton_policy(method: str, n_params: int) -> str:
    if "newton" in phase_methods(method) and n_params > NEWTON_MAX_PARAMS:
        return (f"newton's dense Hessian of {n_params} network parameters (> {NEWTON_MAX_PARAMS}): "
                "minutes per step; newton is for direct optimisation (--set no_network=true)")  # fmt: skip
    return ""


# Bench-only exclusions: (method spec, trainable parameter count) -> reason, or "" to keep.
POLICY: tuple[Callable[[str, int], str], ...] = (_newton_policy,)


def applicability(problem: str, methods: Sequence[str], settings: dict[str, Any] | None = None) -> list[Verdict]:
    """Decide for each method spec whether it runs on ``problem`` under the bench's
    ``settings`` (see the module docstring), without generating data or training.

    Raises :class:`ConfigError` for a bad setting value (the user's input, not the
    method's fault)."""
    from ...engine import abstract_setup
    from ...precision import float64_scope
    from ..train import phases_of, problem_of

    settings = settings or {}
    objectives: dict[str, tuple] = {}  # the objective depends on the problem's settings only
    verdicts = []
    for method in methods:
        try:
            config = make_config(problem, method, budget=Steps(1), settings=problem_settings(problem, method, settings))
        except MissingExtra as e:  # an optional extra is not installed: listed with the pip line
            verdicts.append(Verdict(method, "skipped", one_line(e)))
            continue
        phases = phases_of(config)
        problem_obj = problem_of(config)
        cache_key = json.dumps([config.problem_settings, config.no_network], sort_keys=True, default=str)
        try:
            with float64_scope(problem_obj.needs_float64):
                if cache_key not in objectives:
                    shapes = abstract_setup(problem_obj)  # the engine's, as its memory preflight sees it
                    objectives[cache_key] = (
                        shapes.n_train,
                        shapes.parameter_count,
                        problem_obj.objective(shapes.static),
                        shapes,
                    )
                n_train, size, objective, shapes = objectives[cache_key]
                for phase in phases:
                    batch_size = phase.batch_size
                    assert batch_size is not None  # the config's, resolved
                    phase.method.check(objective)
                    phase.method.check_batch_size(batch_size)
                    if n_train is not None and batch_size > n_train:
                        raise ValueError(f"batch_size {batch_size} exceeds the {n_train} training samples")
                    _refused_by_footprint(phase.method, objective, shapes, batch_size)
        # the contract of check(): one line saying what to use instead; ConfigError (a ValueError)
        # e.g. for SIP's solver resolution on a problem without an inverse
        except ValueError as e:  # a rule's typed refusal in the command line's words (nog, no_temporal, ...)
            verdicts.append(Verdict(method, "not applicable", " ".join(command_line_words(e).split())))
            continue
        except Exception as e:  # noqa: BLE001 — a check that crashed: a failure to report, not a crash
            verdicts.append(Verdict(method, "error", f"{type(e).__name__}: {one_line(e)}"))
            continue
        reason = next((r for r in (rule(method, size) for rule in POLICY) if r), "")
        verdicts.append(Verdict(method, "skipped", reason) if reason else Verdict(method, "applicable"))
    return verdicts


def _refused_by_footprint(method, objective, shapes, batch_size: int) -> None:
    """A method's footprint from the shapes alone, which raises ``ValueError`` where the
    method refuses what only shapes and dtypes show (kfac: a complex simulator output), as
    the run's memory preflight would; a footprint that needs concrete values is left to the run."""
    from ...engine.memory import stand_in
    from ...engine.setup import NOT_TRACEABLE

    if shapes.data is None:
        return
    try:
        method.footprint(objective, shapes.params, stand_in(shapes.data["train"], batch_size))
    except NOT_TRACEABLE:
        return


def plan(
    problems: Sequence[str],
    methods: Sequence[str],
    settings: dict[str, Any] | None = None,
    echo: Callable[[str], None] = lambda line: None,
) -> dict[str, list[Verdict]]:
    """Every problem's verdicts on every candidate method, after checking the settings:
    all input errors surface here, before anything trains."""
    settings = settings or {}
    check_settings(problems, methods, settings)
    verdicts = {}
    for problem in problems:
        verdicts[problem] = applicability(problem, methods, settings)
        echo(f"{problem}: {describe_verdicts(verdicts[problem])}")
    return verdicts


def describe_verdicts(verdicts: Sequence[Verdict]) -> str:
    """One line: the applicable methods, then the others grouped by status."""
    parts = [f"runs {', '.join(v.method for v in verdicts if v.runs) or 'nothing'}"]
    for status in ("not applicable", "skipped", "error"):
        names = [v.method for v in verdicts if v.status == status]
        if names:
            parts.append(f"{status}: {', '.join(names)}")
    return "; ".join(parts)
