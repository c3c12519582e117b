"""Sweeps: many runs of one base configuration over a grid of parameters (``lieflow sweep``).

A grid file is a run configuration (``[system]``, ``[initial]``, ``[scheme]``, ``[solver]``,
``[splitting]``, ``[run]``, see :mod:`lieflow.app.config`) plus a ``[sweep]`` table of lists
over dotted configuration keys; their product defines the runs::

    [sweep]
    directory = "convergence"                  # optional: default the grid file's stem
    "scheme.name" = ["gauss2", "gauss3"]       # an axis: one value per run
    "solver.params.rtol" = [1e-10, 1e-14]

    [[sweep.zip]]                              # optional: keys that change together
    "run.h" = [0.1, 0.05, 0.025]               # (one axis, named after its first key)
    "run.steps" = [10, 20, 40]

gives 2 x 2 x 3 = 12 runs. Each run is the base configuration with the swept keys set,
checked like any configuration (unknown keys and sections refused). It writes one
trajectory file, ``DIRECTORY/runs/<id>.h5`` (the existing format, resumable), ``<id>``
derived from its parameters alone; ``DIRECTORY/manifest.json`` (rewritten atomically)
lists every run with its parameters, status, error and file.

:func:`sweep` runs a grid on any :class:`concurrent.futures.Executor` (default: a process
pool, one BLAS thread per worker) or on Dask distributed. Running it again skips complete
runs and resumes the others from their checkpoints, bit for bit; a failed run is recorded
with its error and does not stop the others; a run whose worker died is run again from its
checkpoint; two attempts never write one file at once (the trajectory's lock:
:class:`~lieflow.app.io.OutputBusyError` is retried later).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import copy
import datetime as _dt
import hashlib
import itertools
import json
import math
import os
import re
import signal
import socket
import sys
import threading
import time
import traceback
import warnings
from collections import deque
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from types import FrameType, MappingProxyType
from typing import Any

import attrs
import numpy as np

from ..errors import InputError, LieflowError
from ..progress import start_live, stop_live
from .config import (
    _SECTIONS,
    Config,
    ConfigError,
    _fail,
    _Section,
    parse_config,
    read_toml_file,
)
from .datasets import ZARR_STORE

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = [
    "MANIFEST",
    "STORES",
    "SWEEP_FORMAT",
    "Axis",
    "RunSpec",
    "Sweep",
    "SweepMonitor",
    "SweepProgress",
    "SweepResult",
    "load_sweep",
    "parse_sweep",
    "sweep",
]

SWEEP_FORMAT = "lieflow-sweep"
#: Stores :func:`sweep` can write besides the trajectory files (``store=``).
STORES = ("zarr",)
SWEEP_FORMAT_VERSION = 1
MANIFEST = "manifest.json"
#: Statuses of a run in the manifest.
STATUSES = ("pending", "running", "complete", "failed", "interrupted")
_OPTIONS = ("directory", "zip")
_THREAD_VARS = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)


def _require(module: str, extra: str = "sweep") -> Any:
    """Import an optional dependency or say which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise InputError(
            f"this needs the {module.split('.')[0]!r} package ({exc}). To fix: "
            f"pip install 'lieflow[{extra}]'."
        ) from None


# -- the grid ----------------------------------------------------------------------------


@attrs.frozen
class Axis:
    """One dimension of a sweep: a key and its values, or a zipped group of keys.

    Attributes
    ----------
    name : str
        The dimension's name in :func:`lieflow.open_sweep` (short: ``"h"`` for
        ``run.h``, ``"scheme"`` for ``scheme.name``, the full key where short names clash).
    keys : tuple of str
        Dotted configuration keys set together (one, or a zipped group's).
    values : tuple of tuple
        ``values[j]`` are the values of ``keys[j]``, one per point of the axis.
    """

    name: str
    keys: tuple[str, ...]
    values: tuple[tuple[Any, ...], ...]

    @property
    def size(self) -> int:
        """Number of points."""
        return len(self.values[0])

    def point(self, i: int) -> dict[str, Any]:
        """The keys' values at point ``i``."""
        return {key: vals[i] for key, vals in zip(self.keys, self.values, strict=True)}


@attrs.frozen(eq=False)
class RunSpec:
    """One run of a sweep.

    Attributes
    ----------
    id : str
        The file stem, derived from :attr:`params` alone (readable slug + hash).
    index : tuple of int
        Position on each axis.
    params : Mapping
        Dotted key -> value of every swept key.
    config : Config
        The run's full configuration (its ``[run] output`` is :attr:`output`).
    output : Path
        The trajectory file (absolute).
    """

    id: str
    index: tuple[int, ...]
    params: Mapping[str, Any]
    config: Config = attrs.field(repr=False)
    output: Path


@attrs.frozen(eq=False)
class Sweep:
    """A parsed grid (:func:`parse_sweep`, :func:`load_sweep`)."""

    source: str
    text: str = attrs.field(repr=False)
    axes: tuple[Axis, ...]
    directory: Path
    runs: tuple[RunSpec, ...] = attrs.field(repr=False)
    base_dir: Path = attrs.field(factory=Path.cwd, repr=False)

    @property
    def shape(self) -> tuple[int, ...]:
        """Points per axis."""
        return tuple(a.size for a in self.axes)

    @property
    def manifest(self) -> Path:
        """Where the manifest is written."""
        return self.directory / MANIFEST


def _flatten_axes(
    value: Any, prefix: str, source: str, out: dict[str, list[Any]]
) -> dict[str, list[Any]]:
    """Dotted key -> list, from nested TOML tables (``[sweep.run] h = [...]`` too)."""
    if isinstance(value, dict):
        for key, item in value.items():
            _flatten_axes(item, f"{prefix}.{key}", source, out)
        return out
    if not isinstance(value, list) or not value:
        raise _fail(
            source,
            f"[sweep] {prefix}",
            f"expected a non-empty list of values, got {value!r}",
            f'write "{prefix}" = [value1, value2, ...]',
        )
    out[prefix] = value
    return out


def _sweep_keys(raw: Mapping[str, Any], source: str, where: str) -> dict[str, list[Any]]:
    out: dict[str, list[Any]] = {}
    for key, value in raw.items():
        head = key.split(".")[0]
        if head not in _SECTIONS:
            raise _fail(
                source,
                f"{where} {key}",
                "unknown key",
                f"sweep dotted configuration keys of the sections {', '.join(_SECTIONS)} "
                f'(e.g. "run.h" = [0.1, 0.05]); {where} also accepts '
                + ", ".join(_OPTIONS if where == "[sweep]" else ()),
            )
        _flatten_axes(value, key, source, out)
    for key in out:
        if key in ("run.output",):
            raise _fail(
                source,
                f"{where} {key}",
                "cannot be swept",
                "the sweep names each run's file itself (under [sweep] directory)",
            )
        if len(key.split(".")) < 2:
            raise _fail(
                source,
                f"{where} {key}",
                "is a whole section, not a key",
                f'sweep its keys, e.g. "{key}.name" = [...]',
            )
    return out


def _short_names(groups: list[list[str]]) -> list[str]:
    reserved = {
        "time",
        "step",
        "ensemble",
        "row",
        "col",
        "casimir",
        "run",
        "W",
        "energy",
        "energy_error",
        "casimirs",
        "casimir_drift",
        "iterations",
        "residual",
        "status",
    }

    def short(key: str) -> str:
        parts = key.split(".")
        return parts[0] if parts[-1] == "name" and len(parts) == 2 else parts[-1]

    names = [short(g[0]) for g in groups]
    return [
        g[0] if names.count(n) > 1 or n in reserved or n == "params" else n
        for n, g in zip(names, groups, strict=True)
    ]


def _set(data: dict[str, Any], key: str, value: Any, source: str) -> None:
    """Set the dotted ``key`` of a run's configuration to ``value``.

    A part that is a number indexes a list of the base configuration (``[[splitting.flows]]``
    tables: ``"splitting.flows.1.params.nu"`` is the second flow's ``nu``); tables on the
    way that the base configuration lacks are created.
    """
    parts = key.split(".")
    if parts[0] == "solver" and "solver" not in data and parts[1] != "name":
        data["solver"] = {"name": "fixed_point"}  # the default of a configuration without one
    node: Any = data
    for i, part in enumerate(parts):
        if isinstance(node, list):
            if not part.isdigit() or int(part) >= len(node):
                raise _fail(
                    source,
                    f"[sweep] {key}",
                    f"{'.'.join(parts[:i])} is a list of {len(node)} in the base "
                    f"configuration, and {part!r} is not an index of it",
                    f"index it from 0 to {len(node) - 1}, e.g. "
                    f'"{".".join([*parts[:i], "0", *parts[i + 1 :]])}"',
                )
            index: int | str = int(part)
        elif isinstance(node, dict):
            index = part
        else:
            raise _fail(
                source,
                f"[sweep] {key}",
                f"{'.'.join(parts[:i])} is {node!r} in the base configuration, not a table",
                f"sweep {'.'.join(parts[:i])} as a whole instead",
            )
        if i == len(parts) - 1:
            node[index] = copy.deepcopy(value)
        elif isinstance(node, dict):
            node = node.setdefault(part, {})
        else:
            node = node[index]


# -- TOML text of a run's configuration (stored in its file) ----------------------------------

_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_key(key: str) -> str:
    return key if _BARE.match(key) else json.dumps(key)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        items = ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items())
        return "{ " + items + " }" if items else "{}"
    return json.dumps(str(value))  # dates and times: as text (no configuration key takes one)


def _toml(data: Mapping[str, Any], header: str) -> str:
    lines = [f"# {line}" for line in header.splitlines()]
    for section in _SECTIONS:
        if section not in data:
            continue
        lines.append(f"\n[{section}]")
        for key, value in data[section].items():
            lines.append(f"{_toml_key(key)} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"


def _label(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, tuple)):
        return "-".join(_label(v) for v in value)
    if isinstance(value, dict):
        return "-".join(f"{k}{_label(v)}" for k, v in value.items())
    return str(value)


def run_id(params: Mapping[str, Any]) -> str:
    """The file stem of a run: a readable slug of its parameters (each value after its key's
    last part; a ``name`` bare) and 10 hex digits of the SHA-256 of their canonical JSON,
    independent of the order of the grid's keys.

    >>> run_id({"scheme.name": "gauss2", "run.h": 0.1})
    'gauss2_h0.1_3a718b93ce'
    """
    digest = hashlib.sha256(
        json.dumps(dict(params), sort_keys=True, default=str).encode()
    ).hexdigest()[:10]
    parts = []
    for key, value in params.items():
        short = key.split(".")[-1]
        parts.append(f"{'' if short == 'name' else short}{_label(value)}")
    slug = re.sub(r"[^A-Za-z0-9.=+-]+", "_", "_".join(parts)).strip("_.")[:80]
    return f"{slug}_{digest}" if slug else digest


def parse_sweep(
    text: str,
    *,
    source: str = "<string>",
    base_dir: Path | str | None = None,
    directory: Path | str | None = None,
) -> Sweep:
    """Parse and check a grid: the base configuration, the ``[sweep]`` table and every run.

    Parameters
    ----------
    text : str
        TOML text.
    source : str
        Where it came from (a path), for messages; its stem names the default directory.
    base_dir : path, optional
        What relative paths are relative to (default: the current directory).
    directory : path, optional
        The sweep's directory, overriding ``[sweep] directory``.

    Raises
    ------
    ConfigError
        Invalid TOML; a missing, ill-typed or unknown key in the base configuration, in
        ``[sweep]``, or in any run's configuration (the message names the run).
    """
    if not isinstance(text, str):
        raise ConfigError(
            f"{source}: a sweep grid must be TOML text (str), got "
            f"{type(text).__name__}. To fix: use load_sweep(path) for a file."
        )
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _fail(source, "", f"is not valid TOML ({exc})", "correct the syntax") from None
    base = Path.cwd() if base_dir is None else Path(base_dir)
    raw = data.pop("sweep", None)
    if raw is None:
        raise _fail(
            source,
            "[sweep]",
            "missing section",
            'add a [sweep] table of lists, e.g. "run.h" = [0.1, 0.05]; '
            "for a single run use `lieflow run`",
        )
    if not isinstance(raw, dict):
        raise _fail(source, "sweep", "must be a table", "write it as a [sweep] section")
    if isinstance(data.get("run"), dict) and "output" in data["run"]:
        raise _fail(
            source,
            "[run] output",
            "is not used by a sweep",
            "remove it: each run's file is DIRECTORY/runs/<id>.h5 ([sweep] directory)",
        )
    sec = _Section(raw, "sweep", source)
    dir_name = sec.string("directory", required=False, hint='"study"')
    zips = sec._raw("zip", False, '[{ "run.h" = [...], "run.steps" = [...] }]')
    sec.seen.update(k for k in raw if k.split(".")[0] in _SECTIONS)
    sec.finish()
    groups: list[dict[str, list[Any]]] = [
        {k: v}
        for k, v in _sweep_keys(
            {k: v for k, v in raw.items() if k not in _OPTIONS}, source, "[sweep]"
        ).items()
    ]
    if zips is not None:
        if isinstance(zips, dict):
            zips = [zips]
        if not isinstance(zips, list) or not all(isinstance(z, dict) and z for z in zips):
            raise _fail(
                source,
                "[sweep] zip",
                f"expected tables of lists, got {zips!r}",
                'write [[sweep.zip]] tables with "key" = [values] of equal length',
            )
        for i, z in enumerate(zips):
            keys = _sweep_keys(z, source, f"[[sweep.zip]] #{i + 1}")
            lengths = {k: len(v) for k, v in keys.items()}
            if len(set(lengths.values())) != 1:
                raise _fail(
                    source,
                    f"[[sweep.zip]] #{i + 1}",
                    f"lists of different lengths {lengths}",
                    "give every key of a zipped group one value per point",
                )
            groups.append(keys)
    for g in groups:
        points = [json.dumps(p, sort_keys=True) for p in zip(*g.values(), strict=True)]
        twice = next((p for i, p in enumerate(points) if p in points[:i]), None)
        if twice is not None:
            raise _fail(
                source,
                f"[sweep] {next(iter(g))}",
                f"the point {twice} is listed twice",
                "list each value once (two runs would be the same run)",
            )
    all_keys = [k for g in groups for k in g]
    for a, b in itertools.permutations(all_keys, 2):
        if a == b or b.startswith(a + "."):
            raise _fail(
                source,
                f"[sweep] {b}",
                f"is swept twice (also as {a})",
                "sweep each key once, in one axis or one zipped group",
            )
    names = _short_names([list(g) for g in groups])
    axes = tuple(
        Axis(name, tuple(g), tuple(tuple(v) for v in g.values()))
        for name, g in zip(names, groups, strict=True)
    )
    stem = Path(source).stem if source != "<string>" else "sweep"
    where = Path(directory) if directory is not None else Path(dir_name or stem)
    where = (
        (where if where.is_absolute() else (Path.cwd() if directory is not None else base) / where)
        .expanduser()
        .absolute()
    )
    runs = []
    for index in itertools.product(*(range(a.size) for a in axes)):
        params: dict[str, Any] = {}
        for axis, i in zip(axes, index, strict=True):
            params.update(axis.point(i))
        merged = copy.deepcopy(data)
        for key, value in params.items():
            _set(merged, key, value, source)
        rid = run_id(params)
        output = where / "runs" / f"{rid}.h5"
        merged.setdefault("run", {})["output"] = str(output)
        shown = ", ".join(f"{k} = {_toml_value(v)}" for k, v in params.items())
        header = f"run {rid} of the sweep {source}\n{shown}" if shown else f"sweep {source}"
        run_text = _toml(merged, header)
        try:
            config = parse_config(run_text, source=source, base_dir=base)
        except ConfigError as exc:
            raise ConfigError(
                f"{exc} (in the run with {shown or 'no swept keys'})", exc.key
            ) from None
        runs.append(RunSpec(rid, tuple(index), MappingProxyType(params), config, output))
    ids = [r.id for r in runs]
    if len(set(ids)) != len(ids):  # pragma: no cover - needs a SHA-256 collision
        raise _fail(source, "[sweep]", "two runs have the same id", "report this")
    return Sweep(source, text, axes, where, tuple(runs), base.absolute())


def load_sweep(path: Path | str, *, directory: Path | str | None = None) -> Sweep:
    """Read and parse the grid file ``path`` (:func:`parse_sweep`); relative paths in it
    are relative to its directory, and so is the default sweep directory (its stem)."""
    p, text = read_toml_file(path, "grid")
    return parse_sweep(text, source=str(p), base_dir=p.resolve().parent, directory=directory)


# -- one run on a worker ------------------------------------------------------------------

#: True while a worker of the default pool runs a task (its SIGTERM handler then raises
#: KeyboardInterrupt, which lieflow.app.io.run turns into an "interrupted", resumable file).
_BUSY = False
#: Set by SIGTERM in a worker of the default pool: tasks it has not started return at once.
_STOP = False
#: True in the default pool's workers (which then report their OS threads: BLAS's included).
_POOL_WORKER = False


def _worker_init() -> None:
    """Initializer of the default pool's workers: one BLAS thread (the variables are also
    set before the workers start), Ctrl-C left to the coordinator, SIGTERM stops the run
    at its next step with its file marked "interrupted"."""
    global _POOL_WORKER
    _POOL_WORKER = True
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    with contextlib.suppress(ImportError):
        import threadpoolctl

        threadpoolctl.threadpool_limits(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def on_term(signum: int, frame: FrameType | None) -> None:
        global _STOP
        _STOP = True
        if _BUSY:  # through the SIGINT handler a run installed (it stops at a safe point)
            handler = signal.getsignal(signal.SIGINT)
            if callable(handler):
                handler(signal.SIGINT, frame)
            else:
                raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, on_term)
    threading.Thread(target=_exit_with_parent, name=_WATCH, daemon=True).start()


#: The name of a pool worker's thread that watches its coordinator (:func:`_exit_with_parent`).
_WATCH = "lieflow-parent-watch"


#: Seconds a worker whose coordinator died waits for its run to stop (at its next step)
#: before it exits anyway (the file is then resumable from its last checkpoint, as after a
#: kill).
_ORPHAN_GRACE = 60.0


def _exit_with_parent() -> None:
    """A default-pool worker's watch of its coordinator: once the coordinator is gone (a
    ``kill -9`` runs no cleanup, and its workers used to live on, blocked on the task queue
    for ever, a running run stepping to its end), stop the run at its next step as SIGTERM
    does (its file marked "interrupted"), then exit. Waits on the spawn start method's
    parent sentinel (readable once the parent process has died), so it costs nothing."""
    import multiprocessing.connection

    parent = multiprocessing.parent_process()
    if parent is None:  # pragma: no cover - not a spawned worker
        return
    multiprocessing.connection.wait([parent.sentinel])
    os.kill(os.getpid(), signal.SIGTERM)  # the run stops at its next step (on_term)
    deadline = time.monotonic() + _ORPHAN_GRACE
    while _BUSY and time.monotonic() < deadline:
        time.sleep(0.05)
    os._exit(1)


class _ProgressFile:
    """A :class:`~lieflow.driver.Monitor` that writes a run's step count to a small JSON
    file (atomically, at most once a second) for the coordinator's progress display, and
    stops the run (:class:`KeyboardInterrupt`, which marks its file "interrupted") once the
    coordinator's stop file exists — how an interrupted sweep stops runs on Dask workers,
    which no signal of the coordinator reaches."""

    def __init__(self, path: Path | None, stop: Path | None = None) -> None:
        self.path = path
        self.stop_file = stop
        self.done = self.total = 0
        self.last = self.checked = 0.0

    def _stop_requested(self) -> bool:
        return self.stop_file is not None and self.stop_file.exists()

    def _write(self) -> None:
        self.last = time.monotonic()
        if self.path is None:
            return
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(
                json.dumps(
                    {
                        "done": self.done,
                        "total": self.total,
                        "host": socket.gethostname(),
                        "pid": os.getpid(),
                    }
                )
            )
            os.replace(tmp, self.path)
        except OSError:  # progress is a courtesy: never fail a run for it
            pass

    def start(self, done: int, total: int) -> None:
        self.done, self.total = done, total
        self._write()

    def advance(self, steps: int, iterations: int, energy_error: float | None) -> None:
        self.done += steps
        now = time.monotonic()
        if now - self.last >= 1.0:
            self._write()
        if now - self.checked >= 0.1:
            self.checked = now
            if self._stop_requested():
                raise KeyboardInterrupt

    def stop(self) -> None:
        self._write()


def run_task(task: Mapping[str, Any]) -> dict[str, Any]:
    """Run (or resume) one run of a sweep; what a worker executes.

    ``task`` holds the run's configuration text, ``source``, ``base_dir``, ``output`` and
    ``progress`` (paths). Never raises for the run's own errors: returns a dictionary with
    ``status`` (``"complete"``, ``"interrupted"``, ``"failed"`` or ``"busy"`` when another
    process holds the file's lock) and the run's numbers, or its ``error``.
    """
    global _BUSY
    from . import io
    from .config import build

    started = time.time()
    out: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid(), "started": started}
    if _POOL_WORKER and os.path.isdir("/proc/self/task"):  # 1: one BLAS thread, no pool
        watch = sum(t.name == _WATCH for t in threading.enumerate())  # lieflow's own
        out["threads"] = len(os.listdir("/proc/self/task")) - watch
    stop = Path(task["stop"]) if task.get("stop") else None
    if _STOP or (stop is not None and stop.exists()):  # interrupted before it started
        return {**out, "status": "pending", "error": "", "finished": started}
    _BUSY = True
    try:
        config = parse_config(task["text"], source=task["source"], base_dir=task["base_dir"])
        setup = build(config, output=task["output"], replace=False)
        monitor = _ProgressFile(Path(task["progress"]) if task.get("progress") else None, stop)
        stored: list[Any] = []  # the run's ZarrSink, once its file is open
        also = _store_sink(task, stored)
        try:
            try:
                summary = io.run(setup, resume=True, monitor=monitor, also=also)
            except io.DamagedOutputError as exc:
                # a worker killed during a write (the lost attempt of a Dask task) can leave
                # the file unreadable past its last good checkpoint; the run is deterministic,
                # so running it again from the start gives the same bits
                out["restarted"] = str(exc)
                setup = build(config, output=task["output"], replace=True)
                stored.clear()
                summary = io.run(setup, monitor=monitor, also=also)
        except LieflowError:
            _store_run(task, out, stored)  # a failed run: its steps before the failure
            raise
        _store_run(task, out, stored)
        out.update(
            status=summary.status,
            completed_steps=summary.completed_steps,
            requested_steps=summary.requested_steps,
            new_steps=summary.new_steps,
            wall_time=summary.wall_time,
            max_energy_error=summary.max_energy_error,
            error=summary.failure,
        )
    except io.OutputBusyError as exc:
        out.update(status="busy", error=str(exc))
    except ConfigError as exc:
        # another attempt created the file between this one's check and its create: try
        # again (it will resume it); any other configuration error is the run's failure
        raced = exc.key == "[run] output" and "already exists" in str(exc)
        out.update(status="busy" if raced else "failed", error=str(exc))
    except LieflowError as exc:
        out.update(status="failed", error=str(exc))
    except KeyboardInterrupt:
        out.update(status="interrupted", error="")
    except Exception as exc:  # a bug or an environment problem: record it, go on
        tb = traceback.format_exc(limit=-6)
        out.update(status="failed", error=f"{type(exc).__name__}: {exc}", traceback=tb)
    finally:
        _BUSY = False
    out["finished"] = time.time()
    return out


def _store_sink(task: Mapping[str, Any], opened: list[Any]) -> Any:
    """The run's sinks besides its file (:func:`lieflow.app.io.run`'s ``also``): with a
    Zarr store (``task["store"]``), a :class:`~lieflow.app.zarr_sink.ZarrSink` writing the
    run's group as it steps (appended to ``opened``); else None."""
    if not task.get("store"):
        return None
    from .zarr_sink import ZarrSink

    def also(writer: Any) -> tuple[Any, ...]:
        sink = ZarrSink.open(task["store"], task["id"], writer)
        opened.append(sink)
        return (sink,)

    return also


def _store_run(task: Mapping[str, Any], out: dict[str, Any], opened: Sequence[Any]) -> None:
    """Make the run's group of the sweep's Zarr store (``task["store"]``) hold its file's
    steps: its :class:`~lieflow.app.zarr_sink.ZarrSink` wrote them as it stepped; only where
    it could not (the group was not at the file's checkpoint on a resume, a write failed)
    is the group rebuilt from the file. A failure is recorded in ``out["store_error"]``,
    never the run's failure (the dataset then reads the run from its file)."""
    if not task.get("store") or (opened and opened[-1].in_sync):
        return
    from .datasets import write_zarr_run

    try:
        write_zarr_run(task["output"], task["store"], task["id"])
    except Exception as exc:
        out["store_error"] = f"{type(exc).__name__}: {exc}"


def _consolidate(store: Path) -> None:
    """Consolidate the store's metadata (one read opens it), if it exists."""
    if not store.is_dir():
        return
    with contextlib.suppress(Exception), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "not part of the Zarr format 3 specification"
        import zarr

        zarr.consolidate_metadata(str(store))


# -- the file's own word on a run -----------------------------------------------------------


def _file_state(spec: RunSpec) -> dict[str, Any] | None:
    """The status and step counts a run's file records, or None (missing, locked,
    unreadable: the run is then attempted, and the attempt reports what is wrong)."""
    if not spec.output.exists():
        return None
    try:
        import h5py

        with h5py.File(spec.output, "r") as f:
            a = f.attrs
            return {
                "status": str(_plain(a.get("status", ""))),
                "completed_steps": int(a.get("completed_steps", 0)),
                "requested_steps": int(a.get("requested_steps", 0)),
                "identity": str(_plain(a.get("identity", ""))),
                "wall_time": float(a.get("wall_time", 0.0)),
            }
    except Exception:
        return None


def file_status(spec: RunSpec) -> str:
    """What a run's file says: ``"complete"``, ``"to run"`` (no file yet), or its status
    and steps (``"interrupted 120/400"``; ``"other config"`` when it is the file of another
    configuration); nothing is written."""
    state = _file_state(spec)
    if state is None:
        return "unreadable" if spec.output.exists() else "to run"
    if _is_complete(spec, state):
        return "complete"
    if state["identity"] != spec.config.identity():
        return "other config"
    return f"{state['status']} {state['completed_steps']}/{spec.config.run.steps}"


def _max_energy_error(path: Path) -> float | None:
    try:
        from .io import read_diagnostics

        return float(np.max(read_diagnostics(path).energy_error))
    except Exception:
        return None


def _plain(value: Any) -> Any:
    return value.decode() if isinstance(value, bytes) else value


def _is_complete(spec: RunSpec, state: Mapping[str, Any] | None) -> bool:
    return (
        state is not None
        and state["status"] == "complete"
        and state["completed_steps"] == spec.config.run.steps
        and state["identity"] == spec.config.identity()
    )


# -- the coordinator ------------------------------------------------------------------------


class SweepMonitor:
    """Receives a sweep's progress (:func:`sweep`'s ``monitor``); subclass what you need.

    ``counts`` maps each status (``"pending"``, ``"running"``, ``"complete"``, ``"failed"``,
    ``"interrupted"``) to its number of runs; ``steps`` and ``total_steps`` count steps
    over all runs (those of running runs included, as far as their workers reported).
    """

    def start(self, runs: int, skipped: int) -> None:
        """Called once: ``runs`` in the sweep, ``skipped`` of them complete already."""

    def update(self, counts: Mapping[str, int], steps: int, total_steps: int) -> None:
        """Called about twice a second while the sweep runs."""

    def finished(self, record: Mapping[str, Any]) -> None:
        """A run ended (its manifest record: ``id``, ``params``, ``status``, ``error``...)."""

    def stop(self) -> None:
        """Called once when the sweep ends, however it ends."""


@attrs.frozen(eq=False)
class SweepResult:
    """How :func:`sweep` ended.

    Attributes
    ----------
    directory, manifest : Path
        The sweep's directory and its manifest file.
    runs : tuple of Mapping
        The manifest's records, one per run, in grid order.
    wall_time : float
        Seconds this call took.
    interrupted : bool
        Whether the sweep was stopped (Ctrl-C, SIGTERM) before every run ended.
    """

    directory: Path
    manifest: Path
    runs: tuple[Mapping[str, Any], ...] = attrs.field(repr=False)
    wall_time: float
    interrupted: bool = False
    skipped: int = 0

    @property
    def counts(self) -> dict[str, int]:
        """Number of runs per status."""
        out = dict.fromkeys(STATUSES, 0)
        for r in self.runs:
            out[r["status"]] = out.get(r["status"], 0) + 1
        return out

    @property
    def ok(self) -> bool:
        """Whether every run is complete."""
        return all(r["status"] == "complete" for r in self.runs)

    @property
    def failed(self) -> tuple[Mapping[str, Any], ...]:
        """The records of the failed runs."""
        return tuple(r for r in self.runs if r["status"] == "failed")

    def open(self, **kwargs: Any) -> Any:
        """The results as one :class:`xarray.Dataset` (:func:`lieflow.open_sweep`)."""
        from .datasets import open_sweep

        return open_sweep(self.manifest, **kwargs)


def _describe(record: Mapping[str, Any]) -> str:
    params = ", ".join(f"{k} = {_toml_value(v)}" for k, v in record["params"].items())
    return params or record["id"]


class SweepProgress(SweepMonitor):
    """The progress display of ``lieflow sweep``: on a terminal, one rich bar over all the
    steps of all runs (runs complete, running, failed; ETA) with a line per failed run; on
    anything else (a batch job's log), one line per finished run.

    Parameters
    ----------
    stream : file, optional
        Where to write (default ``sys.stderr``).
    live : bool, optional
        Draw the bar (default: whether ``stream`` is a terminal and ``rich`` is installed).
    """

    def __init__(self, stream: Any = None, live: bool | None = None) -> None:
        self.stream = sys.stderr if stream is None else stream
        if live is None:
            live = bool(getattr(self.stream, "isatty", lambda: False)())
        self._progress: Any = None
        if live:
            try:
                from rich.console import Console
                from rich.progress import (
                    BarColumn,
                    Progress,
                    TextColumn,
                    TimeElapsedColumn,
                    TimeRemainingColumn,
                )
            except ImportError:
                live = False
            else:
                self._progress = Progress(
                    TextColumn("sweep"),
                    BarColumn(bar_width=24),
                    TextColumn("{task.fields[runs]}"),
                    TimeElapsedColumn(),
                    TextColumn("ETA"),
                    TimeRemainingColumn(),
                    console=Console(file=self.stream),
                )
        self._task: Any = None
        self.runs = self.ended = 0

    def _line(self, text: str) -> None:
        if self._progress is not None:
            self._progress.console.print(text, markup=False, highlight=False)
        else:
            print(text, file=self.stream, flush=True)

    def start(self, runs: int, skipped: int) -> None:
        self.runs, self.ended = runs, skipped
        if skipped:
            self._line(f"{skipped} of {runs} runs complete already (skipped)")
        if self._progress is not None:
            self._task = self._progress.add_task("sweep", total=None, runs="")
            start_live(self._progress)

    def update(self, counts: Mapping[str, int], steps: int, total_steps: int) -> None:
        if self._progress is None:
            return
        text = (
            f"{counts['complete']}/{self.runs} runs done, {counts['running']} running, "
            f"{counts['failed']} failed"
        )
        self._progress.update(self._task, total=total_steps, completed=steps, runs=text)

    def finished(self, record: Mapping[str, Any]) -> None:
        self.ended += 1
        status = record["status"]
        if status == "failed":
            error = str(record.get("error", "")).strip().splitlines()
            self._line(
                f"[{self.ended}/{self.runs}] failed: {_describe(record)}: "
                f"{error[0] if error else ''}"
            )
        elif self._progress is None:
            self._line(
                f"[{self.ended}/{self.runs}] {status}: {_describe(record)} "
                f"({record.get('completed_steps', 0)} steps, "
                f"{record.get('wall_time', 0.0):.2f} s)"
            )

    def stop(self) -> None:
        if self._progress is not None:
            stop_live(self._progress)


def _write_json(path: Path, data: Any) -> None:
    """Write JSON atomically: a temporary file in the same directory, fsync, rename."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=1, default=str, allow_nan=True)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


@contextlib.contextmanager
def _thread_env() -> Iterator[None]:
    """One BLAS/OpenMP thread in processes started inside the block."""
    saved = {v: os.environ.get(v) for v in _THREAD_VARS}
    os.environ.update(dict.fromkeys(_THREAD_VARS, "1"))
    try:
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


class _LocalPool:
    """The default executor: a spawn-started process pool, re-created if a worker dies."""

    def __init__(self, workers: int) -> None:
        import multiprocessing

        self.workers = workers
        self._ctx = multiprocessing.get_context("spawn")
        self.pool = self._new()

    def _new(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(self.workers, mp_context=self._ctx, initializer=_worker_init)

    def renew(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = self._new()

    def stop_workers(self) -> None:
        """SIGTERM to every worker: a running run stops at its next step, "interrupted"."""
        for proc in list(getattr(self.pool, "_processes", {}).values()):
            with contextlib.suppress(Exception):
                proc.terminate()


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT while worker processes are started, so that they inherit "ignored"
    (Python keeps an ignored SIGINT ignored): Ctrl-C on a terminal signals the whole
    process group, and the coordinator alone decides how runs stop (their files marked
    "interrupted"), instead of each worker dying with a traceback mid-write."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _dask_executor(
    scheduler: str | None, workers: int | None, stack: contextlib.ExitStack
) -> cf.Executor:
    distributed = _require("distributed")
    if scheduler:
        try:
            client = distributed.Client(scheduler)  # distributed.comm.timeouts.connect
        except (OSError, TimeoutError) as exc:
            raise LieflowError(
                f"cannot connect to the Dask scheduler at {scheduler!r} ({exc}). To fix: start "
                "it (`dask scheduler`) and give the address it prints (tcp://HOST:8786)."
            ) from None
    else:
        with _thread_env(), _sigint_ignored():  # the workers inherit it: Ctrl-C is ours
            cluster = distributed.LocalCluster(
                n_workers=workers or os.cpu_count() or 1,
                threads_per_worker=1,
                processes=True,
                dashboard_address=None,
            )
        stack.callback(cluster.close)
        client = distributed.Client(cluster)
    stack.callback(client.close)
    return client.get_executor(pure=False)


def _executor_of(obj: Any) -> cf.Executor:
    """A ``distributed.Client`` -> its executor; an Executor as it is."""
    if isinstance(obj, cf.Executor):
        return obj
    if hasattr(obj, "get_executor") and hasattr(obj, "submit"):
        return obj.get_executor(pure=False)
    raise InputError(
        f"executor must be 'local', 'dask', a concurrent.futures.Executor or a "
        f"distributed.Client, got {obj!r}"
    )


def sweep(
    grid: Sweep | Path | str,
    executor: str | cf.Executor | Any = "local",
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    directory: Path | str | None = None,
    monitor: SweepMonitor | None = None,
    max_attempts: int = 3,
    busy_timeout: float = 600.0,
    store: str | None = None,
) -> SweepResult:
    """Run every run of a sweep that is not complete, in parallel; write the manifest.

    Parameters
    ----------
    grid : Sweep or path
        A parsed grid (:func:`parse_sweep`) or a grid file (:func:`load_sweep`).
    executor : {"local", "dask"}, concurrent.futures.Executor or distributed.Client
        Where runs execute. ``"local"`` (default): a process pool of ``workers`` processes
        (default: one per core), each with one BLAS thread. ``"dask"``: Dask distributed,
        on the cluster at ``scheduler`` or on a new ``LocalCluster`` of ``workers``
        processes. Any other :class:`~concurrent.futures.Executor` (or a Dask ``Client``)
        is used as it is and not shut down.
    workers : int, optional
        Processes of the local pool or the local Dask cluster.
    scheduler : str, optional
        Address of a running Dask scheduler (``"tcp://host:8786"``), with ``"dask"``.
    directory : path, optional
        The sweep directory, overriding the grid's (only with a path ``grid``).
    monitor : SweepMonitor, optional
        Progress callbacks.
    max_attempts : int
        Attempts of a run whose worker died or whose task failed outside the run
        (a run that fails by itself, e.g. a solver that does not converge, is not retried
        within the call).
    busy_timeout : float
        Seconds to keep retrying a run whose file another process is writing (e.g. a worker
        the scheduler gave up on that still runs) before recording it as failed.
    store : {None, "zarr"}
        ``"zarr"``: also write each run's results (states at the saved times, diagnostics,
        header) into one Zarr store, ``DIRECTORY/runs.zarr``, one group per run written by
        the worker that runs it as it steps (a second sink next to the run's file,
        :class:`~lieflow.app.zarr_sink.ZarrSink`); complete runs the store lacks are
        copied from their files by this process first. :func:`lieflow.open_sweep` reads the store
        where it holds a run as the manifest records it (else the run's file). The
        trajectory files stay the record that resumes and skips are decided on.

    Returns
    -------
    SweepResult
        The manifest's records; ``result.ok`` when every run is complete. Ctrl-C (or
        SIGTERM under ``lieflow sweep``) stops the running runs at their next step with
        their files resumable and returns with ``interrupted=True``.

    Raises
    ------
    ConfigError
        The grid is invalid.
    OutputBusyError
        Another sweep is running in the same directory.
    """
    from .io import OutputBusyError, _OutputLock

    if not isinstance(grid, Sweep):
        grid = load_sweep(_grid_path(grid), directory=directory)
    elif directory is not None:
        raise InputError("directory= is for a grid given as a path; a parsed Sweep has its own")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise InputError(f"workers must be a positive integer, got {workers!r}")
    if scheduler is not None and executor != "dask":
        raise InputError("scheduler= is the address of a Dask scheduler: pass executor='dask'")
    if store is not None and store not in STORES:
        raise InputError(
            f"store must be one of {', '.join(map(repr, STORES))} or None (the trajectory "
            f"files only), got {store!r}"
        )
    if store is not None:
        _require("zarr")
    if scheduler is not None and workers is not None:
        raise InputError(
            "workers= sizes a new local pool or LocalCluster; the cluster at scheduler= has "
            "its own workers (start more with `dask worker`)"
        )
    t0 = time.perf_counter()
    root = grid.directory
    try:
        (root / "runs").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LieflowError(
            f"cannot create the sweep directory {str(root)!r}: "
            f"{exc.strerror or exc}. To fix: choose a writable place "
            "([sweep] directory or --out)."
        ) from None
    try:
        lock = _OutputLock.acquire(grid.manifest)
    except OutputBusyError:
        raise OutputBusyError(
            f"{str(root)!r} is in use by another `lieflow sweep` (it holds the lock of "
            f"{MANIFEST}). To fix: wait until it has finished, or give this sweep another "
            "directory (--out)."
        ) from None
    with contextlib.ExitStack() as stack:
        stack.callback(lock.release)
        local: _LocalPool | None = None
        if isinstance(executor, str):
            if executor == "local":
                n = workers or os.cpu_count() or 1
                # workers start when runs are submitted (and again if one dies): the variables
                # stay set while the pool lives (this process's BLAS is loaded already)
                stack.enter_context(_thread_env())
                local = _LocalPool(min(n, max(1, len(grid.runs))))
                pool: cf.Executor = local.pool
                stack.callback(lambda: local.pool.shutdown(wait=True, cancel_futures=True))
            elif executor == "dask":
                pool = _dask_executor(scheduler, workers, stack)
            else:
                raise InputError(
                    f"executor must be 'local' or 'dask' (or an Executor), got {executor!r}"
                )
        else:
            pool = _executor_of(executor)
        zarr_store = root / ZARR_STORE if store == "zarr" else None
        coord = _Coordinator(grid, pool, local, monitor, max_attempts, busy_timeout, zarr_store)
        interrupted = coord.run()
        records = tuple(coord.records)
    wall = time.perf_counter() - t0
    return SweepResult(root, grid.manifest, records, wall, interrupted, coord.skipped)


def _grid_path(grid: Any) -> Path:
    if isinstance(grid, (str, os.PathLike)) and str(grid):
        return Path(grid)
    raise InputError(f"grid must be a Sweep or the path of a grid file, got {grid!r}")


class _Coordinator:
    """Submits runs, collects outcomes, retries, writes the manifest, reports progress."""

    def __init__(
        self,
        grid: Sweep,
        pool: cf.Executor,
        local: _LocalPool | None,
        monitor: SweepMonitor | None,
        max_attempts: int,
        busy_timeout: float,
        store: Path | None = None,
    ) -> None:
        self.grid, self.pool, self.local, self.store = grid, pool, local, store
        self.monitor, self.max_attempts, self.busy_timeout = monitor, max_attempts, busy_timeout
        self.progress_dir = grid.directory / ".progress"
        #: created on Ctrl-C: every run (on any worker) stops at its next chunk of steps
        self.stop_file = self.progress_dir / "stop"
        self.records: list[dict[str, Any]] = []
        self.last_write = 0.0
        self.dirty = False
        self.skipped = 0
        self.worked = False  # a task started or returned (the pool's workers can start)
        self.t0 = time.time() - 1.0

    def _record(
        self, spec: RunSpec, state: Mapping[str, Any] | None, previous: Mapping[str, Any]
    ) -> dict[str, Any]:
        complete = _is_complete(spec, state)
        carried = {}
        if complete:  # what the last sweep recorded of it, or the file's own numbers
            carried = {k: previous[k] for k in ("host", "pid") if k in previous}
            error = previous.get("max_energy_error")
            carried["max_energy_error"] = (
                error if isinstance(error, float) else _max_energy_error(spec.output)
            )
        return {
            "id": spec.id,
            "index": list(spec.index),
            "params": dict(spec.params),
            "output": os.path.relpath(spec.output, self.grid.directory),
            "status": "complete" if complete else "pending",
            "error": "",
            "completed_steps": state["completed_steps"] if state else 0,
            "requested_steps": spec.config.run.steps,
            "wall_time": state["wall_time"] if state else 0.0,
            "max_energy_error": None,
            "attempts": previous.get("attempts", 0) if complete else 0,
            **carried,
        }

    def write_manifest(self, force: bool = False) -> None:
        now = time.monotonic()
        every = 0.5 + len(self.records) / 4000  # 3 s for 10,000 runs: writes stay cheap
        if not force and (not self.dirty or now - self.last_write < every):
            return
        g = self.grid
        from .. import __version__

        _write_json(
            g.manifest,
            {
                "format": SWEEP_FORMAT,
                "format_version": SWEEP_FORMAT_VERSION,
                "lieflow_version": __version__,
                "grid_source": g.source,
                "grid": g.text,
                "updated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                "axes": [
                    {"name": a.name, "keys": list(a.keys), "values": [list(v) for v in a.values]}
                    for a in g.axes
                ],
                "counts": self.counts(),
                "runs": self.records,
            },
        )
        self.last_write, self.dirty = now, False

    def counts(self) -> dict[str, int]:
        out = dict.fromkeys(STATUSES, 0)
        for r in self.records:
            out[r["status"]] += 1
        return out

    def _task(self, i: int) -> dict[str, Any]:
        spec = self.grid.runs[i]
        return {
            "text": spec.config.text,
            "source": self.grid.source,
            "base_dir": str(self.grid.base_dir),
            "output": str(spec.output),
            "progress": str(self.progress_dir / f"{spec.id}.json"),
            "id": spec.id,
            "store": str(self.store) if self.store is not None else "",
            "stop": str(self.stop_file),
        }

    def _capacity(self, runs: int) -> int:
        """How many runs to keep submitted: two per worker where the pool's size is known
        (the default pool, a ProcessPoolExecutor, a Dask cluster: its threads now), so that
        an interrupt has little to cancel and progress is read from few files; else all."""
        if self.local is not None:
            return 2 * self.local.workers
        client = getattr(self.pool, "_client", None)  # a Dask ClientExecutor
        if client is not None:
            try:
                threads = sum(client.nthreads().values())
            except Exception:
                threads = 0
            return max(2 * threads, 8)
        size = getattr(self.pool, "_max_workers", 0)
        return 2 * size if isinstance(size, int) and size > 0 else runs

    def _started_any(self) -> bool:
        """Whether a worker of this sweep has reported progress (so workers can start)."""
        try:
            return any(p.stat().st_mtime >= self.t0 for p in self.progress_dir.glob("*.json"))
        except OSError:
            return False

    def _steps_now(self, in_flight: Sequence[int]) -> int:
        """Steps done in all runs, those of in-flight runs as their workers report them; an
        in-flight run is "running" once its worker has reported, "pending" (queued) before."""
        flying = set(in_flight)
        steps = sum(r["completed_steps"] for j, r in enumerate(self.records) if j not in flying)
        for i in flying:
            rec = self.records[i]
            p = self.progress_dir / f"{self.grid.runs[i].id}.json"
            try:
                steps += int(json.loads(p.read_text())["done"])
            except (OSError, ValueError, KeyError, TypeError):
                steps += rec["completed_steps"]
            else:
                if rec["status"] == "pending":
                    rec["status"] = "running"
                    self.dirty = self.worked = True
        return steps

    def run(self) -> bool:
        grid = self.grid
        with contextlib.suppress(OSError):
            self.progress_dir.mkdir(exist_ok=True)
            self.stop_file.unlink(missing_ok=True)  # left by a coordinator that was killed
        try:
            old = json.loads(grid.manifest.read_text(encoding="utf-8"))
            before = {r["id"]: r for r in old["runs"]}
        except (OSError, ValueError, KeyError, TypeError):
            before = {}
        self.records = [self._record(s, _file_state(s), before.get(s.id, {})) for s in grid.runs]
        # longest runs first (by steps, then grid order): the last runs to finish are then
        # short ones, so workers fall idle together at the end (LPT scheduling)
        todo: deque[tuple[float, int]] = deque(
            sorted(
                ((0.0, i) for i, r in enumerate(self.records) if r["status"] != "complete"),
                key=lambda item: -grid.runs[item[1]].config.run.steps,
            )
        )
        self.skipped = skipped = len(grid.runs) - len(todo)
        if self.store is not None:
            self._store_complete_runs()
        self.dirty = True
        self.write_manifest(force=True)
        total_steps = sum(s.config.run.steps for s in grid.runs)
        if self.monitor is not None:
            self.monitor.start(len(grid.runs), skipped)
        in_flight: dict[cf.Future[Any], int] = {}
        busy_since: dict[int, float] = {}
        interrupted = False
        cap, cap_checked, scanned = self._capacity(len(grid.runs)), time.monotonic(), 0.0
        try:
            while todo or in_flight:
                now = time.monotonic()
                if now - cap_checked > 5.0:  # a Dask cluster may grow or shrink
                    cap, cap_checked = self._capacity(len(grid.runs)), now
                for _ in range(len(todo)):
                    if len(in_flight) >= cap:
                        break
                    not_before, i = todo.popleft()
                    if not_before > now:
                        todo.append((not_before, i))
                        continue
                    rec = self.records[i]
                    rec["attempts"] += 1
                    rec["status"], rec["error"] = "pending", ""  # queued: "running" once started
                    with contextlib.suppress(OSError):  # a lost attempt's
                        (self.progress_dir / f"{grid.runs[i].id}.json").unlink()
                    try:
                        in_flight[self.pool.submit(run_task, self._task(i))] = i
                    except Exception as exc:  # a broken pool, a closed client, a lost scheduler
                        rec["attempts"] -= 1
                        if self.local is not None:  # our pool broke: its futures tell which
                            todo.appendleft((0.0, i))
                            if not in_flight:
                                self.local.renew()
                                self.pool = self.local.pool
                            break
                        raise LieflowError(
                            f"the executor refused to run more runs ({type(exc).__name__}: "
                            f"{exc}); the manifest records where the sweep stands. To fix: "
                            "restart the executor (the Dask scheduler and workers) and run "
                            "the sweep again: it continues where it stopped."
                        ) from None
                    self.dirty = True
                done, _ = cf.wait(list(in_flight), timeout=0.5, return_when=cf.FIRST_COMPLETED)
                broken = False
                for fut in done:
                    i = in_flight.pop(fut)
                    broken |= self._collect(fut, i, todo, busy_since)
                if broken and self.local is not None:
                    for fut, i in list(in_flight.items()):  # the whole pool died with it
                        in_flight.pop(fut)
                        self._collect(fut, i, todo, busy_since)
                    self.local.renew()
                    self.pool = self.local.pool
                if time.monotonic() - scanned >= 0.5 or not in_flight:
                    scanned = time.monotonic()
                    steps = self._steps_now(list(in_flight.values()))
                    if self.monitor is not None:
                        self.monitor.update(self.counts(), steps, total_steps)
                self.write_manifest()
        except KeyboardInterrupt:
            interrupted = True
            self._interrupt(in_flight, todo)
        finally:
            if self.monitor is not None:
                self.monitor.stop()
            self.write_manifest(force=True)
            if self.store is not None:
                _consolidate(self.store)
        return interrupted

    def _store_complete_runs(self) -> None:
        """Create the Zarr store and write into it the complete runs it lacks (a sweep
        run before without ``store``); the runs still to run are written by their workers."""
        import zarr

        from .datasets import _STORED, write_zarr_run

        store = self.store
        if store is None:  # pragma: no cover - called only with a store
            return
        root = zarr.open_group(str(store), mode="a")
        for spec, rec in zip(self.grid.runs, self.records, strict=True):
            if rec["status"] != "complete":
                continue
            group = root.get(spec.id)
            if group is not None and group.attrs.get(_STORED) == rec["completed_steps"]:
                continue
            with contextlib.suppress(LieflowError, OSError):
                write_zarr_run(spec.output, store, spec.id)

    def _collect(
        self,
        fut: cf.Future[Any],
        i: int,
        todo: deque[tuple[float, int]],
        busy_since: dict[int, float],
    ) -> bool:
        """Record a finished future; requeue a lost or busy run. True if the pool broke."""
        rec = self.records[i]
        spec = self.grid.runs[i]
        broken = False
        try:
            out = fut.result(timeout=0)
            self.worked = True
        except cf.CancelledError:
            rec["status"] = "pending"
            return False
        except Exception as exc:  # the task did not run to its end: the worker died ...
            from concurrent.futures.process import BrokenProcessPool

            broken = isinstance(exc, BrokenProcessPool)
            if broken and self.local is not None and not (self.worked or self._started_any()):
                raise LieflowError(
                    "the sweep's worker processes could not start (they died before running "
                    f"any run: {exc}). If lieflow.sweep is called from a script, protect the "
                    'call with `if __name__ == "__main__":` (Python starts the workers by '
                    "importing the script, as for any process pool); otherwise see the "
                    'workers\' errors above, or pass executor="dask" or another Executor.'
                ) from None
            state = _file_state(spec)
            if _is_complete(spec, state):
                out = {"status": "complete", **(state or {})}
            elif rec["attempts"] < self.max_attempts:
                rec["status"] = "pending"
                rec["error"] = f"attempt {rec['attempts']}: {type(exc).__name__}: {exc}"
                todo.append((time.monotonic() + 0.5 * rec["attempts"], i))
                self.dirty = True
                return broken
            else:
                out = {
                    "status": "failed",
                    "error": f"{type(exc).__name__}: {exc} (the task "
                    f"was lost {rec['attempts']} times; its file stays resumable)",
                }
        if out["status"] == "busy":
            first = busy_since.setdefault(i, time.monotonic())
            if time.monotonic() - first < self.busy_timeout:
                rec["attempts"] -= 1  # waiting for another writer is not an attempt
                rec["status"] = "pending"
                rec["error"] = out["error"]
                todo.append((time.monotonic() + min(5.0, 0.5 + (time.monotonic() - first)), i))
                self.dirty = True
                return broken
            out["status"] = "failed"
        busy_since.pop(i, None)
        for key in (
            "status",
            "error",
            "completed_steps",
            "requested_steps",
            "new_steps",
            "wall_time",
            "max_energy_error",
            "host",
            "pid",
            "traceback",
            "threads",
            "store_error",
        ):
            if key in out:
                rec[key] = out[key]
        rec["error"] = out.get("error", "") if out["status"] == "failed" else ""
        if rec["status"] not in STATUSES:  # pragma: no cover
            rec["status"] = "failed"
        state = _file_state(spec)
        if state is not None:
            rec["completed_steps"] = state["completed_steps"]
            rec["wall_time"] = state["wall_time"]
        with contextlib.suppress(OSError):
            (self.progress_dir / f"{spec.id}.json").unlink()
        self.dirty = True
        if self.monitor is not None:
            self.monitor.finished(rec)
        return broken

    def _interrupt(
        self, in_flight: dict[cf.Future[Any], int], todo: deque[tuple[float, int]]
    ) -> None:
        """Ctrl-C: stop what runs, where it runs (files marked interrupted), and collect it.

        The stop file stops every run at its next chunk of steps, and a task that starts
        after it returns at once; the default pool's workers also get SIGTERM. Futures are
        then waited for (not cancelled: a cancelled Dask task is killed mid-write, its run
        recorded "pending" with 0 steps) so each run's record says where it stopped."""
        with contextlib.suppress(OSError):
            self.stop_file.touch()
        if self.local is not None:
            for fut in in_flight:
                fut.cancel()
            self.local.stop_workers()
        deadline = time.monotonic() + 60.0
        pending = [f for f in in_flight if not f.cancelled()]
        with contextlib.suppress(Exception):
            cf.wait(pending, timeout=max(0.0, deadline - time.monotonic()))
        with contextlib.suppress(OSError):
            self.stop_file.unlink(missing_ok=True)
        for fut, i in in_flight.items():
            if fut.done() and not fut.cancelled():
                with contextlib.suppress(Exception):
                    self._collect(fut, i, deque(), {})
            rec = self.records[i]
            if rec["status"] in ("running", "pending", "interrupted"):
                # the file's own word: a worker stopped twice (the stop file, then SIGTERM
                # while it closed the file) reports "interrupted" without its steps
                state = _file_state(self.grid.runs[i])
                rec["status"] = "interrupted" if state else "pending"
                if state:
                    rec["completed_steps"] = state["completed_steps"]
        self.dirty = True
