"""No import cycle in ``src/physgrad``: the import graph of the package's modules, read with
:mod:`ast` (nothing is imported), has no strongly connected component of more than one module.

Two graphs are checked:

- the **module-level** imports (those at the top of a module, and inside module-level ``if``
  and ``try`` blocks): what runs when the module is imported. A cycle here makes the import
  order matter, and it may not have a single exception;
- **every** import, function-level ones included. A function-level import is how a cycle
  hides: ``engine/result.py`` read run directories through ``engine/recording.py`` inside a
  function while ``recording`` imported ``result`` at its top (issue 52). Two modules that
  need each other are one concern split over two files, whatever the level of the import.
  A function-level import that only defers a heavy dependency (the command line's lazy
  imports) points down the layers and makes no cycle.

An import ``from a import b`` counts as an edge to the module ``a.b`` where that is a module,
else to ``a`` (whose ``__init__`` runs); implicit imports of parent packages are not edges
(a package's ``__init__`` importing its own modules is the usual shape).
"""

from __future__ import annotations

import ast
from pathlib import Path

import physgrad

ROOT = Path(physgrad.__file__).parent

# Function-level cycles left, each a set of module names with why. Remove an entry when its
# cycle is gone; a new cycle fails.
KNOWN_FUNCTION_LEVEL = [
    # kronecker_hig's deprecated alias of AveragedKronecker (one release) imports its new home
    {"physgrad.methods.averaged_kronecker", "physgrad.methods.kronecker_hig"},
]


def _modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the package: dotted name -> (file, whether it is a package's __init__)."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if package else parts)] = (path, package)
    return out


def _module_level(body: list[ast.stmt]):
    """The import statements that run when a module is imported."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, (ast.If, ast.Try)):
            for block in (node.body, node.orelse, getattr(node, "finalbody", [])):
                yield from _module_level(block)
            for handler in getattr(node, "handlers", []):
                yield from _module_level(handler.body)


def _imports(name: str, path: Path, package: bool, modules, *, functions: bool) -> set[str]:
    tree = ast.parse(path.read_text())
    nodes = (
        [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        if functions
        else list(_module_level(tree.body))
    )
    here = name if package else name.rpartition(".")[0]
    out = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names if alias.name in modules)
            continue
        if node.level:  # relative: level 1 is this package, each further dot one package up
            base = here.split(".")[: len(here.split(".")) - (node.level - 1)]
            source = ".".join(base + ([node.module] if node.module else []))
        else:
            source = node.module or ""
        for alias in node.names:
            if f"{source}.{alias.name}" in modules:
                out.add(f"{source}.{alias.name}")
            elif source in modules:
                out.add(source)
    out.discard(name)
    return out


def _cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm,
    iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            node, edges = work[-1]
            for target in edges:
                if target not in index:
                    index[target] = low[target] = len(index)
                    stack.append(target)
                    on_stack.add(target)
                    work.append((target, iter(sorted(graph[target]))))
                    break
                if target in on_stack:
                    low[node] = min(low[node], index[target])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = set()
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.add(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(component)
    return found


def _graph(*, functions: bool) -> dict[str, set[str]]:
    modules = _modules()
    return {
        name: _imports(name, path, package, modules, functions=functions) for name, (path, package) in modules.items()
    }


def test_the_graph_reader_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_at_module_level():
    cycles = _cycles(_graph(functions=False))
    assert not cycles, "import cycles (module level): " + "; ".join(" <-> ".join(sorted(c)) for c in cycles)


def test_no_import_cycle_through_function_level_imports():
    cycles = [c for c in _cycles(_graph(functions=True)) if c not in KNOWN_FUNCTION_LEVEL]
    assert not cycles, "import cycles (function-level imports included): " + "; ".join(
        " <-> ".join(sorted(c)) for c in cycles
    )
