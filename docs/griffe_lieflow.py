"""A griffe extension for lieflow's API reference (loaded by mkdocstrings, see mkdocs.yml).

lieflow's docstrings are numpy style with a few reStructuredText constructs that
mkdocstrings renders verbatim. This extension rewrites them into Markdown at load time:

* ``:math:`x``` -> ``\\(x\\)`` and ``.. math::`` blocks -> ``\\[ ... \\]`` (MathJax via
  pymdownx.arithmatex; blocks with ``&`` or ``\\\\`` are wrapped in ``aligned``);
* ``:class:`~a.b.C``` and the other cross-reference roles -> inline code (``C``);
* a paragraph ending in ``::`` before a literal block -> ``:``;
* grouped numpy entries (``rtol, atol : float``) -> one entry per name (griffe would give
  every name of a group the first name's default).

It also gives attrs classes (``@attrs.frozen`` ...) the ``__init__`` signature attrs
generates at run time, which static analysis cannot see, so the reference shows the real
parameters and defaults instead of "required".

Why it is needed (checked with mkdocstrings-python 2.0 / griffe 2.4): the numpy docstring
style alone builds without warnings, but renders the roles verbatim (``:class:`X```, about
100 of them), drops the types of grouped parameters, and lists every parameter of an attrs
class as "required" with no signature — wrong information, not just cosmetics. Rewriting the
docstrings instead would touch every module; this keeps them valid for Sphinx-style tools
and for ``help()``.
"""

from __future__ import annotations

import importlib
import inspect
import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:class|func|meth|attr|mod|data|exc|obj|py:\w+):`~?\.?([^`]+)`")
_MATH_ROLE = re.compile(r":math:`([^`]+)`")
_MATH_BLOCK = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*(?P<first>.*)$")
_GROUP = re.compile(r"^(?P<names>[A-Za-z_]\w*(?:, [A-Za-z_]\w*)+)(?: : (?P<type>.+))?$")
_SECTIONS = ("Parameters", "Other Parameters", "Attributes")


def _short(match: re.Match[str]) -> str:
    text = match.group(0)
    target = match.group(1)
    if "`~" in text:
        target = target.rsplit(".", 1)[-1]
    return f"`{target}`"


def _display(lines: list[str], indent: str) -> list[str]:
    body = "\n".join(line.strip() for line in lines if line.strip())
    if "&" in body or "\\\\" in body:
        body = "\\begin{aligned}\n" + body + "\n\\end{aligned}"
    return ["", f"{indent}\\[", *(indent + line for line in body.splitlines()), f"{indent}\\]", ""]


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def split_groups(text: str) -> str:
    """In numpy parameter and attribute sections, write ``a, b : T`` as one entry per name.

    The description is repeated; a type that splits on ``", "`` into as many parts as there
    are names (``int, float``) is distributed over them.
    """
    lines = text.splitlines()
    out: list[str] = []
    section = None
    i = 0
    while i < len(lines):
        line = lines[i]
        if i + 1 < len(lines) and set(lines[i + 1].strip()) == {"-"}:
            section = line.strip()
        m = _GROUP.match(line.strip()) if section in _SECTIONS else None
        if m is None:
            out.append(line)
            i += 1
            continue
        base = _indent(line)
        body = []
        i += 1
        while i < len(lines) and (not lines[i].strip() or _indent(lines[i]) > base):
            body.append(lines[i])
            i += 1
        names = m.group("names").split(", ")
        kind = m.group("type")
        types = kind.split(", ") if kind else []
        for k, name in enumerate(names):
            typ = (types[k] if len(types) == len(names) else kind) if kind else None
            out.append(" " * base + name + (f" : {typ}" if typ else ""))
            out.extend(body)
    return "\n".join(out)


def rst_to_markdown(text: str) -> str:
    """Rewrite the reStructuredText constructs lieflow's docstrings use into Markdown."""
    lines = text.splitlines()
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = _MATH_BLOCK.match(lines[i])
        if m is None:
            line = lines[i]
            if line.rstrip().endswith("::") and not line.strip().startswith(".."):
                line = line.rstrip()[:-1]
            out.append(line)
            i += 1
            continue
        indent = m.group("indent")
        block = [m.group("first")] if m.group("first").strip() else []
        i += 1
        # the directive's content: following lines indented deeper (blank lines inside)
        while i < len(lines) and (
            not lines[i].strip() or len(lines[i]) - len(lines[i].lstrip()) > len(indent)
        ):
            if (
                not lines[i].strip()
                and block
                and (
                    i + 1 >= len(lines)
                    or len(lines[i + 1]) - len(lines[i + 1].lstrip()) <= len(indent)
                )
            ):
                break
            block.append(lines[i])
            i += 1
        out.extend(_display(block, indent))
    text = "\n".join(out)
    text = _MATH_ROLE.sub(lambda mm: f"\\({mm.group(1)}\\)", text)
    return _ROLE.sub(_short, text)


def _runtime(path: str) -> Any:
    module, _, name = path.rpartition(".")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return None


def _describe_factory(factory: Any) -> str:
    """``Name()`` for a public factory, else a description of the object it makes."""
    name = getattr(factory, "__name__", "")
    if name and not name.startswith("_"):
        return f"{name}()"
    value = factory()
    label = getattr(value, "name", None)
    return f"<{type(value).__name__} {label}>" if isinstance(label, str) else "<factory>"


def _attrs_init(cls: griffe.Class) -> griffe.Function | None:
    """The ``__init__`` attrs generated for ``cls`` (``None`` if not an attrs class)."""
    runtime = _runtime(cls.path)
    fields = getattr(runtime, "__attrs_attrs__", None)
    if fields is None:
        return None
    factories = {
        f.alias or f.name: (
            "<derived>" if f.default.takes_self else _describe_factory(f.default.factory)
        )
        for f in fields
        if getattr(f.default, "factory", None) is not None
    }
    params = [griffe.Parameter("self", kind=griffe.ParameterKind.positional_or_keyword)]
    for p in inspect.signature(runtime).parameters.values():
        if p.name in factories:
            default: str | None = factories[p.name]
        elif p.default is inspect.Parameter.empty:
            default = None
        else:
            default = repr(p.default)
        annotation = p.annotation if isinstance(p.annotation, str) else None
        params.append(
            griffe.Parameter(
                p.name,
                annotation=annotation,
                kind=griffe.ParameterKind(p.kind.description),
                default=default,
            )
        )
    return griffe.Function(
        "__init__",
        lineno=cls.lineno,
        endlineno=cls.lineno,
        parameters=griffe.Parameters(*params),
        returns="None",
    )


class LieflowDocs(griffe.Extension):
    """Markdown-ify reStructuredText in docstrings; attrs ``__init__`` signatures."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = split_groups(rst_to_markdown(obj.docstring.value))

    def on_class(self, *, cls: griffe.Class, **kwargs: Any) -> None:
        if "__init__" in cls.members:
            return
        init = _attrs_init(cls)
        if init is not None:
            cls.set_member("__init__", init)
