"""MkDocs hook (mkdocs.yml, ``hooks:``): the command-line page's help texts from the parser.

``docs/api/cli.md`` holds a marker line ``<!-- physgrad-help: COMMAND -->`` (``COMMAND``
empty for ``physgrad --help``) where each help text goes; this hook replaces every marker
with the text argparse prints for ``physgrad [COMMAND] --help``, from the parser the command
line itself runs (:func:`physgrad.harness.arguments.build_parser`, of this checkout's
``src``). The page therefore cannot drift from ``--help``: a changed flag changes the page
at the next build, and a subcommand without a marker (or a marker naming none) fails the
build. Generated rather than compared by a test: the texts are never edited by hand, so a
change of the command line needs no change of the page.

The texts are wrapped at 80 columns whatever the terminal of the build (argparse otherwise
reads ``$COLUMNS``), so the site is the same wherever it is built.
"""

from __future__ import annotations

import argparse
import functools
import re
import sys
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import Files
from mkdocs.structure.pages import Page

PAGE = "api/cli.md"
MARKER = re.compile(r"^<!-- physgrad-help:(?P<command>[ \w-]*)-->$", re.MULTILINE)
WIDTH = 80


def parsers(src: Path) -> dict[str, argparse.ArgumentParser]:
    """``{"": physgrad's parser, "train": train's, ...}``, each printing at :data:`WIDTH` columns."""
    if str(src) not in sys.path:  # this checkout's command line, not an installed one
        sys.path.insert(0, str(src))
    from physgrad.harness.arguments import build_parser

    root = build_parser()
    found: dict[str, argparse.ArgumentParser] = {"": root}
    for action in root._actions:  # argparse keeps its subparsers in the subparsers action's choices
        if isinstance(action, argparse._SubParsersAction):
            found.update(action.choices)
    for parser in found.values():
        parser.formatter_class = functools.partial(parser.formatter_class, width=WIDTH)  # pyright: ignore[reportCallIssue]  (every HelpFormatter takes width)
    return found


def help_page(markdown: str, src: Path) -> str:
    """``markdown`` with every marker replaced by its command's ``--help`` in a ``text`` block;
    a :class:`PluginError` if a marker names no command or a command has no marker."""
    helps = parsers(src)
    named = [m["command"].strip() for m in MARKER.finditer(markdown)]
    unknown = sorted(set(named) - set(helps))
    missing = sorted(set(helps) - set(named))
    if unknown or missing:
        raise PluginError(
            f"{PAGE}: markers for commands that do not exist: {unknown or 'none'}; commands without a marker "
            f"(<!-- physgrad-help: COMMAND -->): {missing or 'none'}"
        )
    return MARKER.sub(lambda m: f"```text\n{helps[m['command'].strip()].format_help().rstrip()}\n```", markdown)


def on_page_markdown(markdown: str, page: Page, config: MkDocsConfig, files: Files) -> str:
    if page.file.src_uri != PAGE:
        return markdown
    return help_page(markdown, Path(config.config_file_path).parent / "src")
