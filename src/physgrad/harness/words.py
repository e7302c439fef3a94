"""The library's errors in the command line's words.

The library speaks its own arguments (``resume=True``, ``Budget(steps=N)``, ``devices=4``,
``out``); the command line prints the same line with its flags (``--resume``, ``--steps N``,
``--devices 4``, ``--out``). The translation lives here, beside the flags, so no module of
the core names a flag. Each rule rewrites one phrase the core is known to use; a message
with none of them is printed as it is.
"""

from __future__ import annotations

import re

# (pattern, replacement), applied in order; every pattern is a phrase of a core message
_RULES: tuple[tuple[re.Pattern[str], str], ...] = tuple(
    (re.compile(pattern), replacement)
    for pattern, replacement in (
        (r"resume it \(resume=True\) or choose another run directory", "pass --resume or choose another --out"),
        (r"choose another run directory", "choose another --out"),
        (r"Budget\(steps=N\), Budget\(epochs=E\) or Budget\(seconds=S\)", "--steps N, --epochs E or --seconds S"),
        (r"Budget\((steps|epochs|seconds)=([^)]*)\): \1 must be (.*)$", r"--\1 must be \3, got \2"),
        (r"0 <= process_id < num_processes", "0 <= --process-id < --num-processes"),
        (r"^coordinator must be", "--coordinator must be"),
        (r"^devices must be", "--devices must be"),
        (r"\bdevices=(\d+)", r"--devices \1"),
        (r"(?<![-\w])out '", "--out '"),  # not the "--out '" of a message already in flags
        (r"\banother out\b", "another --out"),
    )
)


def command_line_words(message: str) -> str:
    """``message`` (a :class:`~physgrad.ConfigError`'s line) with the library's argument
    names replaced by the command line's flags."""
    for pattern, replacement in _RULES:
        message = pattern.sub(replacement, message)
    return message
