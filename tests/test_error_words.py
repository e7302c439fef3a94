"""A rule's refusal names library objects; the command line says the same with its methods.

The core raises typed errors (:mod:`physgrad.errors`) whose fields carry what the line names
(a rule's spelling, the fields of a missing part); :func:`physgrad.harness.words.command_line_words`
writes the command line's line from those fields, by type. No core message names a
command-line method, and the harness parses no prose.
"""

from __future__ import annotations

from types import SimpleNamespace

import jax.numpy as jnp
import pytest

from physgrad.errors import MethodRefused, MissingPieces, SolverNotDifferentiable
from physgrad.harness import words
from physgrad.harness.registry import INVERSE_SOLVERS, METHODS
from physgrad.inverse import Analytic
from physgrad.methods import Gradient, Objective, RolloutGradient, ScaleInvariantPhysics, UnrolledGradient
from physgrad.rollout import Combined, M, R, S

# The command line's method names: none may appear in a core message.
CLI_METHODS = ("nog", "one", "no_temporal", "gauss_newton", "saddle_free_newton", "lbfgs", "linear_solve")


def _open_loop(differentiable: bool = True) -> Objective:
    return Objective(predict=lambda p, s: p * s, loss=lambda y, s: y**2, differentiable=differentiable)


def _no_derivatives():
    """A rollout system (stand-in) whose physics declares itself non-differentiable."""
    return SimpleNamespace(differentiable_physics=False)


def _refusal(rule, objective) -> Exception:
    with pytest.raises(ValueError) as info:
        rule.check(objective)
    return info.value


def _names_no_cli_method(message: str) -> bool:
    return not any(f" {name}" in message.replace(",", " ") for name in CLI_METHODS)


def test_a_rule_through_a_non_differentiable_solver_is_told_the_rules_that_stop_there():
    unrolled = Objective(unrolled=lambda m, teacher_forcing: _no_derivatives())
    rollout = Objective(rollout=_no_derivatives())
    cases = [
        (Gradient(), _open_loop(differentiable=False), "nog or one"),
        (UnrolledGradient(), unrolled, "nog or one"),
        (UnrolledGradient(policy=M()), unrolled, "nog or one"),
        (RolloutGradient(R()), rollout, "no_temporal"),
        (RolloutGradient(Combined(M(), R())), rollout, "no_temporal"),
    ]
    for rule, objective, cli in cases:
        error = _refusal(rule, objective)
        assert isinstance(error, SolverNotDifferentiable), rule
        assert "not differentiable" in str(error) and _names_no_cli_method(str(error)), str(error)
        assert "Gradient(" in str(error)  # the library's rule objects
        assert words.command_line_words(error).endswith(f"not differentiable; use {cli}")
    # the rules that stop the gradient at the solver run on the same objectives
    UnrolledGradient(policy=S()).check(unrolled)
    UnrolledGradient(teacher_forcing=True).check(unrolled)
    RolloutGradient(S()).check(rollout)
    # every spelling the library uses is one the command line knows
    for rule in words.METHODS:
        assert words.METHODS[rule] in METHODS


def test_a_missing_part_names_library_objects_and_the_command_line_its_own():
    error = _refusal(Gradient(), Objective(rollout=_no_derivatives()))
    assert isinstance(error, MissingPieces) and error.fields == ("predict", "loss")
    assert str(error) == (
        "the DP gradient needs a problem with predict(params, sample) and loss(y, sample); "
        "use a rollout rule (RolloutGradient, UnrolledGradient)"
    )
    assert words.command_line_words(error).endswith("; use a rollout method")
    error = _refusal(RolloutGradient(), _open_loop())
    assert "AbstractClosedLoop" in str(error)
    assert words.command_line_words(error).endswith("(cartpole, guidance, quantum_control)")
    error = _refusal(UnrolledGradient(), _open_loop())
    assert "AbstractTimeStepper" in str(error)
    assert words.command_line_words(error).endswith("(ks, kolmogorov, advection_1d)")


def test_sip_without_an_analytic_inverse_offers_the_other_solvers():
    split = Objective(
        network_output=lambda p, s: p * s, simulate=lambda x, s: x, target=lambda s: jnp.zeros(()), loss=None
    )
    ScaleInvariantPhysics().check(split)  # solver=None falls back to Gauss-Newton
    error = _refusal(ScaleInvariantPhysics(solver=Analytic()), split)
    assert isinstance(error, MissingPieces) and _names_no_cli_method(str(error))
    assert "GaussNewton()" in str(error)
    assert words.command_line_words(error) == (
        "this problem has no analytic inverse; valid choices: gauss_newton, saddle_free_newton, lbfgs, linear_solve"
    )
    ScaleInvariantPhysics(solver=Analytic()).check(split._replace(inverse=lambda x, y, yt, s: x))
    # without the split pieces, those are what it names first
    error = _refusal(ScaleInvariantPhysics(solver=Analytic()), _open_loop())
    assert isinstance(error, MissingPieces) and error.fields == ("network_output", "simulate", "target")
    # the command line's list is its registry's, less the two that pick the analytic inverse
    assert words.OTHER_SOLVERS == tuple(s for s in INVERSE_SOLVERS if s not in ("auto", "analytic"))


def test_a_stage_refusal_keeps_its_cause_for_the_command_line():
    cause = _refusal(UnrolledGradient(), Objective(unrolled=lambda m, teacher_forcing: _no_derivatives()))
    error = MethodRefused("wig", "ks", cause)
    assert str(error) == f"wig on ks: {cause}"
    assert words.command_line_words(error) == (
        "wig on ks: this method differentiates through the solver, which is not differentiable; use nog or one"
    )


def test_prdp_on_a_composition_without_a_solver_names_compositions():
    from physgrad.errors import NotRefinable
    from physgrad.problems import Advection1d
    from physgrad.problems.sim.steppers import Parallel, Prediction

    Advection1d(composition=Parallel(1.0)).check_refinable()
    with pytest.raises(NotRefinable) as info:
        Advection1d(composition=Prediction()).check_refinable()
    assert "Prediction()" in str(info.value) and "setup" not in str(info.value)
    assert words.command_line_words(info.value) == "prdp refines the solver of a correction setup; use setup=correction"
