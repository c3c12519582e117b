"""Plugins: the pluggy hook specification and the registry of systems, schemes and solvers.

Every provider — lieflow's own built-ins included — is a distribution that declares an entry
point in the group ``lieflow`` pointing at a module (or object) with a hook implementation::

    # pyproject.toml of a plugin
    [project.entry-points.lieflow]
    vortices = "lieflow_vortices.plugin"

    # lieflow_vortices/plugin.py
    import lieflow
    @lieflow.hookimpl
    def lieflow_register(registry):
        registry.add_system("point_vortices", PointVortices, "N point vortices on the sphere")

A plugin may also register *flows* — sub-steps such as dissipation or forcing that
``lieflow run`` composes with the scheme (``[splitting]``) — with
``registry.add_flow("viscosity", Viscosity)``: the factory is called as
``factory(system=system, **params)`` and must return a :class:`~lieflow.flows.Flow`.

A plugin may also register a *sink* — where a run's steps go — for a file suffix,
``registry.add_sink(".h5", factory)``: ``integrate(..., out="run.h5")`` opens it as
``factory(path, run, resume=..., replace=...)`` (:func:`lieflow.sinks.open_sink`). The
application's HDF5 trajectory writer is registered this way, by its own entry point
(``app = "lieflow.app.plugin"``), so the core never imports the application.

A plugin may also register extra ``lieflow plot`` figures for trajectory files of a system,
``registry.add_plotter("euler_zeitlin", plot_run)`` with ``plot_run(trajectory, out_dir,
stem) -> list of PNG paths`` (see :class:`Plotter`).

Each entry point is loaded and called inside a guard: a plugin that fails to import, whose
hook raises, or that registers something invalid (a duplicate name, a class of the wrong
kind, a scheme on a non-symplectic tableau) yields a :class:`~lieflow.errors.PluginError`
naming the distribution and the reason. Environment variables:

``LIEFLOW_DISABLE_PLUGIN_AUTOLOAD=1``
    load only lieflow's own entry points (third-party plugins are skipped);
``LIEFLOW_PLUGIN_ERRORS=warn``
    a broken plugin is skipped with a :class:`PluginWarning` instead of raising.
"""

from __future__ import annotations

import functools
import importlib.metadata as md
import inspect
import os
import re
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any, Literal

import attrs
import pluggy

from .errors import InputError, LieflowError, PluginError, RegistryError, quote, shorten

PROJECT = "lieflow"
ENTRY_POINT_GROUP = "lieflow"
DISABLE_AUTOLOAD_ENV = "LIEFLOW_DISABLE_PLUGIN_AUTOLOAD"
ERRORS_ENV = "LIEFLOW_PLUGIN_ERRORS"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

Kind = Literal["system", "scheme", "solver", "flow"]
KINDS: tuple[Kind, ...] = ("system", "scheme", "solver", "flow")
_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


class PluginWarning(UserWarning):
    """A broken plugin was skipped (``LIEFLOW_PLUGIN_ERRORS=warn``)."""


class HookSpecs:
    """The hooks a lieflow plugin may implement."""

    @hookspec
    def lieflow_register(self, registry: RegistryBuilder) -> None:
        """Register systems, schemes and solvers by calling ``registry.add_system(...)``,
        ``registry.add_scheme(...)`` and ``registry.add_solver(...)`` (and, optionally,
        flows, file sinks and ``lieflow plot`` figures with ``registry.add_flow(...)``,
        ``registry.add_sink(...)`` and ``registry.add_plotter(...)``)."""


#: ``plotter(trajectory, out_dir, stem) -> paths``: extra PNGs of ``lieflow plot`` for a system.
PlotFunction = Callable[[Any, Path, str], Sequence[Path]]


@attrs.frozen
class Entry:
    """One registered name: what it makes and who provided it."""

    kind: Kind
    name: str
    factory: Callable[..., Any] = attrs.field(repr=False)
    description: str
    source: str

    def create(self, **params: Any) -> Any:
        """Call the factory with ``params`` and check what it made.

        Raises
        ------
        RegistryError
            The factory does not accept ``params``.
        PluginError
            The factory returned something that is not a :attr:`kind` (a plugin bug; a
            factory that needs parameters cannot be checked when the plugin loads).
        """
        try:
            obj = self.factory(**params)
        except LieflowError:
            raise
        except TypeError as exc:
            sig = _signature(self.factory)
            raise RegistryError(
                f"{self.kind} {self.name!r} does not accept {sorted(params)}: {exc}. "
                f"Its parameters are {sig}"
            ) from exc
        except (ValueError, ArithmeticError, LookupError, AttributeError) as exc:
            raise InputError(
                f"{self.kind} {self.name!r} rejected its parameters {quote(params)}: "
                f"{type(exc).__name__}: {shorten(exc)}. To fix: check their values; its "
                f"parameters are {_signature(self.factory)}"
            ) from exc
        problem = _check_kind(self.kind, obj)
        if problem:
            raise PluginError(
                f"{self.kind} {self.name!r} (registered by {self.source}) is broken: {problem}. "
                "To fix: correct that plugin's factory, or uninstall its distribution"
            )
        return obj


def _signature(factory: Callable[..., Any]) -> str:
    try:
        return str(inspect.signature(factory))
    except (TypeError, ValueError):
        return "(unknown)"


def _check_kind(kind: Kind, obj: Any) -> str | None:
    """Why ``obj`` is not a valid ``kind`` (or ``None`` if it is)."""
    from .flows import Flow
    from .schemes.base import Scheme
    from .solvers.base import Solver
    from .systems.base import IsospectralSystem

    expected: type = {
        "system": IsospectralSystem,
        "scheme": Scheme,
        "solver": Solver,
        "flow": Flow,
    }[kind]
    return (
        None
        if isinstance(obj, expected)
        else (f"its factory made a {type(obj).__name__}, not a {expected.__name__}")
    )


@attrs.frozen
class Plotter:
    """Extra figures that ``lieflow plot`` draws for trajectory files of one system.

    ``function(trajectory, out_dir, stem)`` receives the file's
    :class:`~lieflow.app.io.Trajectory`, the output directory and the file's stem, writes PNGs
    (conventionally ``out_dir / f"{stem}_<what>.png"``) and returns their paths.
    """

    system: str
    function: PlotFunction = attrs.field(repr=False)
    description: str
    source: str


@attrs.frozen
class SinkFormat:
    """A file format a run can be written to: ``factory(path, run, resume=..., replace=...)``
    returns a :class:`~lieflow.sinks.Sink` for files named ``*<suffix>``."""

    suffix: str
    factory: Callable[..., Any] = attrs.field(repr=False)
    description: str
    source: str


_SUFFIX = re.compile(r"^\.[a-z0-9][a-z0-9_.-]*$")


class RegistryBuilder:
    """Collects registrations while plugins load (handed to ``lieflow_register``)."""

    def __init__(self) -> None:
        self._entries: dict[Kind, dict[str, Entry]] = {k: {} for k in KINDS}
        self._plotters: dict[str, Plotter] = {}
        self._sinks: dict[str, SinkFormat] = {}
        self._source = "?"
        self._pending: list[Entry] = []
        self._pending_plotters: list[Plotter] = []
        self._pending_sinks: list[SinkFormat] = []

    def add_system(self, name: str, factory: Callable[..., Any], description: str = "") -> None:
        """Register an :class:`~lieflow.IsospectralSystem` subclass or factory."""
        self._add("system", name, factory, description)

    def add_scheme(self, name: str, factory: Callable[..., Any], description: str = "") -> None:
        """Register a :class:`~lieflow.Scheme` subclass or factory."""
        self._add("scheme", name, factory, description)

    def add_solver(self, name: str, factory: Callable[..., Any], description: str = "") -> None:
        """Register a :class:`~lieflow.solvers.Solver` class or factory."""
        self._add("solver", name, factory, description)

    def add_flow(self, name: str, factory: Callable[..., Any], description: str = "") -> None:
        """Register a :class:`~lieflow.flows.Flow` factory, called as
        ``factory(system=system, **params)`` (a sub-step for ``[splitting]``)."""
        self._add("flow", name, factory, description)

    def add_plotter(self, system: str, function: PlotFunction, description: str = "") -> None:
        """Register extra ``lieflow plot`` figures for trajectory files of ``system``.

        ``function(trajectory, out_dir, stem)`` returns the paths of the PNGs it wrote (see
        :class:`Plotter`); it runs after the generic figures. The system may come from any
        plugin; at most one plotter per system name.
        """
        if not isinstance(system, str) or not _NAME.match(system):
            raise PluginError(
                f"invalid system name {system!r} for a plotter: use lower-case letters, "
                "digits and underscores"
            )
        if not callable(function):
            raise PluginError(f"plotter for {system!r}: {function!r} is not callable")
        taken = self._plotters.get(system) or next(
            (p for p in self._pending_plotters if p.system == system), None
        )
        if taken is not None:
            raise PluginError(f"a plotter for {system!r} is already registered by {taken.source}")
        doc = description or (inspect.getdoc(function) or "").split("\n")[0]
        self._pending_plotters.append(Plotter(system, function, doc, self._source))

    def add_sink(self, suffix: str, factory: Callable[..., Any], description: str = "") -> None:
        """Register the :class:`~lieflow.sinks.Sink` that writes files named ``*<suffix>``
        (lower case, with its dot: ``".h5"``): ``factory(path, run, resume=..., replace=...)``
        with ``run`` a :class:`~lieflow.sinks.RunInfo`; with ``resume`` the sink continues an
        existing file and its ``start`` attribute is where (a
        :class:`~lieflow.sinks.ResumePoint`, ``None`` for a new file). At most one sink per
        suffix."""
        if not isinstance(suffix, str) or not _SUFFIX.match(suffix):
            raise PluginError(
                f"invalid sink suffix {suffix!r}: a dot, then lower-case letters, digits, '_', "
                "'-' or '.' (e.g. '.h5')"
            )
        if not callable(factory):
            raise PluginError(f"sink {suffix!r}: the factory {factory!r} is not callable")
        taken = self._sinks.get(suffix) or next(
            (e for e in self._pending_sinks if e.suffix == suffix), None
        )
        if taken is not None:
            raise PluginError(
                f"a sink for {suffix!r} files is already registered by {taken.source}"
            )
        doc = description or (inspect.getdoc(factory) or "").split("\n")[0]
        self._pending_sinks.append(SinkFormat(suffix, factory, doc, self._source))

    def _add(self, kind: Kind, name: str, factory: Callable[..., Any], description: str) -> None:
        if not isinstance(name, str) or not _NAME.match(name):
            raise PluginError(
                f"invalid {kind} name {name!r}: use lower-case letters, digits and underscores"
            )
        if not callable(factory):
            raise PluginError(f"{kind} {name!r}: the factory {factory!r} is not callable")
        taken = self._entries[kind].get(name) or next(
            (e for e in self._pending if e.kind == kind and e.name == name), None
        )
        if taken is not None:
            raise PluginError(f"{kind} name {name!r} is already registered by {taken.source}")
        self._validate(kind, name, factory)
        doc = description or (inspect.getdoc(factory) or "").split("\n")[0]
        self._pending.append(Entry(kind, name, factory, doc, self._source))

    @staticmethod
    def _validate(kind: Kind, name: str, factory: Callable[..., Any]) -> None:
        """Instantiate with defaults where possible: catches wrong kinds and bad tableaus."""
        try:
            params = inspect.signature(factory).parameters.values()
        except (TypeError, ValueError):
            return
        required = [
            p
            for p in params
            if p.default is p.empty and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        if required:
            return
        try:
            obj = factory()
        except Exception as exc:
            raise PluginError(
                f"{kind} {name!r} cannot be created with its defaults: {exc}"
            ) from exc
        problem = _check_kind(kind, obj)
        if problem:
            raise PluginError(f"{kind} {name!r} is invalid: {problem}")

    def _commit(self) -> None:
        for e in self._pending:
            self._entries[e.kind][e.name] = e
        for p in self._pending_plotters:
            self._plotters[p.system] = p
        for k in self._pending_sinks:
            self._sinks[k.suffix] = k
        self._discard()

    def _discard(self) -> None:
        self._pending = []
        self._pending_plotters = []
        self._pending_sinks = []

    def freeze(self) -> Registry:
        """The immutable registry."""
        tables = {f"{k}s": MappingProxyType(dict(v)) for k, v in self._entries.items()}
        return Registry(**tables, plotters=MappingProxyType(dict(self._plotters)),
                        sinks=MappingProxyType(dict(self._sinks)))  # fmt: skip


@attrs.frozen
class Registry:
    """Immutable name -> :class:`Entry` tables for systems, schemes, solvers and flows, the
    system name -> :class:`Plotter` table of extra ``lieflow plot`` figures, and the
    suffix -> :class:`SinkFormat` table of file formats."""

    systems: Mapping[str, Entry]
    schemes: Mapping[str, Entry]
    solvers: Mapping[str, Entry]
    flows: Mapping[str, Entry] = attrs.field(factory=lambda: MappingProxyType({}))
    plotters: Mapping[str, Plotter] = attrs.field(factory=lambda: MappingProxyType({}))
    sinks: Mapping[str, SinkFormat] = attrs.field(factory=lambda: MappingProxyType({}))

    def table(self, kind: Kind) -> Mapping[str, Entry]:
        """The entries of one kind."""
        if kind not in KINDS:
            raise RegistryError(f"unknown kind {kind!r}; use one of {KINDS}")
        return getattr(self, f"{kind}s")

    def entry(self, kind: Kind, name: str) -> Entry:
        """Look a name up, or raise :class:`RegistryError` listing the known names."""
        table = self.table(kind)
        try:
            return table[name]
        except (KeyError, TypeError):
            known = ", ".join(sorted(table)) or "(none)"
            raise RegistryError(
                f"unknown {kind} {name!r}. Known {kind}s: {known}. A {kind} from a plugin "
                "appears here once its distribution is installed"
            ) from None

    def create(self, kind: Kind, name: str, **params: Any) -> Any:
        """Look ``name`` up and build it with ``params``."""
        return self.entry(kind, name).create(**params)


def _plugin_entry_points(autoload: bool) -> list[md.EntryPoint]:
    eps = list(md.entry_points(group=ENTRY_POINT_GROUP))
    if not autoload:
        eps = [ep for ep in eps if _dist_name(ep) == PROJECT]
    # one distribution can appear twice on sys.path (e.g. an editable and a regular install)
    unique = {(_dist_name(ep), ep.name, ep.value): ep for ep in eps}
    return sorted(unique.values(), key=lambda ep: (_dist_name(ep) != PROJECT, ep.name))


def _constant(obj: object) -> Callable[[], object]:
    return lambda: obj


def _dist_name(ep: md.EntryPoint) -> str:
    dist = getattr(ep, "dist", None)
    return str(dist.metadata["Name"]) if dist is not None else "unknown distribution"


def load_registry(
    *,
    autoload: bool | None = None,
    plugins: Iterable[tuple[str, object]] = (),
    errors: Literal["raise", "warn"] | None = None,
) -> Registry:
    """Load every plugin and return the frozen :class:`Registry`.

    Parameters
    ----------
    autoload : bool, optional
        Load third-party entry points too (default: unless ``LIEFLOW_DISABLE_PLUGIN_AUTOLOAD``
        is set). lieflow's own entry point is always loaded.
    plugins : iterable of (name, object)
        Extra plugin objects (modules or instances with a ``lieflow_register`` hookimpl), e.g.
        for tests; they are guarded like entry points.
    errors : {"raise", "warn"}, optional
        What to do with a broken plugin (default: ``LIEFLOW_PLUGIN_ERRORS`` or ``"raise"``).
    """
    if autoload is None:
        autoload = not os.environ.get(DISABLE_AUTOLOAD_ENV)
    if errors is None:
        errors = "warn" if os.environ.get(ERRORS_ENV, "").lower() == "warn" else "raise"
    pm = pluggy.PluginManager(PROJECT)
    pm.add_hookspecs(HookSpecs)
    builder = RegistryBuilder()

    candidates: list[tuple[str, Callable[[], object]]] = [
        (f"entry point {ep.name!r} of distribution {_dist_name(ep)!r}", ep.load)
        for ep in _plugin_entry_points(autoload)
    ]
    candidates += [(f"plugin {name!r}", _constant(obj)) for name, obj in plugins]
    for label, load in candidates:
        builder._source = label
        plugin: object | None = None
        try:
            plugin = load()
            pm.register(plugin, name=label)
            others = [p for p in pm.get_plugins() if p is not plugin]
            if not any(i.plugin is plugin for i in pm.hook.lieflow_register.get_hookimpls()):
                raise PluginError("it has no lieflow_register hook implementation")
            pm.subset_hook_caller("lieflow_register", remove_plugins=others)(registry=builder)
            builder._commit()
        except Exception as exc:
            builder._discard()
            if plugin is not None and pm.is_registered(plugin):
                pm.unregister(plugin)
            reason = str(exc) if isinstance(exc, PluginError) else f"{type(exc).__name__}: {exc}"
            message = (
                f"lieflow {label} is broken: {reason}. Fix or uninstall that distribution, "
                f"or set {DISABLE_AUTOLOAD_ENV}=1 to skip third-party plugins"
            )
            if errors == "warn":
                warnings.warn(message, PluginWarning, stacklevel=2)
            else:
                raise PluginError(message) from exc
    return builder.freeze()


@functools.cache
def default_registry() -> Registry:
    """The registry of the installed plugins, loaded once (it is immutable)."""
    return load_registry()
