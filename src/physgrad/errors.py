"""The one error type of bad user input (its own module: every other module may raise it)."""


class ConfigError(ValueError):
    """A wrong problem, method, setting or budget; the message is one line with the choices.

    The message speaks the library's words (``resume=True``, ``out``); ``flags``, where
    given, is the same line in the command line's words (``--resume``, ``--out``), which
    the command line prints instead."""

    def __init__(self, message: str, *, flags: str | None = None):
        super().__init__(message)
        self.flags = flags


class DoesNotFit(ConfigError):
    """The memory guard's refusal: a step needs more memory than is available; the message
    says what would fit (a batch size, a lighter variant of the method, more devices).

    A :class:`ConfigError` (the remedy is a setting), but one that depends on the method and
    the machine rather than on a wrong name or value: a study that records failures
    (``physgrad.harness.study.compare(record_failures=True)``, the bench) records it as that run's
    failure and goes on with the others."""
