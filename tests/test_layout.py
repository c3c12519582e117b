"""The package layout: the numerical core below the application on it, with no arrow back up
and no import circle (issues 16 and 26)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import lieflow as lf

PACKAGE = Path(lf.__file__).resolve().parent
APP_MODULES = {
    "cli",
    "config",
    "datasets",
    "io",
    "plotting",
    "plugin",
    "reports",
    "reproduce",
    "salvage",
    "studies",
    "sweeps",
    "zarr_sink",
}


def _module_name(path: Path) -> str:
    parts = ["lieflow", *path.relative_to(PACKAGE).with_suffix("").parts]
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    """Whether ``name`` is a module (or package) of lieflow, as a file in the package."""
    path = PACKAGE.parent.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _imports(
    path: Path, *, anywhere: bool, module: str | None = None, typing: bool = True
) -> list[str]:
    """Absolute names of the modules (or module attributes) a file imports: at module level,
    or ``anywhere`` (inside functions too, and ``importlib.import_module("...")`` strings);
    with ``typing``, those under ``if TYPE_CHECKING:`` too (read by type checkers only).
    ``module``: the file's module name (by default from its place in the package)."""
    module = module or _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    tree = ast.parse(path.read_text())
    nodes = ast.walk(tree) if anywhere else tree.body
    unrun = set() if typing else {
        id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
        and "TYPE_CHECKING" in ast.unparse(block.test)
        for stmt in block.body for n in ast.walk(stmt)
    }  # fmt: skip
    names: list[str] = []
    for node in nodes:
        if id(node) in unrun:
            continue
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                root = ".".join([*base, *([node.module] if node.module else [])])
            else:
                root = node.module or ""
            members = [f"{root}.{a.name}" for a in node.names]
            # ``from package import submodule`` reads no name of the package's __init__
            names += ([] if all(map(_is_module, members)) else [root]) + members
        elif isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif (
            anywhere
            and isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            names.append(node.args[0].value)
    return names


def _core_files() -> list[Path]:
    """Every module of the core: ``lieflow`` minus ``lieflow.app``, ``__init__`` (lazy
    re-exports) and ``__main__`` (``python -m lieflow`` runs the command line)."""
    return [
        p
        for p in PACKAGE.rglob("*.py")
        if p.relative_to(PACKAGE).parts[0] != "app"
        and str(p.relative_to(PACKAGE)) not in ("__init__.py", "__main__.py")
    ]


def test_the_application_lives_in_lieflow_app() -> None:
    """Its modules and packages (``io``: one module per concern) are in lieflow.app only."""
    app = PACKAGE / "app"
    found = {p.stem for p in app.glob("*.py")} | {p.parent.name for p in app.glob("*/__init__.py")}
    assert found == APP_MODULES | {"__init__"}
    assert not [
        m
        for m in APP_MODULES - {"plugin"}
        if (PACKAGE / f"{m}.py").exists() or (PACKAGE / m).is_dir()
    ]


def test_core_modules_never_import_the_application() -> None:
    """Not at module level, not inside a function, not by ``import_module``."""
    offenders = {}
    for path in _core_files():
        hits = [n for n in _imports(path, anywhere=True) if n.startswith("lieflow.app")]
        if hits:
            offenders[_module_name(path)] = hits
    assert offenders == {}


def test_the_scan_finds_lazy_imports_of_the_application(tmp_path: Path) -> None:
    """The scan above can fail: an import inside a function, relative or absolute, and an
    ``import_module`` string are all seen."""
    probe = tmp_path / "probe.py"
    probe.write_text(
        "import importlib\n\n"
        "def f():\n    from .app import io\n\n"
        "def g():\n    import lieflow.app.sweeps\n\n"
        "def h():\n    return importlib.import_module('lieflow.app.datasets')\n"
    )
    found = [n for n in _imports(probe, anywhere=True, module="lieflow.probe")
             if n.startswith("lieflow.app")]  # fmt: skip
    assert {"lieflow.app.io", "lieflow.app.sweeps", "lieflow.app.datasets"} <= set(found)
    assert _imports(probe, anywhere=False, module="lieflow.probe") == ["importlib"]


def test_import_lieflow_loads_no_application_module() -> None:
    code = "import sys, lieflow; print([m for m in sys.modules if m.startswith('lieflow.app')])"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def _circle(paths: list[Path], *, anywhere: bool, typing: bool = True) -> list[str]:
    """A circle in the graph of imports between the modules of ``paths`` (module-level, or
    ``anywhere``: inside functions too; ``typing``: ``TYPE_CHECKING`` blocks too), ``[]`` if
    there is none."""
    modules = {_module_name(p): p for p in paths}

    def ancestors(name: str) -> set[str]:
        parts = name.split(".")
        return {".".join(parts[:i]) for i in range(1, len(parts))}

    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        edges = set()
        for m in _imports(path, anywhere=anywhere, typing=typing):
            # importing a.b.c runs the __init__ of a and a.b first: edges too, except to the
            # importer's own packages (they are being imported already: the package's
            # modules import each other, not the package, unless they name it)
            edges |= {m} | (ancestors(m) - ancestors(name))
        graph[name] = {m for m in edges if m in modules and m != name}
    state: dict[str, int] = {}
    cycle: list[str] = []

    def visit(node: str, stack: list[str]) -> bool:
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle.extend([*stack[stack.index(nxt) :], nxt] if nxt in stack else [node, nxt])
                return True
            if nxt not in state and visit(nxt, [*stack, nxt]):
                return True
        state[node] = 2
        return False

    for start in sorted(graph):
        if start not in state and visit(start, [start]):
            break
    return cycle


def test_the_package_has_no_import_circle_even_inside_functions() -> None:
    """Issue 36: the graph of imports between lieflow's modules — core and application, at
    module level and inside functions (``TYPE_CHECKING`` blocks aside: the top-level package
    names the application's functions it loads lazily for type checkers), a package's
    ``__init__`` counted wherever one of its modules is imported — is acyclic. The
    application's layers import downwards only: ``config`` (a TOML file parsed and checked,
    then built into a run) -> ``io`` (file headers, writer, reader; running a configuration
    into a file) -> ``salvage``; ``datasets`` and ``zarr_sink`` (the results' formats and
    readers) -> ``sweeps`` -> ``reports`` -> ``studies`` -> ``reproduce`` -> ``plotting``,
    ``cli``."""
    assert _circle(list(PACKAGE.rglob("*.py")), anywhere=True, typing=False) == []


def test_the_core_has_no_import_circle_even_inside_functions() -> None:
    """Issue 36: the core's layers — errors, algebras, tableaus, backends; systems, schemes,
    solvers; flows, warm starts; engines; stepping; sinks, solution; integration — import
    downwards only, at module level, inside functions and in ``TYPE_CHECKING`` blocks (the
    stepping loop defines the ``Sink`` protocol its loop feeds; the registry checks what it holds
    by shape, systems name lieflow's compiled maps instead of importing the engine)."""
    assert _circle(_core_files(), anywhere=True) == []


def test_the_circle_scan_finds_a_circle_inside_functions(tmp_path: Path) -> None:
    """The scan can fail: two modules that import each other inside functions."""
    (tmp_path / "a.py").write_text("def f():\n    from . import b\n")
    (tmp_path / "b.py").write_text("def g():\n    from . import a\n")
    graph = {name: _imports(tmp_path / f"{name}.py", anywhere=True, module=f"lieflow.{name}")
             for name in ("a", "b")}  # fmt: skip
    assert "lieflow.b" in graph["a"] and "lieflow.a" in graph["b"]


def test_the_application_reaches_the_core_through_the_registry() -> None:
    """``integrate(out="x.h5")`` finds the HDF5 writer as a registered sink."""
    sinks = lf.default_registry().sinks
    assert ".h5" in sinks and "'app'" in sinks[".h5"].source


def test_documented_top_level_names_and_the_command() -> None:
    for name in ("integrate", "iterate", "open_run", "open_sweep", "sweep", "load_sweep",
                 "parse_sweep", "Solution", "MemorySink", "Sink"):  # fmt: skip
        assert callable(getattr(lf, name))
    out = subprocess.run(
        [sys.executable, "-m", "lieflow", "--version"], capture_output=True, text=True, check=True
    )
    assert lf.__version__ in out.stdout


TESTS = Path(__file__).resolve().parent
#: The plugins of this repository as modules (plugins/lieflow-zeitlin: lieflow_zeitlin).
PLUGIN_MODULES = {
    p.name.replace("-", "_")
    for p in TESTS.parent.glob("plugins/*")
    if (p / "pyproject.toml").is_file()
}


def _plugin_imports_on_import(path: Path) -> list[str]:
    """``line: code`` of each import of a plugin module run when the file is imported (outside
    a function): an import statement, ``pytest.importorskip`` or ``import_module``."""
    found: list[str] = []

    def visit(node: ast.AST) -> None:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            return  # runs when called, not on import
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [node.module or ""] if not node.level else []
        elif (
            isinstance(node, ast.Call)
            and getattr(node.func, "attr", getattr(node.func, "id", ""))
            in ("importorskip", "import_module")
            and node.args
            and isinstance(node.args[0], ast.Constant)
        ):
            names = [str(node.args[0].value)]
        else:
            names = []
        if any(name.split(".")[0] in PLUGIN_MODULES for name in names):
            found.append(f"{node.lineno}: {ast.unparse(node)}")  # type: ignore[attr-defined]
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(path.read_text(encoding="utf-8")))
    return found


def test_the_core_tests_import_no_plugin_on_import() -> None:
    """The core's tests collect and run without the plugins (pip install -e ".[test]"): a
    test that needs one imports it inside the test and carries the mark of tests/helpers.py
    (``needs_zeitlin``, ``needs_vortices``, ``plugin_marks``); a test of a plugin itself
    lives in its plugins/*/tests."""
    assert PLUGIN_MODULES == {"lieflow_zeitlin", "lieflow_vortices"}
    offenders = {p.name: hits for p in TESTS.glob("*.py") if (hits := _plugin_imports_on_import(p))}
    assert offenders == {}


def test_the_plugin_import_scan_finds_them(tmp_path: Path) -> None:
    """The scan above can fail: module-level imports, also under ``if``/``try`` and in a
    class body, and ``importorskip`` are seen; imports inside functions are not."""
    probe = tmp_path / "test_probe.py"
    probe.write_text(
        "import pytest\n"
        "import lieflow_zeitlin\n"
        "from lieflow_vortices._compiled import vortex_B\n"
        "lz = pytest.importorskip('lieflow_zeitlin')\n"
        "try:\n    import lieflow_vortices as lv\nexcept ImportError:\n    pass\n"
        "class T:\n    import lieflow_zeitlin.plotting\n"
        "def test_f():\n    import lieflow_zeitlin\n    pytest.importorskip('lieflow_vortices')\n"
        "import lieflow.systems\n"
    )
    assert [hit.split(":")[0] for hit in _plugin_imports_on_import(probe)] == [
        "2", "3", "4", "6", "10"
    ]  # fmt: skip
