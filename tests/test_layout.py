"""The package layout of issue 16: the numerical core apart from the application on it."""

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
    "progress",
    "reproduce",
    "salvage",
    "sweeps",
}


def _module_level_imports(path: Path) -> list[str]:
    """The modules a file imports outside any function (relative names kept as written)."""
    names = []
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            names += [base] + [f"{base}.{a.name}".replace("..", ".") for a in node.names]
        elif isinstance(node, ast.Import):
            names += [a.name for a in node.names]
    return names


def test_the_application_lives_in_lieflow_app() -> None:
    assert {p.stem for p in (PACKAGE / "app").glob("*.py")} == APP_MODULES | {"__init__"}
    assert not [m for m in APP_MODULES if (PACKAGE / f"{m}.py").exists()]


def test_core_modules_do_not_import_the_application_at_module_level() -> None:
    offenders = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE)
        if rel.parts[0] == "app" or str(rel) in ("__init__.py", "__main__.py"):
            continue  # re-exports of the user-facing names, and `python -m lieflow`
        hits = [n for n in _module_level_imports(path) if "app" in n.split(".")]
        if hits:
            offenders[str(rel)] = hits
    assert offenders == {}


def test_documented_top_level_names_and_the_command() -> None:
    for name in ("integrate", "open_run", "open_sweep", "sweep", "load_sweep", "parse_sweep"):
        assert callable(getattr(lf, name))
    out = subprocess.run(
        [sys.executable, "-m", "lieflow", "--version"], capture_output=True, text=True, check=True
    )
    assert lf.__version__ in out.stdout
