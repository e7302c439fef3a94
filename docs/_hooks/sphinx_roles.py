"""Griffe extension for the API reference (mkdocs.yml, mkdocstrings' python handler).

physgrad's docstrings are written in reStructuredText habits that Markdown does not
render; the docstrings stay as they are, and this extension rewrites them as the
reference site loads them (nothing under src/ changes):

- Sphinx roles (``:class:`X```, ``:func:`~a.b.c```, ``:mod:``, ``:meth:``, ``:data:``,
  ``:attr:``) become code spans that link to the object's entry in the reference when it
  has one (an *optional* autorefs cross-reference: a target that is not documented renders
  as plain code, without a warning, so ``mkdocs build --strict`` does not depend on which
  private helpers a docstring mentions). ``X`` is resolved in the scope of the object whose
  docstring names it, as Sphinx would; ``~`` shows the last component only.
- A paragraph ending in ``::`` (an RST literal block follows) ends in ``:``; the indented
  block after it is already a Markdown code block.
- RST simple tables (columns under ``====  ====`` rules) become Markdown tables.

It also gives Equinox modules and NamedTuples the ``__init__`` that Python generates for
them from their annotated fields (as griffe's own extension does for ``@dataclass``), so a
rule's, route's or problem's signature shows its fields and defaults: static analysis sees
no ``__init__`` in ``class Oscillators(AbstractProblem): n_steps: int = eqx.field(...)``.
"""

from __future__ import annotations

import html
import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?P<role>class|func|meth|mod|data|attr|obj|exc|const):`(?P<target>[^`]+)`")
RULE = re.compile(r"^(?P<indent>\s*)=+(?:\s+=+)+\s*$")


class SphinxRoles(griffe.Extension):
    """Rewrites every docstring of the loaded package once it is fully loaded (imports known)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        objects = list(_walk(pkg))
        for obj in objects:
            if obj.docstring is not None:
                obj.docstring.value = rewrite(obj.docstring.value, obj, loader)
        custom = {obj.path for obj in objects if obj.is_class and "__init__" in obj.members}
        for obj in objects:
            if obj.is_class:
                _generated_init(obj, custom)  # type: ignore[arg-type]


def _walk(obj: griffe.Object):
    yield obj
    for member in obj.members.values():
        if not member.is_alias:
            yield from _walk(member)  # type: ignore[arg-type]


def rewrite(text: str, obj: griffe.Object, loader: griffe.GriffeLoader) -> str:
    text = _tables(text)
    text = re.sub(r"(?m)(\S)::[ \t]*$", r"\1:", text)
    return ROLE.sub(lambda m: _reference(m["role"], m["target"], obj, loader), text)


def _reference(role: str, target: str, obj: griffe.Object, loader: griffe.GriffeLoader) -> str:
    target = target.strip()
    explicit = re.fullmatch(r"(?P<title>.+?)\s*<(?P<target>[^>]+)>", target)  # :func:`title <a.b>`
    if explicit:
        title, target = explicit["title"], explicit["target"]
    else:
        title = target
    short = target.startswith("~")
    target = target.lstrip("~.").removesuffix("()")
    if short and not explicit:
        title = target.rsplit(".", 1)[-1]
    path = _resolve(target, obj, loader, module=role == "mod")
    code = f"<code>{html.escape(title)}</code>"
    if path is None:
        return code
    return f'<autoref identifier="{html.escape(path)}" optional>{code}</autoref>'


def _resolve(target: str, obj: griffe.Object, loader: griffe.GriffeLoader, module: bool) -> str | None:
    """The canonical path of ``target`` named in ``obj``'s docstring, or None (not physgrad's).

    A name that is both a submodule and the function it exports (``physgrad.hig``: the
    module ``methods/hig.py`` and its function ``hig``, which the package re-exports) is the
    function, unless the role is ``:mod:`` (Python binds the function; griffe the module)."""
    head, _, rest = target.partition(".")
    candidates = []
    if head == obj.package.name:
        candidates.append(target)
    else:
        scope: griffe.Object | None = obj
        while scope is not None:  # the docstring's object, then its parents (a class, its module)
            try:
                candidates.append(scope.resolve(head) + (f".{rest}" if rest else ""))
                break
            except (griffe.NameResolutionError, griffe.AliasResolutionError):
                scope = scope.parent
        candidates.append(f"{obj.package.name}.{target}")  # :mod:`routes` from inside physgrad
    for candidate in candidates:
        try:
            found = loader.modules_collection[candidate]
        except (KeyError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        try:
            found = found.final_target if found.is_alias else found
        except (griffe.AliasResolutionError, griffe.CyclicAliasError):
            return candidate
        name = candidate.rsplit(".", 1)[-1]
        if found.is_module and not module and name in found.members:
            return _resolve(f"{found.path}.{name}", obj, loader, module)
        return found.canonical_path
    return None


def _tables(text: str) -> str:
    """RST simple tables (a rule, a header, a rule, rows, a rule) as Markdown tables."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        match = RULE.match(lines[i])
        rules = [j for j in range(i, len(lines)) if RULE.match(lines[j])][:3] if match else []
        if len(rules) < 3 or rules[1] - rules[0] != 2 or lines[rules[0]] != lines[rules[2]]:
            out.append(lines[i])
            i += 1
            continue
        rule = lines[i]
        starts = [m.start() for m in re.finditer(r"=+", rule)]
        header = _cells(lines[rules[0] + 1], starts)
        rows = [_cells(line, starts) for line in lines[rules[1] + 1 : rules[2]] if line.strip()]
        indent = match["indent"] if match else ""
        out.append(indent + "| " + " | ".join(header) + " |")
        out.append(indent + "|" + "---|" * len(starts))
        out.extend(indent + "| " + " | ".join(row) + " |" for row in rows)
        i = rules[2] + 1
    return "\n".join(out)


def _cells(line: str, starts: list[int]) -> list[str]:
    """Split a row at the word starts nearest each column's rule (a cell may overrun its rule)."""
    words = [m.start() for m in re.finditer(r"(?<!\S)\S", line)]
    bounds = [0]
    for start in starts[1:]:
        after = [w for w in words if w > bounds[-1]]
        bounds.append(min(after, key=lambda w: abs(w - start)) if after else len(line))
    bounds.append(len(line))
    return [line[a:b].strip().replace("|", "\\|") or " " for a, b in zip(bounds, bounds[1:])]


FIELD_BASES = {"equinox.Module", "typing.NamedTuple"}


def _generated_init(cls: griffe.Class, custom: set[str]) -> None:
    """Add the ``__init__`` an Equinox module or a NamedTuple gets from its fields.

    Not for a class that defines ``__init__`` or inherits one written by hand (Equinox then
    keeps the parent's), nor for other classes."""
    try:
        mro = [cls, *cls.mro()]
    except ValueError:
        return
    if any(c.path in custom for c in mro):
        return
    if not any(getattr(base, "canonical_path", None) in FIELD_BASES for c in mro for base in c.bases):
        return
    fields: dict[str, griffe.Parameter] = {}
    for c in reversed(mro):  # base classes first; a redefined field keeps its place
        for member in c.members.values():
            if member.is_alias or not member.is_attribute or member.annotation is None:
                continue
            if "property" in member.labels or "instance-attribute" not in member.labels:
                continue  # a ClassVar (griffe labels it a class attribute only) or a property
            value = member.value
            arguments: dict[str, Any] = {}
            if isinstance(value, griffe.ExprCall) and value.canonical_path in ("equinox.field", "dataclasses.field"):
                arguments = {a.name: a.value for a in value.arguments if isinstance(a, griffe.ExprKeyword)}
                if str(arguments.get("init")) == "False":
                    continue
                if "default_factory" in arguments:
                    value = griffe.ExprCall(function=arguments["default_factory"], arguments=[])
                else:
                    value = arguments.get("default")
            kind = (
                griffe.ParameterKind.keyword_only
                if str(arguments.get("kw_only")) == "True"
                else griffe.ParameterKind.positional_or_keyword
            )
            fields[member.name] = griffe.Parameter(
                member.name, annotation=member.annotation, kind=kind, default=value, docstring=member.docstring
            )
    parameters = sorted(fields.values(), key=lambda p: p.kind is griffe.ParameterKind.keyword_only)
    self = griffe.Parameter("self", kind=griffe.ParameterKind.positional_or_keyword)
    init = griffe.Function(
        "__init__", lineno=0, endlineno=0, parent=cls, parameters=griffe.Parameters(self, *parameters), returns="None"
    )
    cls.set_member("__init__", init)
