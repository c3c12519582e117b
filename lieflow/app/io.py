"""HDF5 trajectory files: a writer that saves as the run proceeds, a reader, and resume.

The files are netCDF-4 files (HDF5 with named dimensions: ``xarray.open_dataset(path,
engine="h5netcdf")`` opens them, and every netCDF tool). File layout (format
``lieflow-trajectory``, format version 2)::

    /                         attributes: lieflow version, the configuration's full text and
                              identity, system / scheme / solver, h, save_every, requested
                              and completed steps, status, wall time, platform and versions
      dimensions              time (unlimited), step (unlimited), [ensemble], row, col,
                              casimir
    /time, /saved_step        t = k h and k of the saved states (every save_every-th step
                              and the last); ``time`` is the coordinate of ``time``
    /W                        saved states (time, [ensemble], row, col)
    /step                     k = 0..K, the coordinate of ``step`` (K = completed steps)
    /energy                   eta(W_k) (step, [ensemble])
    /energy_error             |eta(W_k) - eta(W_0)| / |eta(W_0)|
    /casimirs                 Casimirs C_j(W_k) (step, [ensemble], casimir)
    /casimir_drift            |C_j(W_k) - C_j(W_0)| / ||W_0||^{k_j}
    /iterations, /residual    solver updates and last relative update of step k (step);
                              0 and NaN at step 0
    /ensemble, /casimir       labels: the members' seeds (or 0..K-1), the powers j
    /initial/W0               the initial condition ([ensemble], row, col)
    /diagnostics/extra/step, t, <name>  optional: a system's own diagnostics
                              (``system.extra_diagnostics(W) -> {name: array}``) at step 0
                              and every ``system.diagnostics_every``-th step (default:
                              save_every; 0: none), rows up to the checkpoint, on the
                              unlimited dimension ``sample`` (:func:`read_extra`)
    /checkpoint/slot0, slot1  (W, warm) at a step, written alternately; the root group's
                              "current" attribute names the valid one and is set last; a
                              slot's non-array values are its JSON attribute ``scalars``

Complex states are stored in the committed compound type ``_PFNC_DOUBLE_COMPLEX_TYPE``
{r, i} (the nc-complex convention, as h5netcdf writes complex numbers), which h5py, h5netcdf
and xarray read as complex and netCDF-C as a compound. Every attribute is a string, a
number or a 1-D array of numbers. Files of format version 1 (``/trajectory/step, t, W``,
``/diagnostics/<name>`` with ``iterations`` and ``residual`` of steps 1..K only, no
dimensions, slot values as attributes) are read, and resumed in their own layout.

All datasets are chunked and resizable. Per-step diagnostics are buffered between saves; at
every save the buffers are appended, the state is checkpointed (step index, ``W`` and the
scheme's ``warm`` start) and the file is flushed. A run stopped at any moment — Ctrl-C, a
kill, a power cut after the last flush — therefore leaves a readable file whose checkpoint is
consistent, and :func:`run` with ``resume=True`` truncates whatever was written after the
checkpoint and continues bit-for-bit as if never stopped (same states, same diagnostics).
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import hashlib
import json
import os
import platform
import re
import socket
import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Literal

import attrs
import numpy as np

from .. import _signals, driver, tree
from ..algebras import Array
from ..driver import Cadence, Chunk, ChunkDiagnostics, Diagnostics, Monitor
from ..errors import ConvergenceError, InputError, LieflowError
from ..flows import WarmStart
from ..sinks import Ending, RunInfo, Sink, to_host
from ..solution import Solution, Status
from .config import ConfigError, RunSetup, identity_changes

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no advisory locks (see _OutputLock)
    fcntl = None  # type: ignore[assignment]

if TYPE_CHECKING:  # pragma: no cover
    import h5py

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "Checkpoint",
    "DamagedOutputError",
    "DiskFullError",
    "Monitor",
    "OutputBusyError",
    "RunDiagnostics",
    "RunSummary",
    "Trajectory",
    "TrajectoryHeader",
    "TrajectoryWriter",
    "checkpoint_digest",
    "environment",
    "format_version",
    "read_checkpoint",
    "read_diagnostics",
    "read_extra",
    "read_trajectory",
    "run",
    "run_flow",
]

FORMAT = "lieflow-trajectory"
#: The layout written: 2 (netCDF-4: variables at the root, named dimensions); files of
#: version 1 (groups /trajectory and /diagnostics, no dimensions) are read and resumed.
FORMAT_VERSION = 2
_TINY = float(np.finfo(float).tiny)
_PER_STEP = ("energy", "energy_error", "casimirs", "casimir_drift")
_PER_UPDATE = ("iterations", "residual")
#: Group of the optional per-sample diagnostics a system provides.
_EXTRA = "diagnostics/extra"


@attrs.frozen
class _Layout:
    """Where a format version keeps each array of a trajectory file.

    ``paths`` maps ``saved_step``, ``time``, ``W``, ``W0``, the per-step diagnostics and
    ``step`` (version 2 only) to dataset paths; ``update_row0`` is the row of step 0 in
    ``iterations`` and ``residual`` (-1 in version 1, which has no row for step 0).
    """

    version: int
    paths: Mapping[str, str]
    update_row0: int

    @property
    def netcdf(self) -> bool:
        """Whether the file follows netCDF-4 (named dimensions on every dataset)."""
        return self.version >= 2

    def update_rows(self, k: int) -> slice:
        """Rows of ``iterations`` / ``residual`` holding steps ``1..k``."""
        return slice(1 + self.update_row0, k + 1 + self.update_row0)


_NAMES = ("energy", "energy_error", "casimirs", "casimir_drift", "iterations", "residual")
_V1_PATHS = {"saved_step": "trajectory/step", "time": "trajectory/t", "W": "trajectory/W"}
_V2_PATHS = {"saved_step": "saved_step", "time": "time", "W": "W", "step": "step"}
_LAYOUTS = {
    1: _Layout(
        1,
        MappingProxyType(
            {**_V1_PATHS, "W0": "initial/W0", **{n: f"diagnostics/{n}" for n in _NAMES}}
        ),
        -1,
    ),
    2: _Layout(2, MappingProxyType({**_V2_PATHS, "W0": "initial/W0", **{n: n for n in _NAMES}}), 0),
}
#: Checkpoint slots store the flow's state leaf by leaf under ``warm/<path>`` (a scheme's
#: :class:`~lieflow.flows.WarmStart`: ``warm/last``, ``warm/previous/0``, ...,
#: ``warm/trusted``; files written before the deeper warm starts: ``warm/previous``).
_STATE = "warm"
_HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_DIGEST = "sha256"
#: Errors h5py raises on a file whose bytes are damaged (a bad checksum, a broken B-tree).
_DAMAGE = (OSError, KeyError, RuntimeError, ValueError, TypeError, IndexError, AttributeError)


class OutputBusyError(LieflowError):
    """Another process is writing the output file (or holds its lock)."""


class DiskFullError(LieflowError):
    """The disk filled up while a trajectory file was written; the file keeps its last
    checkpoint, and the same command continues it once space is freed."""


#: What h5py raises when a write fails: OSError from a write, RuntimeError from a flush or
#: a close whose metadata cache could not be written.
_WRITE_ERRORS = (OSError, RuntimeError)


def _no_space(exc: BaseException) -> bool:
    """Whether ``exc`` (or what it was raised from) is a full disk or an exceeded quota."""
    while exc is not None:
        if isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return True
        text = str(exc)
        if "No space left on device" in text or "errno = 28," in text or "quota" in text.lower():
            return True
        exc = exc.__cause__ or exc.__context__  # type: ignore[assignment]
    return False


def _disk_full(path: Path, steps: int | None = None) -> DiskFullError:
    kept = (
        f"the file keeps its last checkpoint (step {steps}); nothing before it is lost"
        if steps is not None
        else "nothing was changed or lost"
    )
    return DiskFullError(
        f"no space left on device writing {_where(path)}: {kept}. To fix: free space on that "
        "disk and run the same command again to continue (`lieflow run CONFIG --resume`, or "
        "integrate(..., out=..., resume=True))."
    )


#: Free space kept in reserve on the output's disk: a write is not started unless this much
#: (plus what it writes) is free, because HDF5 interrupted by a full disk can leave the
#: file's superblock pointing past its end (measured: a resume on a full disk made the file
#: unopenable, "addr overflow"). Enough for the metadata and new chunks of a few commits.
_SPACE_MARGIN = 1 << 20


def _ensure_space(path: Path, nbytes: int = 0) -> None:
    """Raise ENOSPC (before anything is written) unless ``nbytes`` plus the margin are free
    on the disk holding ``path``."""
    try:
        st = os.statvfs(path.parent)
    except (OSError, AttributeError):  # pragma: no cover - no statvfs: HDF5 reports it
        return
    if st.f_bavail * st.f_frsize < nbytes + _SPACE_MARGIN:
        raise OSError(errno.ENOSPC, "No space left on device", str(path))


def _close_quietly(f: Any) -> None:
    """Close an h5py file whose writes failed (its close may fail too: the error is moot)."""
    with contextlib.suppress(*_WRITE_ERRORS, ValueError):
        f.close()


class DamagedOutputError(LieflowError):
    """The output file's bytes are damaged: a checksum does not match, its structure is
    broken, or a process killed during a write left part of it unreadable."""


#: Default seconds between the checkpoints of a trajectory file (:class:`TrajectoryHeader`).
CHECKPOINT_SECONDS = 1.0
#: Saved states are written ahead of the next checkpoint once the buffer holds this many
#: bytes of them (a resume drops such rows until a checkpoint covers them): thousands of
#: small states per write, a large one at once.
_BUFFER_BYTES = 1 << 16


@attrs.frozen(eq=False)
class TrajectoryHeader(RunInfo):
    """What a :class:`TrajectoryWriter` needs to know about a run: the file's header, the
    run's :class:`~lieflow.sinks.RunInfo` (system, names, ``h``, ``save_every``,
    ``requested_steps``, ``identity``, ``W0``) and where and how to write it.

    ``lieflow run`` builds it from its configuration (:meth:`lieflow.app.config.RunSetup.header`),
    :func:`lieflow.integrate` with ``out=`` from its arguments (:func:`trajectory_sink`).

    Attributes
    ----------
    output : Path
        The trajectory file.
    replace : bool
        Whether a new run may replace an existing ``output``.
    make_directory : bool
        Whether a missing directory of ``output`` is created (``lieflow run``: yes, as
        ``--out results/run.h5`` promises) or refused (:func:`lieflow.integrate`: a library
        call creates no directory tree its caller did not ask for).
    config_text, config_source : str
        The configuration's text and where it came from (empty for ``integrate``).
    checkpoint_seconds : float or None
        Seconds between checkpoints (the resume point, flushed and fsync'd; and the last
        one when the run ends however it ends): saved states and diagnostics are buffered
        and written in blocks in between. ``0``: after every chunk of steps; ``None``:
        after every chunk that holds a saved state (``[run] checkpoint = "saves"``).
    """

    output: Path
    replace: bool = False
    config_text: str = attrs.field(default="", repr=False)
    make_directory: bool = False
    config_source: str = ""
    checkpoint_seconds: float | None = CHECKPOINT_SECONDS


def _header(run: TrajectoryHeader | RunSetup) -> TrajectoryHeader:
    """``run`` as a :class:`TrajectoryHeader` (a :class:`RunSetup` builds its own)."""
    return run if isinstance(run, TrajectoryHeader) else run.header()


def _h5py() -> Any:
    try:
        import h5py
    except ImportError as exc:  # pragma: no cover - h5py is in the cli extra
        raise LieflowError(
            "HDF5 output needs the 'h5py' package. To fix: pip install 'lieflow[cli]'."
        ) from exc
    return h5py


def environment() -> dict[str, str]:
    """Versions and platform recorded in every output (lieflow, Python, numpy, scipy, h5py)."""
    import scipy

    from .. import __version__

    info = {
        "lieflow_version": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }
    try:
        import h5py

        info["h5py"] = h5py.__version__
        info["hdf5"] = h5py.version.hdf5_version
    except ImportError:  # pragma: no cover
        pass
    return info


@attrs.frozen(eq=False)
class Checkpoint:
    """A resumable state: ``W`` after step ``step`` and the flow's state then, stored leaf
    by leaf (:mod:`lieflow.tree`: ``leaves`` maps each leaf's path to its value)."""

    step: int
    t: float
    W: Array = attrs.field(repr=False)
    leaves: Mapping[str, Any] = attrs.field(repr=False)

    def state(self, template: Any) -> Any:
        """The flow's state, shaped like ``template`` (the flow's ``init(W0)``)."""
        return tree.rebuild(template, dict(self.leaves))

    @property
    def warm(self) -> WarmStart:
        """The state of a run of one scheme: its :class:`~lieflow.flows.WarmStart`, keeping
        as many solutions as the run did (``previous/0``, ``previous/1``, ... are stored,
        filled or not; older files store one ``previous`` array)."""
        kept = sum(1 for key in self.leaves if re.fullmatch(r"previous/\d+", key))
        state = self.state(WarmStart.keeping(kept + 1) if kept else WarmStart())
        return state if isinstance(state, WarmStart) else WarmStart()


@attrs.frozen(eq=False)
class Trajectory:
    """The contents of a trajectory file (:func:`read_trajectory`).

    Attributes
    ----------
    path : Path
        The file.
    meta : Mapping
        Root attributes (configuration text, versions, status, ...).
    step, t, W : ndarray
        Saved states: step indices, times and states.
    energy, energy_error, casimirs, casimir_drift : ndarray
        Per-step diagnostics for steps ``0..completed_steps``.
    iterations, residual : ndarray
        Per-step solver updates and last relative update, steps ``1..completed_steps``.
    checkpoint : Checkpoint
        The last checkpoint.
    """

    path: Path
    meta: Mapping[str, Any] = attrs.field(repr=False)
    step: Array = attrs.field(repr=False)
    t: Array = attrs.field(repr=False)
    W: Array = attrs.field(repr=False)
    energy: Array = attrs.field(repr=False)
    energy_error: Array = attrs.field(repr=False)
    casimirs: Array = attrs.field(repr=False)
    casimir_drift: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    residual: Array = attrs.field(repr=False)
    checkpoint: Checkpoint

    @property
    def h(self) -> float:
        """Step size."""
        return float(self.meta["h"])

    @property
    def status(self) -> str:
        """``"running"`` (or killed), ``"interrupted"``, ``"failed"`` or ``"complete"``."""
        return str(self.meta["status"])

    @property
    def completed_steps(self) -> int:
        """Steps recorded (the checkpoint's step index)."""
        return self.checkpoint.step

    @property
    def step_times(self) -> Array:
        """Times ``k h`` of the per-step diagnostics, ``k = 0..completed_steps``."""
        return np.arange(self.completed_steps + 1) * self.h


def _where(path: Path) -> str:
    return repr(str(path))


def _as_path(path: object, what: str = "path") -> Path:
    """``path`` as a :class:`Path`, or :class:`InputError` for anything else."""
    if isinstance(path, (str, os.PathLike)) and str(path):
        return Path(path)
    raise InputError(
        f"{what} must be a file path (str or pathlib.Path), got {path!r}. To fix: pass the "
        "path of a file written by `lieflow run`."
    )


def _check_signature(path: Path, fix: str) -> None:
    """Refuse a path that is missing, a directory, empty or not HDF5, reading 8 bytes only
    (nothing is opened for writing, so a refused file is left exactly as it was)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(_HDF5_SIGNATURE))
    except FileNotFoundError:
        raise LieflowError(
            f"{_where(path)} does not exist. To fix: check the path, or run the configuration "
            "first."
        ) from None
    except IsADirectoryError:
        raise LieflowError(
            f"{_where(path)} is a directory, not a trajectory file. To fix: give the path of "
            "the .h5 file written by `lieflow run`."
        ) from None
    except OSError as exc:
        raise LieflowError(
            f"cannot read {_where(path)}: {exc.strerror or exc}. To fix: check the path and "
            "its permissions."
        ) from None
    if not head:
        raise LieflowError(
            f"{_where(path)} is empty (0 bytes), not a lieflow trajectory file (lieflow never "
            f"leaves an empty file: it writes under a temporary name first). To fix: {fix}."
        )
    if head != _HDF5_SIGNATURE:
        raise LieflowError(
            f"{_where(path)} is not an HDF5 file (it does not start with the HDF5 signature), "
            f"so it is not a lieflow trajectory file. To fix: {fix}."
        )


_READ_FIX = "check the path; give a file written by `lieflow run`"
_RESUME_FIX = (
    "check the path; to start a new run there instead, drop --resume and pass --force "
    "(which replaces the file)"
)


#: HDF5's chunk cache per open dataset, in bytes. None: the writer stores whole chunks (a state, a
#: checkpoint slot's arrays, a chunk of diagnostic rows per save) and reads whole datasets,
#: so a cache would only hold memory — HDF5 keeps a chunk-sized buffer for every dataset
#: it cached (measured: one state per open slot dataset, 12 of them with five-deep warm
#: starts, which took a streamed N = 512 run from 15 to 28 states of peak memory).
_CHUNK_CACHE_BYTES = 0


def _open(path: Path, mode: str, fix: str = _READ_FIX) -> h5py.File:
    h5py = _h5py()
    _check_signature(path, fix)
    try:
        return h5py.File(path, mode, rdcc_nbytes=_CHUNK_CACHE_BYTES)
    except FileNotFoundError:
        raise LieflowError(
            f"{_where(path)} does not exist. To fix: check the path, or run the configuration "
            "first."
        ) from None
    except OSError as exc:
        if _HDF5_LOCKED.search(str(exc)):
            raise OutputBusyError(
                f"cannot open {_where(path)}: another process has it open for writing "
                f"({exc}). To fix: wait until that run has finished, or stop it first."
            ) from None
        what = "truncated (shorter than HDF5 recorded)" if "truncated file" in str(exc) else (
            "damaged")  # fmt: skip
        raise DamagedOutputError(
            f"cannot open {_where(path)} as HDF5: the file is {what} ({exc}). To fix: "
            f"{salvage_fix(path)}; or {fix}."
        ) from None


#: HDF5's own message when another process holds its lock on the file: the only open
#: error that means "busy" (a truncated file's message names ``sblock``, not a lock).
_HDF5_LOCKED = re.compile(r"unable to lock file", re.IGNORECASE)


def salvage_fix(path: Path) -> str:
    """The fix offered for a damaged trajectory file: :func:`lieflow.app.salvage.salvage`."""
    return (
        f"`lieflow salvage {path}` cuts it back to its last verified checkpoint (the damaged "
        "original is kept next to it), then continue it with --resume"
    )


def _damaged(path: Path, exc: BaseException) -> DamagedOutputError:
    return DamagedOutputError(
        f"{_where(path)} is damaged: reading it failed ({type(exc).__name__}: {exc}). Its "
        "bytes were changed on disk (a checksum did not match, e.g. after a process was "
        "killed while it wrote, or its structure is broken). "
        f"To fix: {salvage_fix(path)}; or restore it from a backup, or run the configuration "
        "again (--force)."
    )


class _Reading:
    """``with _Reading(path):`` turns h5py's errors on a damaged file into one LieflowError."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self) -> None:
        return None

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: Any
    ) -> Literal[False]:
        if exc is None or isinstance(exc, LieflowError) or not isinstance(exc, _DAMAGE):
            return False
        if _no_space(exc):
            raise _disk_full(self.path) from None
        raise _damaged(self.path, exc) from None


def _check_format(f: h5py.File, path: Path) -> _Layout:
    """The layout of a lieflow trajectory file, or LieflowError for any other file."""
    if _plain(f.attrs.get("format")) != FORMAT:
        raise LieflowError(
            f"{_where(path)} is not a lieflow trajectory file (no format = {FORMAT!r} "
            "attribute). To fix: pass a file written by `lieflow run`."
        )
    version = _plain(f.attrs.get("format_version", 1))
    layout = _LAYOUTS.get(version) if isinstance(version, int) else None
    if layout is None:
        raise LieflowError(
            f"{_where(path)} is a lieflow trajectory file of format version {version!r}, "
            f"which this lieflow cannot read (it reads versions 1 to {FORMAT_VERSION}). To "
            "fix: read it with the newer lieflow that wrote it (pip install -U lieflow)."
        )
    return layout


def format_version(path: Path | str) -> int:
    """The format version of a trajectory file (1: groups, no dimensions; 2: netCDF-4)."""
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        return _check_format(f, p).version


# -- checkpoint integrity -----------------------------------------------------------------


def _canonical(value: Any) -> tuple[bytes, memoryview]:
    """What identifies a checkpoint item (an array, a scalar, a string or ``None``): a
    header and, for an array, its contiguous data as a buffer (hashed where it lies, never
    copied: a checkpoint of a large state would otherwise allocate two more states)."""
    if value is None:
        return b"none", memoryview(b"")
    if isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        return f"array:{a.dtype.str}:{a.shape}:".encode(), a.reshape(-1).view(np.uint8).data
    value = _plain(value)
    return f"{type(value).__name__}:{value!r}".encode(), memoryview(b"")


def checkpoint_digest(step: int, t: float, items: Mapping[str, Any]) -> str:
    """SHA-256 of a checkpoint: its step index, time and every item it stores.

    ``items`` maps the names stored in the checkpoint slot (``"W"``, ``"warm/last"``, ...)
    to their values; arrays are hashed with their dtype and shape, other values by type and
    ``repr`` (``None`` is stored as ``"none"``). The writer stores the digest in the slot's
    ``sha256`` attribute and every reader recomputes it from what it reads back.
    """
    h = hashlib.sha256(f"lieflow-checkpoint;step={int(step)};t={float(t).hex()};".encode())
    for key in sorted(items):
        head, data = _canonical(items[key])
        h.update(key.encode() + b"=" + (len(head) + data.nbytes).to_bytes(8, "little"))
        h.update(head)
        h.update(data)
    return h.hexdigest()


_SLOT_ATTRS = ("step", "t", _DIGEST)
#: Version 2 stores a slot's non-array items (``None``, booleans, numbers, strings) as one
#: JSON attribute, so that every attribute is a plain netCDF string or number.
_SCALARS = "scalars"


def _slot_items(slot: h5py.Group) -> dict[str, Any]:
    """Everything a checkpoint slot stores except step, t and the digest: datasets by path
    (arrays; dimension scales are not items) and the other values (version 1: one attribute
    each, ``"none"`` read back as ``None``; version 2: the JSON attribute ``scalars``)."""
    h5py = _h5py()
    items: dict[str, Any] = {}

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset) and not _is_scale(obj):
            items[name] = np.asarray(obj[()])

    slot.visititems(visit)
    for key, raw in slot.attrs.items():
        if key == _SCALARS:
            items.update(json.loads(_plain(raw)))
        elif key not in _SLOT_ATTRS:
            value = _plain(raw)
            items[key] = None if isinstance(value, str) and value == "none" else value
    return items


def _read_checkpoint(f: h5py.File, path: Path | None = None) -> Checkpoint:
    """The current checkpoint, its SHA-256 verified (files written before lieflow stored
    digests have none and are read as they are)."""
    where = _where(Path(f.filename) if path is None else path)
    group = f["checkpoint"]
    slot_id = int(group.attrs["current"])
    if slot_id not in (0, 1):
        raise LieflowError(
            f"{where} is damaged: its checkpoint pointer is {slot_id}, not 0 or 1. To fix: "
            f"{salvage_fix(Path(f.filename))}; or run the configuration again (--force)."
        )
    slot = group[f"slot{slot_id}"]
    step, t = int(slot.attrs["step"]), float(slot.attrs["t"])
    items = _slot_items(slot)
    stored = slot.attrs.get(_DIGEST)
    if stored is not None and _plain(stored) != checkpoint_digest(step, t, items):
        raise LieflowError(
            f"{where} is damaged: the checkpoint at step {step} does not match its SHA-256 "
            "checksum (its bytes changed on disk after lieflow wrote them), so continuing "
            "from it would silently continue a wrong state. To fix: "
            f"{salvage_fix(Path(f.filename))}; or restore the file from a backup, or run the "
            "configuration again from the start (--force)."
        )
    if "W" not in items:
        raise LieflowError(f"{where} is damaged: its checkpoint has no state W.")
    leaves = {
        key[len(_STATE) + 1 :]: value
        for key, value in items.items()
        if key == _STATE or key.startswith(f"{_STATE}/")
    }
    return Checkpoint(step, t, items["W"], MappingProxyType(leaves))


def _check_lengths(f: h5py.File, k: int, path: Path, layout: _Layout) -> None:
    """The diagnostics reach the checkpoint at step ``k`` (rows after it are dropped later)."""
    at = layout.paths
    per_step = [f[at[n]].shape[0] for n in (*_PER_STEP, *(("step",) if "step" in at else ()))]
    if min(per_step) < k + 1 or f[at["iterations"]].shape[0] < k + 1 + layout.update_row0:
        raise LieflowError(
            f"{_where(path)} is damaged: its diagnostics end before its checkpoint at step "
            f"{k}. To fix: {salvage_fix(Path(f.filename))}; or start the run again without "
            "--resume (use --force)."
        )


def _check_invariants(
    f: h5py.File, ck: Checkpoint, system: Any, path: Path, layout: _Layout
) -> None:
    """The checkpointed state reproduces the energy and Casimirs recorded for its step."""
    k = ck.step
    at = layout.paths
    H, C = system.hamiltonian(ck.W), system.casimirs(ck.W)
    H_rec, C_rec, H0 = f[at["energy"]][k], f[at["casimirs"]][k], f[at["energy"]][0]
    scale_H = np.maximum(np.maximum(np.abs(H_rec), np.abs(H0)), _TINY)
    scale_C = system.casimir_scale(f[at["W0"]][()])
    bad = []
    if np.shape(H) != np.shape(H_rec) or not np.all(np.abs(H - H_rec) <= 1e-10 * scale_H):
        bad.append(f"energy {np.max(H)!r} (recorded {np.max(H_rec)!r})")
    if np.shape(C) != np.shape(C_rec) or not np.all(np.abs(C - C_rec) <= 1e-10 * scale_C):
        bad.append("Casimirs")
    if bad:
        raise LieflowError(
            f"{_where(path)} is damaged: the state checkpointed at step {k} does not reproduce "
            f"the invariants recorded for that step ({', '.join(bad)}), so continuing from it "
            "would continue a wrong state. To fix: restore the file from a backup, or run the "
            "configuration again from the start (--force)."
        )


def _check_coordinates(f: h5py.File, k: int, path: Path, layout: _Layout) -> None:
    """Version 2: read the coordinate variables a reader does not otherwise read (so that
    their Fletcher-32 checksums are verified) and check the step axis counts ``0..k``."""
    if not layout.netcdf:
        return
    steps = f[layout.paths["step"]][: k + 1]
    for name in _LABELS:
        if name in f:
            f[name][()]
    if not np.array_equal(steps, np.arange(k + 1)):
        raise LieflowError(
            f"{_where(path)} is damaged: its step coordinate is not 0..{k}. To fix: restore "
            "it from a backup, or run the configuration again (--force)."
        )


def _readable_rows(ds: h5py.Dataset, rows: int | None = None) -> int:
    """How many of the first ``rows`` rows of ``ds`` (default: all) read back, every chunk's
    Fletcher-32 checksum verified: read chunk by chunk, so memory holds one chunk."""
    n = ds.shape[0] if rows is None else min(rows, ds.shape[0])
    if not ds.shape:
        try:
            ds[()]
        except _DAMAGE:
            return 0
        return 1
    size = (ds.chunks or (max(n, 1),))[0]
    for start in range(0, n, size):
        try:
            ds[start : min(start + size, n)]
        except _DAMAGE:
            return start
    return n


def _kept_rows(f: h5py.File, k: int, layout: _Layout) -> dict[str, tuple[h5py.Dataset, int]]:
    """Every dataset a file that ends at step ``k`` keeps, with the rows it keeps of it."""
    at = layout.paths
    rows: dict[str, tuple[h5py.Dataset, int]] = {}
    for name in (*_PER_STEP, *(("step",) if "step" in at else ())):
        rows[at[name]] = (f[at[name]], k + 1)
    for name in _PER_UPDATE:
        rows[at[name]] = (f[at[name]], k + 1 + layout.update_row0)
    n_saved = int(np.searchsorted(f[at["saved_step"]][()], k, side="right"))
    for name in ("saved_step", "time", "W"):
        rows[at[name]] = (f[at[name]], n_saved)
    rows[at["W0"]] = (f[at["W0"]], f[at["W0"]].shape[0] if f[at["W0"]].shape else 1)
    for name in _LABELS:
        if name in f:
            rows[name] = (f[name], f[name].shape[0])
    group = f.get(_EXTRA)
    if group is not None:
        n_extra = int(np.searchsorted(group["step"][()], k, side="right"))
        for ds in group.values():
            if not _is_scale(ds):
                rows[ds.name] = (ds, n_extra)
    return rows


def _check_kept(f: h5py.File, k: int, path: Path, layout: _Layout) -> None:
    """Read back every row a resume keeps (steps ``0..k``), so that a file whose data was
    damaged on disk is refused before it is continued, not reported ``complete``."""
    for name, (ds, rows) in _kept_rows(f, k, layout).items():
        good = _readable_rows(ds, rows)
        if good < rows:
            raise DamagedOutputError(
                f"{_where(path)} is damaged: {name!r} fails its checksum from row {good} on "
                f"(the file keeps {rows} rows of it up to its checkpoint at step {k}; its bytes "
                "changed on disk, e.g. after a process was killed while it wrote). To fix: "
                f"{salvage_fix(path)}; or run the configuration again (--force)."
            )


def _visit_structure(group: h5py.Group) -> None:
    """Open every object under ``group`` and its attributes (their headers), not reading any
    dataset's data: what writing over them needs intact (data is overwritten whole)."""

    def visit(_: str, obj: Any) -> None:
        dict(obj.attrs)

    dict(group.attrs)
    group.visititems(visit)


def _check_spare(f: h5py.File, path: Path) -> None:
    """The spare checkpoint slot, where the next checkpoint goes, has an intact structure
    (a damaged one would fail that write half-way; damaged *data* there is harmless, as
    the next checkpoint overwrites it whole)."""
    group = f["checkpoint"]
    name = f"slot{1 - int(group.attrs['current'])}"
    try:
        _visit_structure(group[name])
    except _DAMAGE as exc:
        raise DamagedOutputError(
            f"{_where(path)} is damaged: its spare checkpoint slot {name!r}, where the next "
            f"checkpoint goes, does not read back ({type(exc).__name__}: {exc}). To fix: "
            f"{salvage_fix(path)}; or run the configuration again (--force)."
        ) from None


@contextmanager
def _opened(path: Path | str) -> Iterator[tuple[h5py.File, Checkpoint, _Layout]]:
    """A trajectory file open for reading, with its verified checkpoint and its layout;
    every reader's checks (format, checksums, diagnostics reaching the checkpoint) done
    once here."""
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        layout = _check_format(f, p)
        ck = _read_checkpoint(f, p)
        _check_lengths(f, ck.step, p, layout)
        _check_coordinates(f, ck.step, p, layout)
        yield f, ck, layout


def read_checkpoint(path: Path | str) -> Checkpoint:
    """The last checkpoint of a trajectory file (its SHA-256 checksum verified).

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, not a lieflow trajectory, or damaged.
    """
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        _check_format(f, p)
        return _read_checkpoint(f, p)


#: Root attributes that belong to the file format, not to the run (netCDF's provenance).
_HIDDEN_ATTRS = ("_NCProperties",)


def _meta(f: h5py.File) -> dict[str, Any]:
    """The root attributes: the run's header (netCDF's own attributes left out)."""
    return {key: _plain(v) for key, v in f.attrs.items() if key not in _HIDDEN_ATTRS}


def read_trajectory(path: Path | str) -> Trajectory:
    """Read a trajectory file, up to its last checkpoint (anything after it is ignored).

    Every dataset lieflow writes carries HDF5's Fletcher-32 chunk checksums and the
    checkpoint a SHA-256 digest, so a file whose bytes changed on disk is refused rather
    than read as wrong numbers (files from lieflow versions before 0.2 have neither).
    Files of both format versions are read (see the module's docstring).

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, not a lieflow trajectory, or damaged.
    """
    with _opened(path) as (f, ck, layout):
        k = ck.step
        at = layout.paths
        saved = f[at["saved_step"]][()]
        n_saved = int(np.searchsorted(saved, k, side="right"))
        updates = layout.update_rows(k)
        return Trajectory(
            path=_as_path(path),
            meta=MappingProxyType(_meta(f)),
            step=saved[:n_saved],
            t=f[at["time"]][:n_saved],
            W=f[at["W"]][:n_saved],
            energy=f[at["energy"]][: k + 1],
            energy_error=f[at["energy_error"]][: k + 1],
            casimirs=f[at["casimirs"]][: k + 1],
            casimir_drift=f[at["casimir_drift"]][: k + 1],
            iterations=f[at["iterations"]][updates],
            residual=f[at["residual"]][updates],
            checkpoint=ck,
        )


@attrs.frozen(eq=False)
class RunDiagnostics:
    """A trajectory file without its saved states (:func:`read_diagnostics`).

    Attributes
    ----------
    completed_steps : int
        The checkpoint's step index ``K``.
    W0, W : ndarray
        The initial state and the checkpointed state after step ``K``.
    energy_error, casimir_drift : ndarray
        Per-step diagnostics, steps ``0..K``.
    iterations : ndarray
        Solver updates of steps ``1..K``.
    """

    completed_steps: int
    W0: Array = attrs.field(repr=False)
    W: Array = attrs.field(repr=False)
    energy_error: Array = attrs.field(repr=False)
    casimir_drift: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)


def read_diagnostics(path: Path | str) -> RunDiagnostics:
    """The per-step diagnostics, the initial and the last checkpointed state of a trajectory
    file — everything but the saved states, so it fits in memory whatever the run's length.

    Raises
    ------
    LieflowError
        The file is missing, not HDF5, not a lieflow trajectory, or damaged.
    """
    with _opened(path) as (f, ck, layout):
        k = ck.step
        at = layout.paths
        return RunDiagnostics(
            completed_steps=k,
            W0=f[at["W0"]][()],
            W=np.asarray(ck.W),
            energy_error=f[at["energy_error"]][: k + 1],
            casimir_drift=f[at["casimir_drift"]][: k + 1],
            iterations=f[at["iterations"]][layout.update_rows(k)],
        )


def read_extra(path: Path | str) -> dict[str, Array]:
    """The system's own diagnostics in a trajectory file (``/diagnostics/extra``): ``step``,
    ``t`` and one array per name, one row per sample up to the last checkpoint; empty if the
    system provides none (no ``extra_diagnostics`` method)."""
    p = _as_path(path)
    with _open(p, "r") as f, _Reading(p):
        _check_format(f, p)
        k = _read_checkpoint(f, p).step
        group = f.get(_EXTRA)
        if group is None:
            return {}
        n = int(np.searchsorted(group["step"][()], k, side="right"))
        return {name: ds[:n] for name, ds in group.items() if not _is_scale(ds)}


def _append_extra(f: h5py.File, rows: list[tuple[int, float, Mapping[str, Any]]]) -> None:
    """Append ``(step, t, {name: value})`` rows to ``/diagnostics/extra`` (datasets are
    created at the first row, shaped like its values; in a netCDF-4 file along the unlimited
    dimension ``sample``, an ensemble's member axis on ``ensemble``)."""
    if not rows:
        return
    netcdf = _is_netcdf(f)
    group = f.get(_EXTRA)
    if group is None:
        group = f.require_group(_EXTRA)
        if netcdf:
            _dimension(group, "sample", 0, unlimited=True)
    columns: dict[str, Array] = {
        "step": np.array([r[0] for r in rows], dtype=np.int64),
        "t": np.array([r[1] for r in rows], dtype=np.float64),
    }
    for name in rows[0][2]:
        columns[name] = np.stack([np.asarray(r[2][name]) for r in rows])
    for name, values in columns.items():
        if name not in group:
            dims = _extra_dims(f, group, name, values.shape[1:]) if netcdf else None
            _growable(group, name, values[0], values.dtype, dims)
        ds = group[name]
        n = ds.shape[0]
        ds.resize(n + len(values), axis=0)
        ds[n:] = values


def _extra_dims(f: h5py.File, group: h5py.Group, name: str, shape: tuple[int, ...]) -> list[Any]:
    """Dimensions of an extra diagnostic: ``sample``, then ``ensemble`` for an axis as long
    as the ensemble's first, then ``<name>_dim<i>`` of the group."""
    dims: list[Any] = [group["sample"]]
    members = f["ensemble"].shape[0] if "ensemble" in f else None
    for i, n in enumerate(shape):
        if i == 0 and n == members:
            dims.append(f["ensemble"])
        else:
            dims.append(_dimension(group, f"{name}_dim{i}", n))
    return dims


def _plain(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _chunk_rows(row_bytes: int, target: int = 1 << 16) -> int:
    return max(1, min(1024, target // max(row_bytes, 1)))


def _growable(
    group: h5py.Group, name: str, row: Array, dtype: Any, dims: Sequence[Any] | None = None
) -> h5py.Dataset:
    """An empty dataset that grows along its first axis, one row shaped like ``row``;
    ``dims`` (netCDF-4 files): the dimension scales of its axes."""
    row = np.asarray(row)
    ds = group.create_dataset(
        name,
        shape=(0, *row.shape),
        maxshape=(None, *row.shape),
        dtype=_stored_dtype(group.file, dtype),
        chunks=(_chunk_rows(row.size * np.dtype(dtype).itemsize), *row.shape),
        fletcher32=True,
    )
    if dims is not None:
        _attach(ds, dims)
    return ds


# -- netCDF-4 ------------------------------------------------------------------------------
#
# A netCDF-4 file is an HDF5 file whose datasets are netCDF variables: every axis of every
# dataset has one HDF5 dimension scale (its netCDF dimension). A dimension with a coordinate
# variable is that variable, made a scale under its own name; one without is an empty
# dataset whose scale name says "not a variable" and its length. Each dimension carries a
# file-wide id (``_Netcdf4Dimid``). Complex numbers are stored as the committed compound
# type ``_PFNC_DOUBLE_COMPLEX_TYPE`` {r, i} (the nc-complex convention: h5py and h5netcdf
# read it as complex, netCDF-C as a compound, nc-complex and netCDF4-python as complex).

_NOT_A_VARIABLE = "This is a netCDF dimension but not a netCDF variable."
_DIMID = "_Netcdf4Dimid"
#: Coordinate variables of the fixed dimensions (labels of the ensemble and Casimirs).
_LABELS = ("ensemble", "casimir")
_COMPLEX_TYPES = {8: "_PFNC_FLOAT_COMPLEX_TYPE", 16: "_PFNC_DOUBLE_COMPLEX_TYPE"}


def _is_netcdf(f: h5py.File) -> bool:
    return _plain(f.attrs.get("format_version", 1)) >= 2


def _is_scale(ds: Any) -> bool:
    """Whether an HDF5 dataset is a dimension scale (a netCDF dimension): HDF5's own test
    (its ``CLASS`` attribute; ~20× faster than reading the attribute through h5py)."""
    h5py = _h5py()
    return isinstance(ds, h5py.Dataset) and bool(h5py.h5ds.is_scale(ds.id))


def _stored_dtype(f: h5py.File, dtype: Any) -> Any:
    """The HDF5 type of ``dtype`` in a netCDF-4 file: complex as the committed compound type
    of the nc-complex convention (created at its first use), anything else as it is."""
    dtype = np.dtype(dtype)
    if dtype.kind != "c" or not _is_netcdf(f):
        return dtype
    name = _COMPLEX_TYPES.get(dtype.itemsize)
    if name is None:  # pragma: no cover - no complex256 state in practice
        return dtype
    if name not in f:
        f[name] = dtype
    return f[name]


def _next_dimid(f: h5py.File) -> int:
    """One more than the largest dimension id in the file (through h5py's low-level API:
    3x faster than ``visititems``, which builds an object per item)."""
    h5py = _h5py()
    ids = [-1]
    key = _DIMID.encode()

    def visit(name: bytes, info: Any) -> None:
        if info.type == h5py.h5o.TYPE_DATASET and info.num_attrs:
            if h5py.h5a.exists(f.id, key, obj_name=name):
                attr = h5py.h5a.open(f.id, key, obj_name=name)
                value = np.zeros(attr.shape, dtype=attr.dtype)
                attr.read(value)
                ids.append(int(value))

    h5py.h5o.visit(f.id, visit, info=True)
    return max(ids) + 1


def _dimension(
    group: h5py.Group, name: str, size: int, *, unlimited: bool = False, dimid: int | None = None
) -> h5py.Dataset:
    """A netCDF dimension without coordinate variable (created if missing; one of another
    length, left by a process killed while it replaced a dataset, is replaced)."""
    if name in group:
        old = group[name]
        if unlimited or old.shape[0] == size:
            return old
        _detach_all(old)
        del group[name]
    kwargs: dict[str, Any] = {"maxshape": (None,), "chunks": (1024,)} if unlimited else {}
    ds = group.create_dataset(name, shape=(size,), dtype=">f4", **kwargs)
    ds.make_scale(f"{_NOT_A_VARIABLE}{size:10d}")
    ds.attrs[_DIMID] = np.int32(_next_dimid(group.file) if dimid is None else dimid)
    return ds


def _coordinate(ds: h5py.Dataset, dimid: int) -> h5py.Dataset:
    """Make a 1-D dataset the coordinate variable of the dimension of its name."""
    ds.make_scale(ds.name.rsplit("/", 1)[-1])
    ds.attrs[_DIMID] = np.int32(dimid)
    return ds


def _attach(ds: h5py.Dataset, dims: Sequence[Any]) -> None:
    """Attach one dimension scale to each axis of ``ds``."""
    for axis, scale in enumerate(dims):
        ds.dims[axis].attach_scale(scale)


def _detach_all(scale: h5py.Dataset) -> None:
    """Detach a dimension scale from every dataset still attached to it."""
    for ref, axis in list(scale.attrs.get("REFERENCE_LIST", [])):
        with contextlib.suppress(*_DAMAGE):
            scale.file[ref].dims[int(axis)].detach_scale(scale)


def _detach(ds: h5py.Dataset) -> None:
    """Detach every dimension scale of ``ds`` (before deleting it: no dangling references)."""
    for axis in range(ds.ndim):
        for scale in list(ds.dims[axis].values()):
            ds.dims[axis].detach_scale(scale)


# -- one writer per output file ------------------------------------------------------------


def _cannot_create(path: Path, exc: OSError) -> LieflowError:
    return LieflowError(
        f"cannot create {_where(path)}: {exc.strerror or exc}. To fix: choose an output path "
        "in a directory you can write to (not under /proc, /sys or /dev)."
    )


def _same_file(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


class _OutputLock:
    """An exclusive advisory lock on an output path, held for a whole run.

    The lock is ``flock`` on a sidecar file ``.<name>.lock`` in the output's directory
    (HDF5 takes its own locks on the data file itself, and those are released whenever the
    library closes it), holding the owner's pid and host. :meth:`release` removes the
    sidecar while still holding the lock; the kernel releases it when the process dies, however
    it dies, so a leftover sidecar never blocks a later run. A process that locked a
    sidecar its previous holder had just removed notices (the path no longer names the file
    it locked) and tries again. Without ``fcntl`` (Windows) there is no lock.
    """

    def __init__(self, path: Path, fd: int | None) -> None:
        self.path = path
        self._fd = fd

    @classmethod
    def acquire(cls, output: Path) -> _OutputLock:
        real = Path(os.path.realpath(output))  # one lock whatever symlink names the file
        lock_path = real.with_name(f".{real.name}.lock")
        if fcntl is None:  # pragma: no cover - not POSIX
            return cls(lock_path, None)
        for _ in range(100):
            try:
                fd = os.open(lock_path, os.O_RDWR | os.O_CREAT | getattr(os, "O_CLOEXEC", 0), 0o644)
            except OSError as exc:
                raise _cannot_create(output, exc) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError as exc:
                holder = os.pread(fd, 200, 0).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                if isinstance(exc, BlockingIOError):
                    raise OutputBusyError(
                        f"{_where(output)} is being written by another lieflow run ({holder}); "
                        "two runs writing one file would lose one of the results, so this "
                        "one is refused (--force and --resume too). To fix: wait until that "
                        "run has finished or stop it, or write to another output (--out)."
                    ) from None
                raise _cannot_create(output, exc) from None
            if _same_file(fd, lock_path):
                os.ftruncate(fd, 0)
                os.write(fd, f"pid {os.getpid()} on {socket.gethostname()}\n".encode())
                return cls(lock_path, fd)
            os.close(fd)  # its previous holder removed it after we opened it: try again
        raise OutputBusyError(  # pragma: no cover - needs 100 lost races in a row
            f"could not lock {_where(output)}: other processes keep taking its lock. To fix: "
            "make sure one run at a time writes this file."
        )

    def release(self) -> None:
        """Remove the sidecar and release the lock (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if _same_file(fd, self.path):
                os.unlink(self.path)
        except OSError:  # pragma: no cover - the directory became read-only
            pass
        finally:
            os.close(fd)


def _file_id(f: h5py.File) -> tuple[int, int]:
    """(device, inode) of the file HDF5 is writing."""
    try:
        st = os.fstat(int(f.id.get_vfd_handle()))
    except (OSError, TypeError, ValueError, AttributeError):  # pragma: no cover - other drivers
        st = os.stat(f.filename)
    return st.st_dev, st.st_ino


def _exists_error(out: Path) -> ConfigError:
    return ConfigError(
        f"{_where(out)} already exists (another run may have created it since this one "
        "started). To fix: pass --resume to continue it, --force to replace it, or choose "
        "another output.",
        "[run] output",
    )


def _publish(tmp: Path, out: Path, replace: bool) -> None:
    """Give the finished file ``tmp`` the name ``out``: atomically replacing an existing file
    if ``replace``, else only if ``out`` does not exist (a hard link is an atomic exclusive
    create; where links are not supported, an O_EXCL placeholder is replaced)."""
    if replace:
        os.replace(tmp, out)
        return
    try:
        os.link(tmp, out)
    except FileExistsError:
        raise _exists_error(out) from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
            raise
        try:
            os.close(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        except FileExistsError:
            raise _exists_error(out) from None
        os.replace(tmp, out)
    else:
        tmp.unlink()


def _verify_for_resume(header: TrajectoryHeader) -> Checkpoint:
    """Every check of a resume, on the file opened read-only: a refused file is not touched."""
    path = header.output
    from_config = bool(header.config_source)
    with _open(path, "r", _RESUME_FIX) as f, _Reading(path):
        layout = _check_format(f, path)
        stored, now = str(_plain(f.attrs["identity"])), header.identity
        if stored != now:
            changed = "; ".join(identity_changes(stored, now)) or f"{stored} -> {now}"
            raise ConfigError(
                f"--resume: {_where(path)} was written by a different configuration; changed: "
                f"{changed}. To fix: "
                + (
                    "restore the configuration it was started with (only [run] steps or "
                    "t_final and output may change)"
                    if from_config
                    else "call integrate with the arguments it was started with (only steps "
                    "or t_final may change)"
                )
                + ", or write to a new output file.",
                "--resume",
            )
        if not np.array_equal(f[layout.paths["W0"]][()], header.W0):
            given = f"[initial] in {header.config_source}" if from_config else "W0"
            raise ConfigError(
                f"--resume: {_where(path)} starts from a different initial condition than "
                f"{given}. To fix: restore the initial condition it was started with, or "
                "write to a new output file.",
                "--resume",
            )
        ck = _read_checkpoint(f, path)
        _check_lengths(f, ck.step, path, layout)
        _check_coordinates(f, ck.step, path, layout)
        _check_invariants(f, ck, header.system, path, layout)
        _check_kept(f, ck.step, path, layout)
        _check_spare(f, path)
        if ck.step > header.requested_steps:
            raise ConfigError(
                f"--resume: {_where(path)} already holds {ck.step} steps, more than the "
                f"{header.requested_steps} asked for ([run] steps / t_final); resuming never "
                f"shortens a file. To fix: ask for at least {ck.step} steps to continue it, or "
                f"read its first {header.requested_steps} steps from the file as it is.",
                "[run] steps",
            )
    return ck


class TrajectoryWriter:
    """Appends a run to an open trajectory file: the application's
    :class:`~lieflow.sinks.Sink` for ``.h5`` files (``TrajectorySink``).

    Create one with :meth:`create` (a new file), :meth:`reopen` (resume) or :meth:`open`
    (either). :func:`lieflow.driver.run` feeds every :class:`~lieflow.driver.Chunk` of steps
    to :meth:`record` (buffered), calls :meth:`checkpoint` at its checkpoint cadence (it
    appends the buffered diagnostics and saved states, writes a checkpoint and flushes) and
    :meth:`close` at the end. A checkpoint runs with interrupts deferred and writes to
    explicit positions, so an interrupt cannot leave it half-done.

    A writer holds an exclusive lock on its output path from :meth:`create` or
    :meth:`reopen` to :meth:`close` (one writer per file: a second is refused with
    :class:`OutputBusyError`), and :meth:`close` raises if the path no longer names the file
    it wrote (deleted or replaced by another program meanwhile).
    """

    def __init__(
        self, f: h5py.File, header: TrajectoryHeader | RunSetup, lock: _OutputLock | None = None
    ) -> None:
        header = _header(header)
        self._f = f
        self._lock = lock
        self._path = Path(f.filename)
        self._file_id = _file_id(f)
        self._layout = layout = _check_format(f, self._path)
        at = layout.paths
        extra, every = driver.extra_hook(header.system, header.save_every)
        self._diagnostics = Diagnostics(
            header.system,
            f[at["energy"]][0],
            f[at["casimirs"]][0],
            header.system.casimir_scale(f[at["W0"]][()]),
            extra,
            every,
        )
        self._header = header
        #: where a reopened file continues (:meth:`reopen`); ``None`` for a new file
        self.start: Checkpoint | None = None
        self._ending: tuple[Ending, ConvergenceError | None, float] | None = None
        # h5py path lookups cost tens of microseconds each: keep the handles (``step``: the
        # per-step coordinate of a netCDF-4 file, appended with the diagnostics)
        per_step = (*_PER_STEP, *(("step",) if "step" in at else ()))
        self._diag = {name: f[at[name]] for name in (*per_step, *_PER_UPDATE)}
        self._traj = {name: f[at[name]] for name in ("saved_step", "time", "W")}
        self._ck = f["checkpoint"]
        self._slots = [self._ck["slot0"], self._ck["slot1"]]
        self._slot_data: list[dict[str, Any]] = [{}, {}]
        # rows committed (steps 0..K)
        self._n_diag = self._diag["iterations"].shape[0] - layout.update_row0
        self._n_saved = self._traj["saved_step"].shape[0]
        self._saved_to = int(self._traj["saved_step"][self._n_saved - 1])  # last saved step
        self._buffered = 0  # bytes of the saved states in the buffer
        self._abandoned = False  # closed without writing more (a full disk)
        # per buffered chunk: (step indices kept, states kept, iterations, residuals, its
        # diagnostics); only the kept states, never a whole chunk (memory stays bounded)
        self._buffer: list[tuple[Array, Array, Array, Array, ChunkDiagnostics]] = []
        self._last: tuple[int, float, Array, Any] | None = None  # (step, h, W, flow state)
        self._slot = int(self._ck.attrs["current"])
        self._step = int(self._slots[self._slot].attrs["step"])  # the checkpoint's step
        self._max_error = float(np.max(self._diag["energy_error"][: self._n_diag]))
        self._attributes: dict[str, Any] = {}  # the header as closed (:meth:`attributes`)

    @property
    def path(self) -> Path:
        """The file being written."""
        return self._path

    @property
    def header(self) -> TrajectoryHeader:
        """The run this writer writes."""
        return self._header

    def attributes(self) -> dict[str, Any]:
        """The file's header attributes as they stand (after :meth:`close`: as closed;
        empty after :meth:`abandon`)."""
        return _meta(self._f) if self._f.id.valid else dict(self._attributes)

    @property
    def max_energy_error(self) -> float:
        """Largest relative energy error recorded so far (buffered steps included)."""
        return self._max_error

    # -- creation --------------------------------------------------------------------------

    @classmethod
    def create(cls, run: TrajectoryHeader | RunSetup) -> TrajectoryWriter:
        """Create ``run.output`` holding the header and step 0, and lock it (``run``: a
        :class:`TrajectoryHeader`, or a :class:`~lieflow.app.config.RunSetup` for its header).

        The file is written under a temporary name in the same directory and then given its
        name, so a failure leaves no partial file. A missing directory is created only with
        ``make_directory`` (``lieflow run``), else refused (``integrate(out=...)``: it used to
        create ``/nonexistent`` for ``out="/nonexistent/a.h5"``). An existing file is
        replaced only if ``setup.replace`` (atomically); otherwise the name is taken with an
        exclusive create, so of two runs started on one new path, one is refused.

        Raises
        ------
        OutputBusyError
            Another process is writing ``setup.output``.
        ConfigError
            The file exists and ``setup.replace`` is false.
        LieflowError
            The file cannot be created there.
        """
        h5py = _h5py()
        setup = _header(run)
        out = setup.output
        if setup.make_directory and not out.parent.exists():
            try:
                out.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise _cannot_create(out, exc) from None
        if not out.parent.is_dir():  # never a directory tree the caller did not ask for
            what = "is not a directory" if out.parent.exists() else "does not exist"
            raise LieflowError(
                f"cannot create {_where(out)}: its directory {str(out.parent)!r} {what} "
                "(lieflow creates the file, not directories). To fix: create the directory "
                f"first (mkdir -p {out.parent}), or choose an output in an existing directory."
            )
        lock = _OutputLock.acquire(out)
        try:
            if not setup.replace and os.path.lexists(out):
                raise _exists_error(out)
            tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
            try:
                f = h5py.File(tmp, "w", rdcc_nbytes=_CHUNK_CACHE_BYTES)
                try:
                    _initialise(f, setup)
                except BaseException:
                    _close_quietly(f)
                    raise
                f.close()
                _publish(tmp, out, setup.replace)
            except _WRITE_ERRORS as exc:
                if _no_space(exc):
                    raise _disk_full(out) from None
                if isinstance(exc, OSError):
                    raise _cannot_create(out, exc) from None
                raise
            finally:
                tmp.unlink(missing_ok=True)
            return cls(_open(out, "r+"), setup, lock)
        except BaseException:
            lock.release()
            raise

    @classmethod
    def reopen(cls, run: TrajectoryHeader | RunSetup) -> tuple[TrajectoryWriter, Checkpoint]:
        """Open ``run.output`` to resume, lock it, and return the writer and the last
        checkpoint; everything written after that checkpoint is dropped (``run``: a
        :class:`TrajectoryHeader`, or a :class:`~lieflow.app.config.RunSetup` for its header).

        Every check runs before the file is opened for writing, so a refused file is left
        byte for byte as it was: it must be a lieflow trajectory of the same configuration
        (the error names the changed keys) and initial condition, its checkpoint must match
        its SHA-256 checksum and reproduce the energy and Casimirs recorded for its step,
        and it must not hold more steps than asked for.

        Raises
        ------
        OutputBusyError
            Another process is writing ``setup.output``.
        ConfigError
            Another configuration or initial condition, or fewer steps than the file holds.
        LieflowError
            The file is empty, not HDF5, not a trajectory, or damaged.
        """
        setup = _header(run)
        path = setup.output
        lock = _OutputLock.acquire(path)
        try:
            ck = _verify_for_resume(setup)
            try:
                _ensure_space(path)
            except OSError:
                raise _disk_full(path, ck.step) from None
            f = _open(path, "r+", _RESUME_FIX)
            try:
                with _Reading(path):
                    _truncate(f, ck.step, _check_format(f, path))
                    f.attrs["resumes"] = int(f.attrs.get("resumes", 0)) + 1
                    f.attrs["requested_steps"] = setup.requested_steps
                    f.attrs["status"] = "running"
                    f.flush()
                writer = cls(f, setup, lock)
            except BaseException as exc:
                _close_quietly(f)
                if isinstance(exc, _WRITE_ERRORS) and _no_space(exc):
                    raise _disk_full(path, ck.step) from None
                raise
        except BaseException:
            lock.release()
            raise
        return writer, ck

    @classmethod
    def open(cls, run: TrajectoryHeader | RunSetup, *, resume: bool = False) -> TrajectoryWriter:
        """:meth:`reopen` ``run.output`` if ``resume`` and it exists (the writer's
        :attr:`start` is then its last checkpoint), else :meth:`create` it."""
        setup = _header(run)
        if resume and setup.output.exists():
            writer, ck = cls.reopen(setup)
            writer.start = ck
            return writer
        return cls.create(setup)

    # -- writing ---------------------------------------------------------------------------

    def record(self, chunk: Chunk, keep: Array, diagnostics: ChunkDiagnostics | None) -> None:
        """Buffer ``chunk``: its diagnostics (computed here when ``None``: a file always
        records them), its states where ``keep`` is true, and its last state and flow state
        for the next checkpoint. Nothing is written until :meth:`checkpoint`."""
        diag = self._diagnostics.of_chunk(chunk) if diagnostics is None else diagnostics
        keep = np.asarray(keep, dtype=bool)
        entry = (chunk.index[keep], to_host(chunk.W[keep]), to_host(chunk.iterations),
                 to_host(chunk.residuals), diag)  # fmt: skip
        last = (chunk.stop, chunk.h, np.array(to_host(chunk.W[-1])), chunk.state)
        # one append and one assignment: recorded entirely or not at all
        self._buffer.append(entry)
        self._last = last
        self._max_error = max(self._max_error, diag.max_energy_error)
        if keep.any():
            self._saved_to = int(chunk.index[keep][-1])
            self._buffered += entry[1].nbytes
            if self._buffered >= _BUFFER_BYTES:  # memory stays bounded between checkpoints
                with _signals.deferred(), self._room():
                    _ensure_space(self._path, self._buffered)
                    self._write_rows()

    @property
    def completed_steps(self) -> int:
        """Steps in the file after the last :meth:`checkpoint` (its step)."""
        return self._step

    def checkpoint(self, *, keep_last: bool = False) -> None:
        """Append the buffered diagnostics and saved states (and the last state, with
        ``keep_last``), checkpoint at the last recorded step, flush and fsync.

        Runs with interrupts deferred (:func:`lieflow._signals.deferred`): an interrupt
        cannot leave the writer's counters and the file disagreeing.
        """
        with _signals.deferred():
            if self._last is None or self._abandoned:
                return
            stop, h, W_last, state = self._last
            last_unsaved = keep_last and self._saved_to != stop
            if stop == self._step and not self._buffer and not last_unsaved:
                return  # nothing new since the last checkpoint
            with self._room():
                _ensure_space(self._path, self._buffered + W_last.nbytes)
                self._write_rows(keep_last=keep_last)
                self._checkpoint(stop, stop * h, W_last, state)
                _sync(self._f)

    @contextlib.contextmanager
    def _room(self) -> Iterator[None]:
        """Writes on a full disk: the file is abandoned at its last checkpoint (the one to
        resume from, untouched) and one :class:`DiskFullError` says so."""
        try:
            yield
        except _WRITE_ERRORS as exc:
            if not _no_space(exc):
                raise
            self.abandon()
            raise _disk_full(self._path, self._step) from None

    def _write_rows(self, *, keep_last: bool = False) -> None:
        """Append the buffered diagnostics, saved states and extra diagnostics (and the last
        recorded state, with ``keep_last``, unless it is saved): rows after the checkpoint,
        which a resume drops until a checkpoint covers them. Call with interrupts deferred."""
        buf = self._buffer
        n0, n_saved = self._n_diag, self._n_saved
        n_rows = 0
        steps = np.zeros(0, dtype=np.int64)
        kept: list[Array] = []
        if buf:
            H = np.concatenate([to_host(b[4].energy) for b in buf])
            C = np.concatenate([to_host(b[4].casimirs) for b in buf])
            columns = {
                "energy": H,
                "energy_error": np.concatenate([to_host(b[4].energy_error) for b in buf]),
                "casimirs": C,
                "casimir_drift": np.concatenate([to_host(b[4].casimir_drift) for b in buf]),
                "iterations": np.concatenate([b[2] for b in buf]).astype(np.int64),
                "residual": np.concatenate([b[3] for b in buf]).astype(float),
            }
            n_rows = H.shape[0]
            if "step" in self._diag:
                columns["step"] = np.arange(n0, n0 + n_rows, dtype=np.int64)
            for name, values in columns.items():
                start = n0 + self._layout.update_row0 if name in _PER_UPDATE else n0
                ds = self._diag[name]
                ds.resize(start + len(values), axis=0)
                ds[start:] = values
            steps = np.concatenate([b[0] for b in buf]).astype(np.int64)
            kept = [b[1] for b in buf]
        if keep_last and self._last is not None and self._saved_to != self._last[0]:
            steps = np.append(steps, np.int64(self._last[0]))
            kept.append(self._last[2][None])
            self._saved_to = self._last[0]
        if steps.size:
            h = self._header.h
            states = np.concatenate(kept)
            for name, value in (("saved_step", steps), ("time", steps * h), ("W", states)):
                ds = self._traj[name]
                ds.resize(n_saved + steps.size, axis=0)
                ds[n_saved:] = value
        _append_extra(self._f, [e for b in buf for e in b[4].extra])
        self._n_diag, self._n_saved = n0 + n_rows, n_saved + steps.size
        self._buffer, self._buffered = [], 0

    def _checkpoint(self, index: int, t: float, W: Array, state: Any) -> None:
        """Write ``W`` and the flow's ``state`` (leaf by leaf, under ``warm/<path>``) at step
        ``index`` to the spare slot with its SHA-256 digest, flush and fsync, then point
        ``current`` at it (the commit point; :meth:`checkpoint` flushes and fsyncs it)."""
        items: dict[str, Any] = {"W": W}
        for path, leaf in tree.paths(state):
            items[f"{_STATE}/{path}" if path else _STATE] = leaf
        slot_id = 1 - self._slot
        _write_slot(self._slots[slot_id], index, t, items, self._slot_data[slot_id])
        _sync(self._f)  # the rows and the slot are on disk before the commit point names them
        self._ck.attrs["current"] = slot_id  # the commit point
        self._slot, self._step = slot_id, index

    def abandon(self) -> None:
        """Close the file without writing more (after a failed write, e.g. a full disk:
        the last checkpoint on disk stays the one to resume from) and release its lock;
        :meth:`checkpoint` and :meth:`close` then do nothing."""
        if self._abandoned:
            return
        self._abandoned = True
        self._last, self._buffer = None, []
        try:
            _close_quietly(self._f)
        finally:
            if self._lock is not None:
                self._lock.release()

    def close(
        self, status: Ending, failure: ConvergenceError | str | None, wall_time: float
    ) -> None:
        """Record the final status, the failure's message and the time spent, close the file
        and release its lock (nothing after :meth:`abandon`).

        Raises
        ------
        LieflowError
            The output path no longer names the file this writer wrote (another program
            deleted or replaced it during the run): the run must not report success.
        """
        error = failure if isinstance(failure, ConvergenceError) else None
        self._ending = (status, error, wall_time)
        if self._abandoned:
            return
        f = self._f
        lost = False
        self._last, self._buffer = None, []  # hold no state once closed
        try:
            f.attrs["completed_steps"] = self._step
            f.attrs["status"] = status
            f.attrs["wall_time"] = float(f.attrs.get("wall_time", 0.0)) + wall_time
            f.attrs["failure"] = "" if failure is None else str(failure)
            f.flush()
            self._attributes = _meta(f)
        finally:
            try:
                try:
                    now = os.stat(self._path)
                    lost = (now.st_dev, now.st_ino) != self._file_id
                except OSError:
                    lost = True
                f.close()
            finally:
                if self._lock is not None:
                    self._lock.release()
        if lost:
            raise LieflowError(
                f"{_where(self._path)} was deleted or replaced by another program while this "
                f"run was writing it: the {self._step} steps it recorded are not in the file "
                "at that path, so the run did not succeed. To fix: let nothing else write, "
                "move or delete the output during a run (`lieflow run --force` on a running "
                "output is refused; `rm` or `mv` are not), and run again."
            )

    def result(self) -> Solution:
        """The run as a :class:`~lieflow.Solution` (after :meth:`close`): the initial and the
        last state (``W``, ``t``, ``saved_steps`` of length 2), and every step's iterations
        and diagnostics read back from the file; ``solvers`` names the requested solver."""
        if self._ending is None:
            raise LieflowError("TrajectoryWriter.result() before the run was closed")
        status, failure, wall = self._ending
        header = self._header
        run = read_diagnostics(self._path)
        k = run.completed_steps
        first = np.asarray(run.W0)
        W = np.stack([first, run.W]) if k else first[None]
        steps_kept = np.array([0, k] if k else [0], dtype=np.int64)
        return Solution(
            system=header.system,
            scheme=header.scheme,
            h=header.h,
            t=steps_kept * header.h,
            W=W,
            saved_steps=steps_kept,
            iterations=run.iterations,
            solvers=(header.solver or header.scheme,) * k,
            energy_error=run.energy_error,
            casimir_drift=run.casimir_drift,
            status=Status.SUCCESS if status == "complete" else Status.FAILED,
            failure=failure,
            wall_time=wall,
            extra={} if self._diagnostics.extra is None else read_extra(self._path),
        )


#: The application's sink for trajectory files (:class:`lieflow.sinks.Sink`).
TrajectorySink = TrajectoryWriter


def trajectory_sink(
    path: Path, run: RunInfo, *, resume: bool = False, replace: bool = False
) -> TrajectoryWriter:
    """The sink factory registered for ``.h5`` (:func:`lieflow.sinks.open_sink`): a
    :class:`TrajectoryWriter` on ``path`` for ``run`` — continuing the file from its last
    checkpoint with ``resume`` (if it exists), else creating it (an existing file only with
    ``replace``)."""
    fields = {f.name: getattr(run, f.name) for f in attrs.fields(RunInfo)}
    header = TrajectoryHeader(**fields, output=_as_path(path, "out"), replace=replace)
    return TrajectoryWriter.open(header, resume=resume)


def _sync(f: h5py.File) -> None:
    """Flush ``f`` and make it durable (``fsync``): a checkpoint survives a power loss."""
    f.flush()
    os.fsync(int(f.id.get_vfd_handle()))


def _write_slot(
    slot: h5py.Group, index: int, t: float, items: Mapping[str, Any], cache: dict[str, Any]
) -> None:
    """Store ``items`` in a checkpoint slot (arrays as datasets; other values as attributes,
    ``None`` as ``"none"``, in version 1, as the JSON attribute ``scalars`` in version 2),
    then its step, time and :func:`checkpoint_digest`."""
    netcdf = _is_netcdf(slot.file)
    if cache.get("") != sorted(items):  # other leaves than this slot's last write here
        _prune(slot, set(items))
        cache.clear()
        cache[""] = sorted(items)
    scalars: dict[str, Any] = {}
    for key, value in items.items():
        if isinstance(value, np.ndarray):
            if key in slot.attrs:  # it was None (an attribute) at this slot's last write
                del slot.attrs[key]
            _put(slot, key, value, cache)
            continue
        if key in slot:
            cache.pop(key, None)
            _drop(slot, key)
        if netcdf:
            scalars[key] = _plain(value)
        else:
            slot.attrs[key] = "none" if value is None else value
    if netcdf:
        slot.attrs[_SCALARS] = json.dumps(scalars, sort_keys=True)
    slot.attrs["step"] = index
    slot.attrs["t"] = t
    slot.attrs[_DIGEST] = checkpoint_digest(index, t, items)


def _checked(value: Array) -> dict[str, Any]:
    """Dataset options for HDF5's Fletcher-32 checksum on the whole array (one chunk);
    an empty or scalar array cannot be chunked and goes without."""
    value = np.asarray(value)
    return {"chunks": value.shape, "fletcher32": True} if value.size and value.ndim else {}


def _put(group: h5py.Group, name: str, value: Array, cache: dict[str, Any]) -> None:
    """Write ``value`` to dataset ``name`` of ``group`` in place (``cache`` keeps handles)."""
    value = np.asarray(value)
    ds = cache.get(name)
    if ds is None and name in group:
        ds = cache[name] = group[name]
    if ds is not None and (ds.shape != value.shape or ds.dtype != value.dtype):
        cache.pop(name)
        _drop(group, name)
        ds = None
    if ds is None:
        ds = cache[name] = _create(group, name, value)
    else:
        ds[...] = value


def _create(group: h5py.Group, name: str, value: Array) -> h5py.Dataset:
    """A dataset holding ``value`` with its checksum; in a netCDF-4 file with dimensions: a
    state (shaped like W0) on the file's (``ensemble``,) ``row``, ``col``, anything else on
    dimensions ``<name>_dim<i>`` of its own group."""
    f = group.file
    ds = group.create_dataset(
        name, data=value, dtype=_stored_dtype(f, value.dtype), **_checked(value)
    )
    if _is_netcdf(f) and value.ndim:
        if name.rsplit("/", 1)[-1] in ("W", "W0") and value.shape == _state_shape(f):
            _attach(ds, [f[d] for d in _state_dims(value.ndim)])
        else:
            base = name.rsplit("/", 1)[-1]
            _attach(ds, [_dimension(ds.parent, f"{base}_dim{i}", n) for i, n in
                         enumerate(value.shape)])  # fmt: skip
    return ds


def _prune(slot: h5py.Group, keep: set[str]) -> None:
    """Delete what a checkpoint slot holds besides the items ``keep`` (the leaves of a flow
    state of another shape: a resume by a lieflow whose scheme keeps other state), so that
    the slot holds exactly the items its digest covers."""
    h5py = _h5py()
    stale: list[str] = []

    def visit(name: str, obj: Any) -> None:
        if isinstance(obj, h5py.Dataset) and not _is_scale(obj) and name not in keep:
            stale.append(name)

    slot.visititems(visit)
    for name in stale:
        if name in slot:
            _drop(slot, name)
    for key in list(slot.attrs):
        if key not in (*_SLOT_ATTRS, _SCALARS) and key not in keep:
            del slot.attrs[key]
    for key in keep:  # a group where a leaf goes (or a leaf where a group goes)
        parts = key.split("/")
        for i in range(1, len(parts) + 1):
            sub = "/".join(parts[:i])
            obj = slot.get(sub)
            if obj is None:
                break
            if isinstance(obj, h5py.Group) != (i < len(parts)):
                _drop(slot, sub)
                break


def _renew_spare(f: h5py.File) -> None:
    """Replace the spare checkpoint slot by an empty one if its structure is damaged (the
    next checkpoint, written there, would fail half-way). The spare slot is never read
    otherwise, so nothing is lost."""
    group = f["checkpoint"]
    name = f"slot{1 - int(group.attrs['current'])}"
    try:
        _visit_structure(group[name])
        return
    except _DAMAGE:
        pass
    with contextlib.suppress(*_DAMAGE):
        _drop(group, name)  # detaching the dimensions it can
    try:
        if name in group:
            del group[name]
        group.create_group(name)
    except _DAMAGE as exc:  # HDF5 frees a group's members as it unlinks it: it reads them
        raise DamagedOutputError(
            f"{_where(Path(f.filename))}: the HDF5 structure of its checkpoint slot {name!r} "
            f"is damaged ({type(exc).__name__}: {exc}), and HDF5 cannot remove it to write "
            "the next checkpoint there. To fix: restore the file from a backup, or run the "
            "configuration again from the start (--force)."
        ) from None


def _drop(group: h5py.Group, name: str) -> None:
    """Delete dataset (or group) ``name`` of ``group`` and the dimensions only it used."""
    h5py = _h5py()
    obj = group[name]
    parent, base = obj.parent, name.rsplit("/", 1)[-1]
    if _is_netcdf(group.file):
        inner = [obj] if isinstance(obj, h5py.Dataset) else []
        if isinstance(obj, h5py.Group):
            obj.visititems(lambda _, o: inner.append(o) if isinstance(o, h5py.Dataset) else None)
        for ds in inner:
            _detach(ds)
    del group[name]
    for i in range(8):
        dim = f"{base}_dim{i}"
        if dim in parent and _is_scale(parent[dim]):
            del parent[dim]


def _state_dims(ndim: int) -> list[str]:
    """The dimensions of a state with ``ndim`` axes: (``ensemble``,) ``row``, ``col``."""
    return [*_batch_dims(ndim - 2), "row", "col"]


def _batch_dims(n: int) -> list[str]:
    """Names of ``n`` batch axes: ``ensemble`` (``ensemble_0``, ... if more than one)."""
    return ["ensemble"] if n == 1 else [f"ensemble_{i}" for i in range(n)]


def _state_shape(f: h5py.File) -> tuple[int, ...]:
    """The shape of one state of a netCDF-4 file (from its dimensions)."""
    ens = [f[d].shape[0] for d in ("ensemble", *(f"ensemble_{i}" for i in range(8))) if d in f]
    return (*ens, f["row"].shape[0], f["col"].shape[0])


def _ensemble_labels(config: str, members: int) -> Array:
    """Labels of an ensemble's members: ``[initial] seeds`` of the configuration if it
    has one per member, else ``0..members-1``."""
    try:
        seeds = tomllib.loads(config).get("initial", {}).get("seeds") if config else None
    except (tomllib.TOMLDecodeError, AttributeError):
        seeds = None
    if isinstance(seeds, list) and len(seeds) == members:
        try:
            return np.asarray(seeds, dtype=np.int64)
        except (TypeError, ValueError, OverflowError):
            pass
    return np.arange(members, dtype=np.int64)


def _initialise(f: h5py.File, header: TrajectoryHeader) -> None:
    """Write a new file's header, dimensions, variables and step 0 (format version 2)."""
    system, W0 = header.system, np.asarray(header.W0)
    powers = [k for k in system.casimir_powers if k <= system.algebra.n]
    meta: dict[str, Any] = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "config": header.config_text,
        "config_source": header.config_source,
        "identity": header.identity,
        "system": header.system_name,
        "scheme": header.scheme,
        "solver": header.solver,
        "h": header.h,
        "save_every": header.save_every,
        "requested_steps": header.requested_steps,
        "casimir_powers": np.asarray(powers, dtype=np.int64),
        "completed_steps": 0,
        "status": "running",
        "wall_time": 0.0,
        "failure": "",
        "resumes": 0,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        **environment(),
    }
    for key, value in meta.items():
        f.attrs[key] = value
    h5py = _h5py()
    props = (
        f"version=2,lieflow={meta['lieflow_version']},hdf5={h5py.version.hdf5_version},"
        f"h5py={h5py.__version__}"
    )
    f.attrs["_NCProperties"] = np.array(props, dtype=h5py.string_dtype("ascii", len(props)))
    H0 = np.asarray(system.hamiltonian(W0), dtype=np.float64)
    C0 = np.asarray(system.casimirs(W0), dtype=np.float64)
    batch = W0.shape[:-2]
    # dimensions: the two unlimited axes first (ids 0, 1), then the fixed ones
    time = _coordinate(_growable(f, "time", np.float64(0), np.float64), 0)
    step = _coordinate(_growable(f, "step", np.int64(0), np.int64), 1)
    dimid = 2
    ens = []
    for name, n in zip(_batch_dims(len(batch)), batch, strict=True):
        labels = _ensemble_labels(header.config_text, n) if len(batch) == 1 else np.arange(n)
        ens.append(_coordinate(f.create_dataset(name, data=labels, **_checked(labels)), dimid))
        dimid += 1
    row = _dimension(f, "row", W0.shape[-2], dimid=dimid)
    col = _dimension(f, "col", W0.shape[-1], dimid=dimid + 1)
    casimir_labels = np.asarray(powers if len(powers) == C0.shape[-1] else
                                np.arange(C0.shape[-1]), dtype=np.int64)  # fmt: skip
    casimir = _coordinate(
        f.create_dataset("casimir", data=casimir_labels, **_checked(casimir_labels)), dimid + 2
    )
    state = [*ens, row, col]
    saved = _growable(f, "saved_step", np.int64(0), np.int64, [time])
    W = _growable(f, "W", W0, W0.dtype, [time, *state])
    variables = {
        "energy": _growable(f, "energy", H0, np.float64, [step, *ens]),
        "energy_error": _growable(f, "energy_error", H0, np.float64, [step, *ens]),
        "casimirs": _growable(f, "casimirs", C0, np.float64, [step, *ens, casimir]),
        "casimir_drift": _growable(f, "casimir_drift", C0, np.float64, [step, *ens, casimir]),
        "iterations": _growable(f, "iterations", np.int64(0), np.int64, [step]),
        "residual": _growable(f, "residual", np.float64(0), np.float64, [step]),
    }
    for name, text in _DESCRIPTIONS.items():
        f[name].attrs["long_name"] = text
    W.attrs["coordinates"] = "saved_step"
    initial = f.create_group("initial").create_dataset(
        "W0", data=W0, dtype=_stored_dtype(f, W0.dtype), **_checked(W0)
    )
    _attach(initial, state)
    rows = {
        time: 0.0, step: 0, saved: 0, W: W0,
        variables["energy"]: H0, variables["energy_error"]: np.zeros_like(H0),
        variables["casimirs"]: C0, variables["casimir_drift"]: np.zeros_like(C0),
        variables["iterations"]: 0, variables["residual"]: np.nan,
    }  # fmt: skip
    for ds, value in rows.items():
        ds.resize(1, axis=0)
        ds[0] = value
    extra, _ = driver.extra_hook(system, header.save_every)
    if extra is not None:
        _append_extra(f, [(0, 0.0, extra(W0))])
    ck = f.create_group("checkpoint")
    for i in (0, 1):
        _write_slot(ck.create_group(f"slot{i}"), 0, 0.0, {"W": W0}, {})
    ck.attrs["current"] = 0


#: ``long_name`` of the variables of a netCDF-4 trajectory file.
_DESCRIPTIONS = {
    "time": "time t = k h of the saved states",
    "saved_step": "step index k of the saved states",
    "W": "saved states W_k",
    "step": "step index k of the per-step diagnostics",
    "energy": "energy (Hamiltonian) H(W_k)",
    "energy_error": "relative energy error |H(W_k) - H(W_0)| / |H(W_0)|",
    "casimirs": "Casimirs C_j(W_k) = tr W_k^j",
    "casimir_drift": "Casimir drift |C_j(W_k) - C_j(W_0)| / ||W_0||^j",
    "iterations": "solver updates of step k (0 at step 0)",
    "residual": "last relative update of step k's solve (NaN at step 0)",
    "casimir": "power j of the Casimir tr W^j",
}


def _truncate(f: h5py.File, k: int, layout: _Layout) -> None:
    """Drop every row written after step ``k`` (a save the process did not finish)."""
    at = layout.paths
    per_step = (*_PER_STEP, *(("step",) if "step" in at else ()))
    for name in per_step:
        if f[at[name]].shape[0] > k + 1:
            f[at[name]].resize(k + 1, axis=0)
    updates = k + 1 + layout.update_row0
    for name in _PER_UPDATE:
        if f[at[name]].shape[0] > updates:
            f[at[name]].resize(updates, axis=0)
    if min(f[at[n]].shape[0] for n in per_step) != k + 1 or f[at["iterations"]].shape[0] != updates:
        raise LieflowError(
            f"{f.filename!r} is damaged: its diagnostics end before its checkpoint at step "
            f"{k}. To fix: {salvage_fix(Path(f.filename))}; or start the run again without "
            "--resume (use --force)."
        )
    n = int(np.searchsorted(f[at["saved_step"]][()], k, side="right"))
    for name in ("saved_step", "time", "W"):
        f[at[name]].resize(n, axis=0)
    kept = [f[at[name]] for name in (*per_step, *_PER_UPDATE, "saved_step", "time", "W")]
    group = f.get(_EXTRA)
    if group is not None:
        n = int(np.searchsorted(group["step"][()], k, side="right"))
        for ds in group.values():
            if not _is_scale(ds):
                ds.resize(n, axis=0)
                kept.append(ds)
    # A process killed while it rewrote a chunk (SIGKILL, power loss) leaves that chunk's
    # checksum wrong; rows before the checkpoint may share it with rows after. Read the last
    # chunk of every dataset now, so that a damaged one is refused here, with its fix, and
    # not found by the next write (h5py: "filter returned failure during read").
    for ds in kept:
        rows, chunk = ds.shape[0], (ds.chunks or (1,))[0]
        if rows:
            ds[(rows - 1) // chunk * chunk : rows]
    f.attrs["completed_steps"] = k


#: ``also(writer) -> sinks``: sinks a run writes besides its trajectory file (:func:`run`).
AlsoSinks = Callable[["TrajectoryWriter"], Sequence[Sink]]


@attrs.frozen
class RunSummary:
    """How :func:`run` ended.

    Attributes
    ----------
    path : Path
        The trajectory file.
    status : str
        ``"complete"``, ``"interrupted"`` (Ctrl-C; resumable) or ``"failed"``.
    completed_steps, requested_steps : int
        Steps in the file and steps asked for.
    new_steps : int
        Steps computed by this call.
    wall_time : float
        Seconds this call spent stepping.
    max_energy_error : float
        Largest relative energy error in the file.
    failure : str
        The error message of a failed run.
    """

    path: Path
    status: str
    completed_steps: int
    requested_steps: int
    new_steps: int
    wall_time: float
    max_energy_error: float
    failure: str = ""


def run(
    setup: RunSetup,
    *,
    resume: bool = False,
    monitor: Monitor | None = None,
    also: AlsoSinks | None = None,
) -> RunSummary:
    """Integrate ``setup`` and write the trajectory to ``setup.output`` as it proceeds.

    Parameters
    ----------
    setup : RunSetup
        A validated run (:func:`lieflow.app.config.build`).
    resume : bool
        Continue the existing file from its last checkpoint (bit-for-bit the same as an
        uninterrupted run; ``[run] steps`` may have grown). Without an existing file the run
        starts afresh. Without ``resume`` an existing file is replaced.
    monitor : Monitor, optional
        Progress callbacks.
    also : callable, optional
        ``also(writer)``: more sinks fed the same steps as the file, opened once the
        file's :class:`TrajectoryWriter` is (a sweep's Zarr store).

    Returns
    -------
    RunSummary
        ``status == "interrupted"`` after Ctrl-C (the file holds every step done).

    Raises
    ------
    ConfigError
        ``resume`` on a file of another configuration.
    LieflowError
        A step failed to converge (the file holds the steps before it, status "failed").
    """
    summary, _ = run_flow(setup.header(), setup.flow(), resume=resume, monitor=monitor,
                          also=also)  # fmt: skip
    if summary.status == "failed":
        raise LieflowError(
            f"{summary.failure} The {summary.completed_steps} steps before the failure are "
            f"saved in {str(setup.output)!r} (status 'failed')."
        )
    return summary


def run_flow(
    header: TrajectoryHeader,
    flow: Any,
    *,
    resume: bool = False,
    monitor: Monitor | None = None,
    also: AlsoSinks | None = None,
) -> tuple[RunSummary, ConvergenceError | None]:
    """Advance ``flow`` and write the trajectory to ``header.output`` as it proceeds: the
    one consumer loop (:func:`lieflow.driver.run`) into a :class:`TrajectoryWriter`.

    Memory: the writer buffers each chunk's diagnostics (a few numbers per step) and only
    the states it will save; at every checkpoint (every ``header.checkpoint_seconds``, and
    at the end) they are written in one block.

    Returns
    -------
    (RunSummary, ConvergenceError or None)
        How it ended (``"complete"``, ``"interrupted"`` after Ctrl-C, ``"failed"``), and
        the error of a failed step (the file then holds the steps before it).
    """
    with _signals.Interrupts() as stop:  # Ctrl-C held from here until stepping, raised there
        return _run_flow(header, flow, resume, monitor, stop, also)


def _run_flow(
    header: TrajectoryHeader,
    flow: Any,
    resume: bool,
    monitor: Monitor | None,
    interrupts: _signals.Interrupts,
    also: AlsoSinks | None = None,
) -> tuple[RunSummary, ConvergenceError | None]:
    target = header.requested_steps
    diagnostics = Diagnostics.of(header.system, header.W0, save_every=header.save_every)
    writer = TrajectoryWriter.open(header, resume=resume)
    try:
        ck = writer.start
        if ck is None:
            W, state, done = header.W0, None, 0
        else:
            W, done = ck.W, ck.step
            state = ck.state(flow.init(W))
        sinks = (writer, *(also(writer) if also is not None else ()))
    except BaseException:  # Ctrl-C before stepping: the file says so, and is resumable
        writer.close("interrupted", None, 0.0)
        raise
    outcome = driver.run(
        flow,
        W,
        header.h,
        target,
        sinks=sinks,
        diagnostics=diagnostics,
        save_every=header.save_every,
        start=done,
        state=state,
        monitor=monitor,
        checkpoint=Cadence(seconds=header.checkpoint_seconds),
        interrupts=interrupts,
    )
    completed = writer.completed_steps
    summary = RunSummary(
        header.output,
        outcome.status,
        completed,
        target,
        completed - done,
        outcome.wall_time,
        writer.max_energy_error,
        "" if outcome.failure is None else str(outcome.failure),
    )
    return summary, outcome.failure
