"""The error types of bad user input (their own module: every other module may raise them).

:class:`ConfigError` is a one-line message. Where the message names an argument of the
library (``resume=True``, ``out``, ``devices=4``, ``Budget(steps=N)``), the error is one of
the small subclasses below, which carry those arguments as fields and write the library's
line from them; the command line writes its own line (``--resume``, ``--out``,
``--devices 4``, ``--steps N``) from the same fields, by type
(:func:`physgrad.harness.words.command_line_words`). So no core message is parsed, and no
module of the core names a flag.
"""

from __future__ import annotations

import sys
import warnings
from typing import Any


class ConfigError(ValueError):
    """A wrong problem, method, setting or budget; the message is one line with the choices."""


class RunDirectoryExists(ConfigError):
    """A run directory already holds a run, and the call did not ask to resume it."""

    def __init__(self, run_dir: Any):
        self.run_dir = run_dir
        super().__init__(f"run directory {run_dir} exists; resume it (resume=True) or choose another run directory")


class RunDirectoryRefused(ConfigError):
    """A run directory cannot take this run; ``reason`` (ending in its own punctuation)
    says why, and the remedy is another run directory."""

    def __init__(self, reason: str):
        self.reason = reason
        super().__init__(f"{reason}choose another run directory")


class NoBudget(ConfigError):
    """A budget that names none, or more than one, of steps, epochs and seconds."""

    def __init__(self):
        super().__init__("give exactly one budget: Budget(steps=N), Budget(epochs=E) or Budget(seconds=S)")


class BudgetOutOfRange(ConfigError):
    """A budget's amount outside its range: ``kind`` (steps, epochs or seconds), the
    ``amount`` given and the ``requirement`` it fails (e.g. "an integer >= 1")."""

    def __init__(self, kind: str, amount: Any, requirement: str):
        self.kind, self.amount, self.requirement = kind, amount, requirement
        super().__init__(f"Budget({kind}={amount!r}): {kind} must be {requirement}")


class ProcessesInvalid(ConfigError):
    """A multi-process run's ``process_id`` outside ``[0, num_processes)``."""

    def __init__(self, process_id: int, num_processes: int):
        self.process_id, self.num_processes = process_id, num_processes
        super().__init__(f"need 0 <= process_id < num_processes; got {process_id} and {num_processes}")


class CoordinatorInvalid(ConfigError):
    """A multi-process run's coordinator address that is not ``HOST:PORT``."""

    def __init__(self, coordinator: Any):
        self.coordinator = coordinator
        super().__init__(f"coordinator must be HOST:PORT, got {coordinator!r}")


class DevicesInvalid(ConfigError):
    """A ``devices`` value of the wrong kind; ``accepted`` says which kinds are taken."""

    def __init__(self, devices: Any, accepted: str):
        self.devices, self.accepted = devices, accepted
        super().__init__(f"devices must be {accepted}, got {devices!r}")


class DevicesRefused(ConfigError):
    """A device count this run cannot use: ``before`` and ``after`` the count, which the
    library writes ``devices=N``."""

    def __init__(self, devices: int, before: str = "", after: str = ""):
        self.devices, self.before, self.after = devices, before, after
        super().__init__(f"{before}devices={devices}{after}")


class DoesNotFit(ConfigError):
    """The memory guard's refusal: a step needs more memory than is available; the message
    says what would fit (a batch size, a lighter variant of the method, more devices).

    A :class:`ConfigError` (the remedy is a setting), but one that depends on the method and
    the machine rather than on a wrong name or value: a study that records failures
    (``physgrad.harness.study.compare(record_failures=True)``, the bench) records it as that run's
    failure and goes on with the others.

    ``DoesNotFit(message)``, or with a device count that would fit: ``before``, the count
    (``devices=N`` in the library's words), ``after``."""

    def __init__(self, before: str, devices: int | None = None, after: str = ""):
        self.before, self.devices, self.after = before, devices, after
        super().__init__(before if devices is None else f"{before}devices={devices}{after}")


class PathRefused(ConfigError):
    """A path argument (``argument``, e.g. ``out``) that cannot be used: the message is
    ``template`` with ``{argument}`` where it names the argument."""

    def __init__(self, argument: str, template: str, **values: Any):
        self.argument, self.template, self.values = argument, template, values
        super().__init__(template.format(argument=argument, **values))


class MissingPieces(ConfigError):
    """A rule refuses a problem whose objective lacks pieces it needs: ``rule`` (how the
    errors call it), the ``fields`` of its part (:class:`physgrad.methods.Part`), the part
    in ``words`` and what to use ``instead``, in the library's objects."""

    def __init__(self, rule: str, fields: tuple[str, ...], words: str, instead: str = ""):
        self.rule, self.fields, self.words, self.instead = rule, fields, words, instead
        super().__init__(f"{rule} needs a problem with {words}" + (f"; {instead}" if instead else ""))


class SolverNotDifferentiable(ConfigError):
    """A rule back-propagates through a solver that declares itself non-differentiable;
    ``instead`` spells the rules that stop the gradient at the solver (e.g.
    ``UnrolledGradient(policy=S())``)."""

    def __init__(self, instead: tuple[str, ...]):
        self.instead = instead
        super().__init__(
            "this method differentiates through the solver, which is not differentiable; use " + " or ".join(instead)
        )


class NotRefinable(ConfigError):
    """PRDP asked of a problem whose solver is not stepped: its ``composition`` (a
    time-stepper's :class:`~physgrad.problems.sim.steppers.AbstractComposition`, as given)
    runs no solver to refine."""

    def __init__(self, composition: Any):
        self.composition = composition
        super().__init__(
            f"prdp refines the solver the composition steps, and {composition!r} steps none; "
            "use a composition that runs the solver (Parallel, Sequential or Bypass)"
        )


class MethodRefused(ConfigError):
    """A method (``label``) refuses a problem (named ``problem``); ``cause`` is its own
    one-line error, kept so the command line can write it in its words."""

    def __init__(self, label: str, problem: str, cause: BaseException):
        self.label, self.problem, self.cause = label, problem, cause
        super().__init__(f"{label} on {problem}: {cause}")


class ProgressInvalid(ConfigError):
    """A ``progress`` argument of :func:`physgrad.fit` that is neither a progress meter nor
    None, True or False."""

    def __init__(self, progress: Any):
        self.progress = progress
        super().__init__(
            f"progress must be None (a bar in a terminal), True, False or a progress meter "
            f"(physgrad.engine.progress.AbstractProgressMeter), got {progress!r}"
        )


# Frames a deprecation warning looks past to find the user's line: this package's own, the
# wrappers that run a Module's __init__ (Equinox) or check its types (jaxtyping and the
# checkers it calls), whose depth varies with how the user imported physgrad, and generated
# code (a dataclass's __init__, "<string>", which runs with its class's module as globals:
# a user's subclass of a physgrad Module).
_LIBRARY_FRAMES = ("physgrad.", "equinox", "jaxtyping", "typeguard", "beartype")


def _library_frame(frame) -> bool:
    return frame.f_globals.get("__name__", "").startswith(_LIBRARY_FRAMES) or frame.f_code.co_filename.startswith("<")


def warn_deprecated(message: str) -> None:
    """A ``DeprecationWarning`` that names the first line outside physgrad and the wrappers
    above (Python 3.12's ``skip_file_prefixes``, by module name, for 3.11)."""
    frame, level = sys._getframe(1), 2  # stacklevel 2 is warn_deprecated's caller
    while frame is not None and _library_frame(frame):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, DeprecationWarning, stacklevel=level)
