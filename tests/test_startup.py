"""``physgrad --version`` and ``physgrad --help`` answer without importing JAX (issue 52: they
took 5.5 s because the package imported the whole library), and the package's public names,
imported on first use, are the ones its static imports declare."""

import ast
import importlib
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import physgrad

INIT = Path(physgrad.__file__)
HEAVY = ("jax", "jaxlib", "equinox", "optax")


@pytest.mark.parametrize("flag", ["--version", "--help"])
def test_version_and_help_import_no_jax(flag):
    """``python -m physgrad FLAG`` in a fresh interpreter (as the ``physgrad`` script runs it):
    which of the heavy packages it imported, read from ``sys.modules`` afterwards."""
    code = textwrap.dedent(
        f"""
        import json, runpy, sys
        sys.argv = ["physgrad", {flag!r}]
        try:
            runpy.run_module("physgrad", run_name="__main__", alter_sys=True)
        except SystemExit as e:
            code = e.code
        print()
        print(json.dumps({{"code": code, "imported": [m for m in {HEAVY!r} if m in sys.modules]}}))
        """
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-4000:]
    info = json.loads(result.stdout.strip().splitlines()[-1])
    assert info["code"] in (0, None)
    assert info["imported"] == []
    assert (
        ("usage: physgrad" in result.stdout)
        if flag == "--help"
        else (f"physgrad {physgrad.__version__}" in result.stdout)
    )


def static_imports() -> dict[str, str]:
    """{name: module} of the imports under ``if TYPE_CHECKING:`` in physgrad/__init__.py
    ("" for a submodule imported as ``from . import name``)."""
    tree = ast.parse(INIT.read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    names = {}
    for node in block.body:
        assert isinstance(node, ast.ImportFrom) and node.level == 1, ast.dump(node)
        for alias in node.names:
            names[alias.asname or alias.name] = "." + node.module if node.module else ""
    return names


def test_the_lazy_table_matches_the_static_imports_and_all():
    assert physgrad._PUBLIC == static_imports()
    assert sorted(physgrad._PUBLIC) == sorted(physgrad.__all__)
    for name, where in physgrad._PUBLIC.items():
        expected = importlib.import_module(f"physgrad.{name}" if not where else where, "physgrad")
        assert getattr(physgrad, name) is (expected if not where else getattr(expected, name)), name
    assert set(physgrad.__all__) <= set(dir(physgrad))


def test_a_submodule_is_an_attribute_and_a_missing_name_an_attribute_error():
    assert physgrad.engine is importlib.import_module("physgrad.engine")
    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        physgrad.no_such_name  # noqa: B018
    assert not hasattr(physgrad, "__no_such_dunder__")
