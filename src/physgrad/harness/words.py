"""The library's errors in the command line's words, by error type and argument.

The library speaks its own arguments and objects (``resume=True``, ``Budget(steps=N)``,
``devices=4``, ``out``, ``UnrolledGradient(policy=S())``); the command line prints the same
line with its flags, problems and methods (``--resume``, ``--steps N``, ``--devices 4``,
``--out``, ``nog``). The core raises the small error types of
:mod:`physgrad.errors`, which carry the arguments they name as fields; this module writes
each type's line from those fields, beside the flags, so no module of the core names a flag
and no message is parsed. Any other error is printed as it is.
"""

from __future__ import annotations

from collections.abc import Callable

from ..errors import (
    BudgetOutOfRange,
    CoordinatorInvalid,
    DevicesInvalid,
    DevicesRefused,
    DoesNotFit,
    MethodRefused,
    MissingPieces,
    NoBudget,
    NotRefinable,
    PathRefused,
    ProcessesInvalid,
    RunDirectoryExists,
    RunDirectoryRefused,
    SolverNotDifferentiable,
)

# the library's argument -> the command line's flag
FLAGS = {"out": "--out", "devices": "--devices", "resume": "--resume", "coordinator": "--coordinator"}


def _devices(count: int) -> str:
    return f"{FLAGS['devices']} {count}"


# a rule's spelling in the library's errors -> its method on the command line
METHODS = {
    "UnrolledGradient(policy=S())": "nog",
    "UnrolledGradient(teacher_forcing=True)": "one",
    "RolloutGradient(policy=S())": "no_temporal",
}
# the fields of a part a problem lacks (physgrad.methods.Part) -> what to use instead, in the
# command line's problems and methods
INSTEAD = {
    ("predict", "loss"): "use a rollout method",
    ("rollout",): "use a closed-loop problem (cartpole, guidance, quantum_control)",
    ("unrolled",): "use a time-stepper problem (ks, kolmogorov, advection_1d)",
}
# SIP's solvers other than the analytic inverse (physgrad.harness.registry.INVERSE_SOLVERS)
OTHER_SOLVERS = ("gauss_newton", "saddle_free_newton", "lbfgs", "linear_solve")


def _missing(e: MissingPieces) -> str:
    if e.fields == ("inverse",):  # SIP's Analytic() on a problem without one: a choice of solver
        return f"this problem has no analytic inverse; valid choices: {', '.join(OTHER_SOLVERS)}"
    instead = INSTEAD.get(e.fields, e.instead)
    return f"{e.rule} needs a problem with {e.words}" + (f"; {instead}" if instead else "")


def _not_differentiable(e: SolverNotDifferentiable) -> str:
    methods = [METHODS.get(rule, rule) for rule in e.instead]
    return f"this method differentiates through the solver, which is not differentiable; use {' or '.join(methods)}"


# error type -> its line in the command line's words, from the error's fields
_LINES: dict[type, Callable] = {
    RunDirectoryExists: lambda e: f"run directory {e.run_dir} exists; pass --resume or choose another --out",
    RunDirectoryRefused: lambda e: f"{e.reason}choose another --out",
    NoBudget: lambda e: "give exactly one budget: --steps N, --epochs E or --seconds S",
    BudgetOutOfRange: lambda e: f"--{e.kind} must be {e.requirement}, got {e.amount!r}",
    ProcessesInvalid: lambda e: f"need 0 <= --process-id < --num-processes; got {e.process_id} and {e.num_processes}",
    CoordinatorInvalid: lambda e: f"--coordinator must be HOST:PORT, got {e.coordinator!r}",
    DevicesInvalid: lambda e: f"--devices must be {e.accepted}, got {e.devices!r}",
    DevicesRefused: lambda e: f"{e.before}{_devices(e.devices)}{e.after}",
    DoesNotFit: lambda e: e.before if e.devices is None else f"{e.before}{_devices(e.devices)}{e.after}",
    MissingPieces: _missing,
    SolverNotDifferentiable: _not_differentiable,
    # the command line picks a time-stepper's composition by its setup setting (harness.objects)
    NotRefinable: lambda e: "prdp refines the solver of a correction setup; use setup=correction",
    MethodRefused: lambda e: f"{e.label} on {e.problem}: {command_line_words(e.cause)}",
    PathRefused: lambda e: e.template.format(argument=FLAGS.get(e.argument, e.argument), **e.values),
}


def command_line_words(error: BaseException) -> str:
    """``error``'s one line with the library's argument names replaced by the command line's
    flags (by its type, :data:`_LINES`); any other error's own line."""
    for kind in type(error).__mro__:
        if kind in _LINES:
            return _LINES[kind](error)
    return str(error)
