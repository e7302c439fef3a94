"""The one error type of bad user input (its own module: every other module may raise it)."""


class ConfigError(ValueError):
    """A wrong problem, method, setting or budget; the message is one line with the choices."""
