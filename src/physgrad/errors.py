"""The one error type of bad user input (its own module: every other module may raise it)."""


class ConfigError(ValueError):
    """A wrong problem, method, setting or budget; the message is one line with the choices.

    The message speaks the library's words (``resume=True``, ``out``); ``flags``, where
    given, is the same line in the command line's words (``--resume``, ``--out``), which
    the command line prints instead."""

    def __init__(self, message: str, *, flags: str | None = None):
        super().__init__(message)
        self.flags = flags
