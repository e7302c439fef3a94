"""The one error type of bad user input (its own module: every other module may raise it)."""


class ConfigError(ValueError):
    """A wrong problem, method, setting or budget; the message is one line with the choices.

    The message speaks the library's words (``resume=True``, ``out``, ``devices=4``); the
    command line prints it in its own (``--resume``, ``--out``, ``--devices 4``:
    :func:`physgrad.harness.words.command_line_words`)."""


class DoesNotFit(ConfigError):
    """The memory guard's refusal: a step needs more memory than is available; the message
    says what would fit (a batch size, a lighter variant of the method, more devices).

    A :class:`ConfigError` (the remedy is a setting), but one that depends on the method and
    the machine rather than on a wrong name or value: a study that records failures
    (``physgrad.harness.study.compare(record_failures=True)``, the bench) records it as that run's
    failure and goes on with the others."""
