"""Docs that cannot drift (issue 53 item 4): every exported name has an API page, the
command-line page's help texts are the parser's, and the site's configuration keeps search
working from disk and the report scripts out of the pages.

An API page documents a name when one of its ``::: path`` directives (mkdocstrings) is the
name, or the same object under another path (``::: physgrad.methods.hig.hig`` documents
``physgrad.hig``), or a module whose rendered members include it (a directive with no
``members`` option renders the module's ``__all__``; a ``members`` list renders those).
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import pkgutil
import re
import types
from pathlib import Path

import pytest

import physgrad

ROOT = Path(__file__).resolve().parents[1]
API = ROOT / "docs" / "api"
DIRECTIVE = re.compile(r"^(?P<indent> *)::: (?P<path>[\w.]+)\s*$")


def public_modules() -> list[str]:
    """physgrad and each of its modules that declares ``__all__``, outside the harness (the
    command line's names and strings: Architecture describes it, not the API reference)."""
    found = ["physgrad"]
    for info in pkgutil.walk_packages(physgrad.__path__, "physgrad."):
        if info.name.startswith("physgrad.harness"):
            continue
        source = ROOT / "src" / (info.name.replace(".", "/") + ("/__init__.py" if info.ispkg else ".py"))
        if re.search(r"^__all__", source.read_text(encoding="utf-8"), re.MULTILINE):
            found.append(info.name)
    return found


def directives() -> dict[str, list[str] | None]:
    """``{path: members}`` of every directive on the API pages: ``members`` None where the
    directive has no ``members`` option, [] for ``members: false``, else the list."""
    found: dict[str, list[str] | None] = {}
    for page in sorted(API.glob("*.md")):
        lines = page.read_text(encoding="utf-8").splitlines()
        for i, line in enumerate(lines):
            m = DIRECTIVE.match(line)
            if m is None:
                continue
            options = []
            for following in lines[i + 1 :]:  # the directive's indented YAML options
                if following.strip() and len(following) - len(following.lstrip()) <= len(m["indent"]):
                    break
                options.append(following.strip())
            members: list[str] | None = None
            for j, option in enumerate(options):
                if option.startswith("members:"):
                    value = option.split(":", 1)[1].strip()
                    members = (
                        [] if value == "false" else [o[2:].strip() for o in options[j + 1 :] if o.startswith("- ")]
                    )
            found[m["path"]] = members
    return found


def resolve(path: str) -> object:
    """The object at a dotted path: the longest importable module, then attributes."""
    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj: object = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for name in parts[k:]:
            obj = getattr(obj, name)
        return obj
    raise ImportError(path)


def documented() -> dict[str, object]:
    """Every documented path and its object, members of module directives included."""
    found: dict[str, object] = {}
    for path, members in directives().items():
        obj = found[path] = resolve(path)
        names = getattr(obj, "__all__", []) if isinstance(obj, types.ModuleType) and members is None else members
        for name in names or []:
            found[f"{path}.{name}"] = getattr(obj, name)
    return found


def test_every_exported_name_is_on_an_api_page():
    pages = documented()
    ids = {id(obj) for obj in pages.values()}
    missing = []
    for module in public_modules():
        for name in importlib.import_module(module).__all__:
            obj = getattr(importlib.import_module(module), name)
            if f"{module}.{name}" in pages:
                continue
            # a constant (a string, a tuple) is the same object under many names: match its name
            if isinstance(obj, (str, int, float, tuple, frozenset, dict)):
                if any(path.rsplit(".", 1)[-1] == name for path in pages):
                    continue
            elif id(obj) in ids:
                continue
            missing.append(f"{module}.{name}")
    assert not missing, f"exported but on no page of docs/api/ (add a ::: directive): {missing}"


def test_the_names_the_readme_and_notebooks_use_have_pages():
    # issue 53: these were used by the README or the notebooks and had no page
    pages = documented()
    for path in ("physgrad.problems.sim.phiflow", "physgrad.problems.sim.steppers", "physgrad.acceptance",
                 "physgrad.cpu.threads", "physgrad.engine.progress.RichProgressMeter",
                 "physgrad.extras.MissingExtra"):  # fmt: skip
        assert path in pages, path


# --- the command-line page ------------------------------------------------------------------
def cli_hook():
    pytest.importorskip("mkdocs")
    spec = importlib.util.spec_from_file_location("cli_help", ROOT / "docs" / "_hooks" / "cli_help.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_cli_page_gets_every_commands_help_from_the_parser():
    hook = cli_hook()
    page = hook.help_page((API / "cli.md").read_text(encoding="utf-8"), ROOT / "src")
    from physgrad.harness.arguments import build_parser

    root = build_parser()
    commands = next(a for a in root._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert {"calibrate", "tune"} <= set(commands)  # those the pasted texts lacked
    for name, parser in {"": root, **commands}.items():
        usage = f"usage: physgrad {name}".rstrip()
        assert usage in page, name
        for action in parser._actions:  # every flag of every command, as --help prints it
            for flag in action.option_strings:
                assert flag in page, (name, flag)
    assert "<!-- physgrad-help" not in page


def test_the_cli_page_is_the_same_whatever_the_builders_terminal(monkeypatch):
    hook = cli_hook()
    markdown = (API / "cli.md").read_text(encoding="utf-8")
    pages = set()
    for columns in ("40", "200"):  # argparse wraps at $COLUMNS unless told a width
        monkeypatch.setenv("COLUMNS", columns)
        pages.add(hook.help_page(markdown, ROOT / "src"))
    assert len(pages) == 1


def test_a_command_without_its_marker_fails_the_build():
    hook = cli_hook()
    from mkdocs.exceptions import PluginError

    page = (API / "cli.md").read_text(encoding="utf-8").replace("<!-- physgrad-help: calibrate -->", "")
    with pytest.raises(PluginError, match=r"without a marker.*calibrate"):
        hook.help_page(page, ROOT / "src")
    with pytest.raises(PluginError, match=r"do not exist: \['nosuch'\]"):
        hook.help_page(page + "\n<!-- physgrad-help: nosuch -->\n<!-- physgrad-help: calibrate -->\n", ROOT / "src")


# --- the site's configuration ---------------------------------------------------------------
def site_config() -> dict:
    yaml = pytest.importorskip("yaml")
    return yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))


def plugin(config: dict, name: str) -> dict | None:
    for entry in config["plugins"]:
        if entry == name:
            return {}
        if isinstance(entry, dict) and name in entry:
            return entry[name] or {}
    return None


def test_search_works_from_disk_without_a_network():
    config = site_config()
    assert plugin(config, "offline") is not None  # the index as a script: a page from disk fetches no file
    assert config["use_directory_urls"] is False
    # the Worker for file:// pages ships with the site; "iframe-worker" in its name keeps
    # the offline plugin from adding a CDN's copy, which a reader without a network never gets
    (shim,) = config["extra"]["polyfills"]
    assert "iframe-worker" in shim and (ROOT / "docs" / shim).is_file()
    assert "docs/_hooks/cli_help.py" in " ".join(config["hooks"])


def test_only_notebooks_become_notebook_pages():
    jupyter = plugin(site_config(), "mkdocs-jupyter")
    assert jupyter is not None and jupyter["include"] == ["*.ipynb"]
