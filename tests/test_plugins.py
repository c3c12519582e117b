"""The plugin registry: built-ins come through the entry point, broken plugins are named."""

from __future__ import annotations

import importlib.metadata as md
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

import pytest
from helpers import needs_vortices, needs_zeitlin

import lieflow as lf
from lieflow import plugins
from lieflow.tableaus import radau_iia2


class _Plugin:
    """A plugin object whose hook calls ``register(registry)``."""

    def __init__(self, register: Callable[[lf.RegistryBuilder], object]) -> None:
        self._register = register

    @lf.hookimpl
    def lieflow_register(self, registry: lf.RegistryBuilder) -> None:
        self._register(registry)


def test_builtins_come_from_lieflow_entry_point() -> None:
    reg = lf.default_registry()
    for name in ("rigid_body", "generalized_rigid_body", "periodic_toda"):
        assert "'lieflow'" in reg.systems[name].source
    for name in (
        "midpoint",
        "sydirk7",
        "triple_jump",
        "suzuki5",
        "gauss2",
        "gauss3",
        "modin_viviani",
    ):
        assert name in reg.schemes
    assert {"fixed_point", "newton", "frozen_b", "auto"} <= set(reg.solvers)
    assert all(e.description for e in reg.schemes.values())


def test_unknown_name_lists_known_ones() -> None:
    with pytest.raises(lf.RegistryError, match=r"unknown scheme 'gauss9'.*gauss2, gauss3"):
        lf.schemes.get("gauss9")
    with pytest.raises(lf.RegistryError, match="does not accept"):
        lf.schemes.get("gauss2", colour="red")


def test_registry_is_immutable() -> None:
    reg = lf.default_registry()
    with pytest.raises(TypeError):
        reg.systems["x"] = reg.systems["rigid_body"]  # type: ignore[index]


def test_autoload_can_be_turned_off(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(plugins.DISABLE_AUTOLOAD_ENV, "1")
    reg = lf.load_registry()
    assert "rigid_body" in reg.systems and "point_vortices" not in reg.systems


def test_extra_plugin_object_registers() -> None:
    def register(registry: lf.RegistryBuilder) -> None:
        registry.add_scheme("gauss5", lambda: lf.schemes.get("gauss", stages=5), "Gauss 5")

    reg = lf.load_registry(autoload=False, plugins=[("mine", _Plugin(register))])
    assert reg.schemes["gauss5"].create().order == 10
    assert "mine" in reg.schemes["gauss5"].source


@pytest.mark.parametrize(
    ("register", "match"),
    [
        (lambda r: r.add_system("rigid_body", lf.systems.RigidBody), "already registered"),
        (lambda r: r.add_scheme("Bad Name", lf.schemes.SyDIRK), "invalid scheme name"),
        (
            lambda r: r.add_scheme("radau", lambda: lf.schemes.BlockGauss(radau_iia2())),
            "not symplectic",
        ),
        (lambda r: r.add_system("oops", lf.schemes.SyDIRK), "not a IsospectralSystem"),
        (lambda r: r.add_solver("nope", 42), "not callable"),
        (lambda r: 1 / 0, "ZeroDivisionError"),
    ],
)
def test_broken_plugin_is_named(register: object, match: str) -> None:
    with pytest.raises(lf.PluginError, match=rf"plugin 'broken' is broken: .*{match}"):
        lf.load_registry(autoload=False, plugins=[("broken", _Plugin(register))])


def test_plugin_without_hook_is_an_error() -> None:
    with pytest.raises(lf.PluginError, match="no lieflow_register"):
        lf.load_registry(autoload=False, plugins=[("empty", object())])


def test_lenient_mode_warns_and_skips(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(plugins.ERRORS_ENV, "warn")
    bad = _Plugin(lambda r: r.add_system("rigid_body", lf.systems.RigidBody))
    with pytest.warns(plugins.PluginWarning, match="already registered"):
        reg = lf.load_registry(autoload=False, plugins=[("broken", bad)])
    assert reg.systems["rigid_body"].source.startswith("entry point")


def test_entry_point_that_fails_to_import_names_its_distribution(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    real = md.entry_points

    class FakeDist:
        metadata: ClassVar[dict[str, str]] = {"Name": "lieflow-broken"}

    ep = md.EntryPoint("broken", "lieflow_no_such_module.plugin", "lieflow")
    broken = ep._for(FakeDist())  # type: ignore[attr-defined]

    def fake(**kw: object) -> list[md.EntryPoint]:
        return [*real(**kw), broken] if kw.get("group") == "lieflow" else real(**kw)

    monkeypatch.setattr(md, "entry_points", fake)
    with pytest.raises(lf.PluginError, match=r"'lieflow-broken'.*ModuleNotFoundError"):
        lf.load_registry()
    # and with autoload off, third-party entry points are not even imported
    monkeypatch.setenv(plugins.DISABLE_AUTOLOAD_ENV, "1")
    assert "rigid_body" in lf.load_registry().systems


def test_importing_lieflow_and_loading_the_plugins_leaves_heavy_scipy_modules_unloaded() -> None:
    """Start-up cost (every CLI call, pool worker and script pays it): scipy's optimize,
    sparse.linalg, special and linalg are imported where they are first used, not by
    ``import lieflow`` or by loading the plugins (0.74 s -> 0.32 s when this was done)."""
    import subprocess
    import sys

    code = (
        "import sys, lieflow as lf; lf.systems.get('rigid_body'); "
        "print(sorted(m for m in ('scipy.optimize', 'scipy.sparse.linalg', 'scipy.special', "
        "'scipy.linalg') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


_THIRD_PARTY = ("lieflow_zeitlin", "lieflow_vortices", "numba")


def _imported_after(code: str) -> dict[str, list[str]]:
    """Run ``code`` in a fresh interpreter; it prints ``loaded(label)`` lines, each the
    third-party modules imported so far."""
    import json
    import subprocess
    import sys

    prelude = (
        "import json, sys\n"
        "def loaded(label):\n"
        f"    print(json.dumps([label, [m for m in {_THIRD_PARTY!r} if m in sys.modules]]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", prelude + code], capture_output=True, text=True, check=False
    )
    assert out.returncode == 0, out.stderr
    return dict(json.loads(line) for line in out.stdout.splitlines() if line.startswith("["))


@needs_zeitlin
@needs_vortices
def test_a_builtin_system_loads_no_other_plugin(tmp_path: Path) -> None:
    """``lieflow run`` on a rigid body, and looking up a built-in, import no third-party
    plugin and no numba (161 ms of ``lieflow run`` before, issue 27); a plugin's system
    still resolves, and listing the systems loads every plugin (but not numba)."""
    config = tmp_path / "rb.toml"
    config.write_text(
        '[system]\nname = "rigid_body"\n[initial]\nrandom = true\nseed = 0\n'
        '[scheme]\nname = "midpoint"\n'
        '[run]\nh = 0.1\nsteps = 3\noutput = "rb.h5"\n',
        encoding="utf-8",
    )
    seen = _imported_after(
        "import lieflow as lf\n"
        "from lieflow.app.cli import main\n"
        f"assert main(['run', '--no-progress', {str(config)!r}]) == 0\n"
        "loaded('run')\n"
        "for kind, name in [('system', 'periodic_toda'), ('scheme', 'gauss3'),\n"
        "                   ('solver', 'newton')]:\n"
        "    lf.default_registry().create(kind, name)\n"
        "assert 'rigid_body' in lf.default_registry().systems\n"
        "assert lf.default_registry().sinks.get('.h5') is not None\n"
        "body = lf.systems.get('rigid_body')\n"
        "lf.integrate(body, lf.schemes.get('midpoint'), body.random_state(0), 0.1, steps=2,\n"
        f"             out={str(tmp_path / 'integrate.h5')!r})\n"
        "loaded('builtins')\n"
        "system = lf.systems.get('euler_zeitlin', N=8)\n"
        "assert type(system).__module__.startswith('lieflow_zeitlin')\n"
        "loaded('zeitlin')\n"
    )
    assert seen["run"] == [] and seen["builtins"] == []
    assert "lieflow_zeitlin" in seen["zeitlin"]
    listed = _imported_after("import lieflow as lf\nlf.systems.available()\nloaded('names')\n")
    assert {"lieflow_zeitlin", "lieflow_vortices"} <= set(listed["names"])
    # the fluids plugin compiles its kernels at their first use, not when it is imported
    assert "numba" not in listed["names"]


class _Recorder:
    """A plugin that records that it was loaded, registering ``names`` as systems."""

    def __init__(self, *names: str) -> None:
        self.names = names
        self.loaded = False

    @lf.hookimpl
    def lieflow_register(self, registry: lf.RegistryBuilder) -> None:
        self.loaded = True
        for name in self.names:
            registry.add_system(name, lf.systems.PeriodicToda)


def test_lazy_registry_loads_other_plugins_only_for_names_not_lieflows() -> None:
    mine = _Recorder("chain")
    reg = lf.load_registry(autoload=False, plugins=[("mine", mine)], lazy=True)
    assert isinstance(reg.create("system", "rigid_body"), lf.systems.RigidBody)
    assert "midpoint" in reg.schemes and not mine.loaded
    # a search that stops at a built-in loads nothing more
    assert next(n for n, e in reg.systems.items() if e.factory is lf.systems.RigidBody)
    assert not mine.loaded
    assert "chain" in reg.systems and mine.loaded
    assert "mine" in reg.systems["chain"].source


def test_lazy_registry_lists_every_plugin() -> None:
    mine = _Recorder("chain")
    reg = lf.load_registry(autoload=False, plugins=[("mine", mine)], lazy=True)
    assert "chain" in sorted(reg.systems) and mine.loaded
    eager = lf.load_registry(autoload=False, plugins=[("mine", _Recorder("chain"))])
    for kind in plugins.KINDS:
        assert list(reg.table(kind)) == list(eager.table(kind))


@pytest.mark.parametrize("first", ["alpha", "omega"])
def test_a_name_two_plugins_register_is_reported_whatever_their_order(first: str) -> None:
    """Lazily, all third-party plugins load together: the duplicate is found, never resolved
    to whichever plugin happened to load first."""
    second = "omega" if first == "alpha" else "alpha"
    plugins = [(first, _Recorder("chain", f"{first}_only")), (second, _Recorder("chain"))]
    reg = lf.load_registry(autoload=False, plugins=plugins, lazy=True)
    for name in ("chain", f"{first}_only"):
        with pytest.raises(lf.PluginError, match=rf"'{second}' is broken: .*'chain'.*{first}"):
            reg.entry("system", name)
    with pytest.raises(lf.PluginError, match="already registered"):
        sorted(reg.systems)
    assert isinstance(
        reg.create("system", "rigid_body"), lf.systems.RigidBody
    )  # built-ins unaffected


def test_a_plugin_that_registers_a_builtin_name_is_broken_when_it_loads() -> None:
    """A built-in name is lieflow's: looking it up never loads another plugin, and the
    plugin that registers it too is reported as soon as anything loads it."""
    reg = lf.load_registry(autoload=False, plugins=[("thief", _Recorder("rigid_body", "x"))],
                           lazy=True)  # fmt: skip
    assert "'lieflow'" in reg.systems["rigid_body"].source
    with pytest.raises(lf.PluginError, match=r"'thief' is broken: .*'rigid_body'.*already"):
        reg.systems.get("x")
    assert "'lieflow'" in reg.systems["rigid_body"].source


def test_lazy_registry_warns_about_a_broken_plugin_when_it_loads(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv(plugins.ERRORS_ENV, "warn")
    plugs = [("broken", _Plugin(lambda r: 1 / 0)), ("fine", _Recorder("chain"))]
    reg = lf.load_registry(autoload=False, plugins=plugs, lazy=True)
    with pytest.warns(plugins.PluginWarning, match="'broken' is broken: ZeroDivisionError"):
        assert "fine" in reg.systems["chain"].source


def _private_lieflow_uses(source: str) -> list[str]:
    """Every private lieflow name a module's source reaches: an imported module or name
    with a part starting with ``_`` under ``lieflow`` (``lieflow.engines._compiled_loops``,
    ``from lieflow.x import _y``), or such an attribute of an imported ``lieflow`` module
    (``lieflow.engines._compiled_loops.f``)."""
    import ast

    def private(dotted: str) -> bool:
        parts = dotted.split(".")
        return parts[0] == "lieflow" and any(p.startswith("_") for p in parts[1:])

    found: list[str] = []
    aliases: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            for a in node.names:
                if private(a.name):
                    found.append(a.name)
                if a.name.split(".")[0] == "lieflow":
                    aliases.add(a.asname or "lieflow")
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for a in node.names:
                if private(f"{node.module}.{a.name}"):
                    found.append(f"{node.module}.{a.name}")
                if node.module.split(".")[0] == "lieflow" and not a.name.startswith("_"):
                    aliases.add(a.asname or a.name)
    for node in ast.walk(ast.parse(source)):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
        ):
            base = node.value
            while isinstance(base, ast.Attribute):
                base = base.value
            if isinstance(base, ast.Name) and base.id in aliases:
                found.append(f"{ast.unparse(node)}")
    return found


def test_the_plugins_use_only_public_lieflow_names() -> None:
    """The plugins in plugins/ are written as a third party would: no private lieflow
    module or name (their compiled B uses :mod:`lieflow.engines.compiled`'s public maps)."""

    root = Path(__file__).resolve().parents[1] / "plugins"
    # the plugins' code (their tests, under plugins/*/tests, may look inside lieflow)
    files = sorted(f for f in root.glob("*/**/*.py") if "tests" not in f.relative_to(root).parts)
    assert len(files) > 10
    uses = {
        str(f.relative_to(root)): _private_lieflow_uses(f.read_text(encoding="utf-8"))
        for f in files
    }
    assert {k: v for k, v in uses.items() if v} == {}
    # the checker finds each form
    assert _private_lieflow_uses(
        "from lieflow.engines._compiled_loops import skew_hermitian_part"
    ) == ["lieflow.engines._compiled_loops.skew_hermitian_part"]
    assert _private_lieflow_uses("import lieflow.engines._compiled_loops as k") == [
        "lieflow.engines._compiled_loops"
    ]
    assert _private_lieflow_uses("from lieflow.flows import _combine") == ["lieflow.flows._combine"]
    assert _private_lieflow_uses("import lieflow as lf\nlf._kernels.gemm") == ["lf._kernels"]
    assert _private_lieflow_uses("from lieflow.engines import compiled\ncompiled._F") == [
        "compiled._F"
    ]
