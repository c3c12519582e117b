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

Plugins are loaded when a name is first looked up, and no more of them than the name needs:
lieflow's own entry points (the built-ins, the application's file sink) first, every other
plugin only when the name is not one of lieflow's own, or when a whole table is listed
(``lieflow list``, :func:`lieflow.systems.available`): ``lieflow run`` on a rigid body
imports no third-party plugin (see :func:`load_registry`, ``lazy``). A name that lieflow
registers is lieflow's; the other plugins are all loaded together, so that a name two of
them register is reported whichever is asked for, whatever their order.

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
import threading
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
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


#: What each kind of registered object must have (checked by shape, not by class: the
#: registry sits below the packages whose objects it holds and imports none of them; the
#: callers that need a class — :func:`lieflow.integrate` — check it themselves): the
#: attributes of an :class:`~lieflow.IsospectralSystem`, a :class:`~lieflow.Scheme`, a
#: :class:`~lieflow.solvers.Solver` and a :class:`~lieflow.flows.Flow`.
_REQUIRED: Mapping[str, tuple[tuple[str, ...], tuple[str, ...], str]] = MappingProxyType({
    "system": (("algebra",), ("B", "hamiltonian", "casimirs", "validate"), "IsospectralSystem"),
    "scheme": (("name", "order"), ("step",), "Scheme"),
    "solver": (("name",), ("solve",), "Solver"),
    "flow": (("name",), ("init", "step"), "Flow"),
})  # fmt: skip


def _check_kind(kind: Kind, obj: Any) -> str | None:
    """Why ``obj`` is not a valid ``kind`` (or ``None`` if it is): the attributes and methods
    every object of that kind has (:data:`_REQUIRED`)."""
    attributes, methods, what = _REQUIRED[kind]
    missing = [a for a in attributes if not hasattr(obj, a)]
    missing += [m for m in methods if not callable(getattr(obj, m, None))]
    if not missing:
        return None
    return f"its factory made a {type(obj).__name__}, not a {what} (missing {', '.join(missing)})"


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
        #: ``(table, key, record)`` of the plugin loading now, committed once it has loaded.
        self._pending: list[tuple[str, str, Any]] = []

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
        doc = self._free("plotters", system, f"a plotter for {system!r}", function, description)
        self._pending.append(("plotters", system, Plotter(system, function, doc, self._source)))

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
        doc = self._free("sinks", suffix, f"a sink for {suffix!r} files", factory, description)
        self._pending.append(("sinks", suffix, SinkFormat(suffix, factory, doc, self._source)))

    def _add(self, kind: Kind, name: str, factory: Callable[..., Any], description: str) -> None:
        if not isinstance(name, str) or not _NAME.match(name):
            raise PluginError(
                f"invalid {kind} name {name!r}: use lower-case letters, digits and underscores"
            )
        doc = self._free(f"{kind}s", name, f"{kind} {name!r}", factory, description)
        self._validate(kind, name, factory)
        self._pending.append((f"{kind}s", name, Entry(kind, name, factory, doc, self._source)))

    def _free(
        self, table: str, key: str, what: str, function: Callable[..., Any], description: str
    ) -> str:
        """Check that ``function`` is callable and ``key`` not yet taken in ``table`` (by a
        loaded plugin, or earlier by the one loading now), and return the registration's
        one-line description (``description``, else the first line of the function's
        docstring); ``what`` names it in the errors."""
        if not callable(function):
            raise PluginError(f"{what}: {function!r} is not callable")
        taken = self._table(table).get(key) or next(
            (record for t, k, record in self._pending if (t, k) == (table, key)), None
        )
        if taken is not None:
            raise PluginError(f"{what} is already registered by {taken.source}")
        return description or (inspect.getdoc(function) or "").split("\n")[0]

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
        for table, key, record in self._pending:
            self._table(table)[key] = record
        self._discard()

    def _discard(self) -> None:
        self._pending = []

    def _table(self, name: str) -> dict[str, Any]:
        """The committed table ``name`` (``"systems"`` ... ``"flows"``, ``"plotters"``,
        ``"sinks"``): the registry's tables are views of these."""
        if name == "plotters":
            return self._plotters
        if name == "sinks":
            return self._sinks
        return self._entries[name[:-1]]  # type: ignore[index]

    def _snapshot(self) -> list[dict[str, Any]]:
        return [dict(self._table(name)) for name in _TABLES]

    def _restore(self, snapshot: list[dict[str, Any]]) -> None:
        for name, saved in zip(_TABLES, snapshot, strict=True):
            table = self._table(name)
            table.clear()
            table.update(saved)


@attrs.frozen
class Registry:
    """Immutable name -> :class:`Entry` tables for systems, schemes, solvers and flows, the
    system name -> :class:`Plotter` table of extra ``lieflow plot`` figures, and the
    suffix -> :class:`SinkFormat` table of file formats.

    The tables of a registry from :func:`load_registry` are read-only views that may load
    plugins when used (``lazy=True``, as :func:`default_registry`): what a name resolves to
    never depends on what was loaded before (a name is lieflow's own, or one plugin's, or
    its lookup raises the :class:`PluginError` of a broken plugin).
    """

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


#: The tables of a :class:`Registry`, by attribute name.
_TABLES = ("systems", "schemes", "solvers", "flows", "plotters", "sinks")

#: ``(label, load)`` pairs: a plugin's description in messages and how to get its object.
Candidates = Sequence[tuple[str, Callable[[], object]]]


class _TieredLoader:
    """Loads plugins a *tier* at a time, on demand, into one :class:`RegistryBuilder`.

    The tiers are lieflow's own entry points, then every other plugin (see
    :func:`load_registry`). A tier is loaded whole or not at all: when a plugin of it is
    broken (and broken plugins raise), the tier's registrations are rolled back and every
    later request for that tier raises the same :class:`PluginError`.
    """

    def __init__(
        self, tiers: Callable[[], Sequence[Candidates]], errors: Literal["raise", "warn"]
    ) -> None:
        self._make_tiers = tiers
        self._tiers: Sequence[Candidates] | None = None
        self._errors = errors
        self._builder = RegistryBuilder()
        self._pm = pluggy.PluginManager(PROJECT)
        self._pm.add_hookspecs(HookSpecs)
        self._loaded = 0
        self._failure: PluginError | None = None
        self._loading = False
        self._lock = threading.RLock()

    def get(self, table: str, key: str) -> Any:
        """``table[key]`` (``None`` if missing), loading further tiers only while ``key`` is
        missing."""
        with self._lock:
            while True:
                found = self._builder._table(table).get(key)
                if found is not None or not self.load_next():
                    return found

    def names(self, table: str, start: int) -> list[str]:
        """The names of ``table`` loaded so far, from the ``start``-th on (a copy)."""
        with self._lock:
            return list(self._builder._table(table))[start:]

    def load_all(self) -> None:
        """Load every tier."""
        while self.load_next():
            pass

    def load_next(self) -> bool:
        """Load the next tier; ``False`` if none is left (or this thread is loading one: a
        plugin that looks a name up while it registers sees the tiers before its own)."""
        with self._lock:
            if self._failure is not None:
                raise PluginError(str(self._failure)) from self._failure.__cause__
            if self._tiers is None:
                self._tiers = self._make_tiers()
            if self._loading or self._loaded == len(self._tiers):
                return False
            self._loading = True
            try:
                self._load(self._tiers[self._loaded])
            finally:
                self._loading = False
            self._loaded += 1
            return True

    def _load(self, tier: Candidates) -> None:
        builder, pm = self._builder, self._pm
        before = builder._snapshot()
        for label, load in tier:
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
                reason = (
                    str(exc) if isinstance(exc, PluginError) else f"{type(exc).__name__}: {exc}"
                )
                message = (
                    f"lieflow {label} is broken: {reason}. Fix or uninstall that distribution, "
                    f"or set {DISABLE_AUTOLOAD_ENV}=1 to skip third-party plugins"
                )
                if self._errors == "warn":
                    warnings.warn(message, PluginWarning, stacklevel=2)
                    continue
                builder._restore(before)
                self._failure = PluginError(message)
                raise self._failure from exc


class _Table(Mapping[str, Any]):
    """One table of a :class:`Registry`, a read-only view that loads plugins on demand.

    Looking a name up loads the next tier of plugins only while the name is missing (a
    built-in is found without importing any other plugin); iteration yields the names tier
    by tier, loading the next tier only when iterated past the names loaded so far, so a
    search that stops at a built-in loads nothing more; ``len``, ``sorted(table)`` and the
    like load every plugin.
    """

    __slots__ = ("_loader", "_name")

    def __init__(self, loader: _TieredLoader, name: str) -> None:
        self._loader = loader
        self._name = name

    def __getitem__(self, key: str) -> Any:
        found = self._loader.get(self._name, key)
        if found is None:
            raise KeyError(key)
        return found

    def __iter__(self) -> Iterator[str]:
        seen = 0
        while True:
            names = self._loader.names(self._name, seen)
            yield from names
            seen += len(names)
            if not self._loader.load_next():
                return

    def __len__(self) -> int:
        self._loader.load_all()
        return len(self._loader.names(self._name, 0))

    def __repr__(self) -> str:
        return f"<registry {self._name}: {', '.join(self._loader.names(self._name, 0))}, ...>"


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


def _tiers(autoload: bool, plugins: Candidates) -> list[Candidates]:
    """lieflow's own entry points, then the other entry points and ``plugins``."""
    own: list[tuple[str, Callable[[], object]]] = []
    others: list[tuple[str, Callable[[], object]]] = []
    for ep in _plugin_entry_points(autoload):
        dist = _dist_name(ep)
        label = f"entry point {ep.name!r} of distribution {dist!r}"
        (own if dist == PROJECT else others).append((label, ep.load))
    return [own, [*others, *plugins]]


def load_registry(
    *,
    autoload: bool | None = None,
    plugins: Iterable[tuple[str, object]] = (),
    errors: Literal["raise", "warn"] | None = None,
    lazy: bool = False,
) -> Registry:
    """Load the plugins and return the :class:`Registry` of what they register.

    The plugins load in two tiers: lieflow's own entry points (the built-ins and the
    application's file sink), then every other entry point and ``plugins``. A name
    registered by lieflow's own plugins is lieflow's: another plugin that registers it too
    is broken. Within the second tier, every plugin is loaded before any of its names is
    used, so a name that two plugins register is always reported, whatever their order.

    Parameters
    ----------
    autoload : bool, optional
        Load third-party entry points too (default: unless ``LIEFLOW_DISABLE_PLUGIN_AUTOLOAD``
        is set). lieflow's own entry points are always loaded.
    plugins : iterable of (name, object)
        Extra plugin objects (modules or instances with a ``lieflow_register`` hookimpl), e.g.
        for tests; they are guarded like entry points.
    errors : {"raise", "warn"}, optional
        What to do with a broken plugin (default: ``LIEFLOW_PLUGIN_ERRORS`` or ``"raise"``).
    lazy : bool
        Load nothing now: the registry loads lieflow's own plugins at its first lookup and
        the others only when a name is not among lieflow's own, or when a table is listed
        (its ``len``, ``sorted(registry.systems)``, a lookup that misses). A broken
        third-party plugin then raises (or warns) there, not here, and never affects a
        lookup of a built-in name. Default ``False``: everything is loaded, and a broken
        plugin reported, before this returns.
    """
    if autoload is None:
        autoload = not os.environ.get(DISABLE_AUTOLOAD_ENV)
    if errors is None:
        errors = "warn" if os.environ.get(ERRORS_ENV, "").lower() == "warn" else "raise"
    extra = [(f"plugin {name!r}", _constant(obj)) for name, obj in plugins]
    loader = _TieredLoader(functools.partial(_tiers, autoload, extra), errors)
    if not lazy:
        loader.load_all()
    return Registry(**{name: _Table(loader, name) for name in _TABLES})


@functools.cache
def default_registry() -> Registry:
    """The registry of the installed plugins, loaded on demand (:func:`load_registry` with
    ``lazy=True``): looking up a built-in imports no third-party plugin; listing a table
    (``lieflow list``, :func:`lieflow.systems.available`) loads them all."""
    return load_registry(lazy=True)
