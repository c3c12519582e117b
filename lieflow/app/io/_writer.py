"""Writing trajectory files as a run goes: :class:`TrajectoryWriter` (the ``.h5`` sink),
the alternating checkpoint slots, the write-ahead of per-step diagnostics, publishing the
finished file under its name, resume's truncation, and stopping cleanly when the disk is full.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import json
import os
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import attrs
import numpy as np

from ... import _signals, driver, tree
from ...algebras import Array
from ...backends import is_foreign_array
from ...driver import Chunk, ChunkDiagnostics, Diagnostics
from ...errors import ConvergenceError, LieflowError
from ...sinks import Ending, RunInfo, to_host
from ...solution import Solution, Status
from ..config import ConfigError, RunSetup, check_output_path
from ._format import (
    _DAMAGE,
    _DIGEST,
    _EXTRA,
    _HEADER_COPY,
    _PER_STEP,
    _PER_UPDATE,
    _SCALARS,
    _SLOT_ATTRS,
    _STATE,
    FORMAT,
    FORMAT_VERSION,
    _as_path,
    _attach,
    _batch_dims,
    _coordinate,
    _detach,
    _dimension,
    _growable,
    _h5py,
    _header_copy,
    _is_netcdf,
    _is_scale,
    _Layout,
    _plain,
    _state_dims,
    _stored_dtype,
    _where,
    checkpoint_digest,
)
from ._header import TrajectoryHeader, _header, environment
from ._lock import (
    _CHUNK_CACHE_BYTES,
    _RESUME_FIX,
    _WRITE_ERRORS,
    DamagedOutputError,
    _cannot_create,
    _disk_full,
    _no_space,
    _open,
    _OutputLock,
    _Reading,
    salvage_fix,
)
from ._reader import (
    Checkpoint,
    _check_format,
    _meta,
    _verify_for_resume,
    _visit_structure,
    read_diagnostics,
    read_extra,
)

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

if TYPE_CHECKING:  # pragma: no cover
    import h5py


#: Free space kept in reserve on the output's disk: a write is not started unless this much
#: (plus what it writes) is free, because HDF5 interrupted by a full disk can leave the
#: file's superblock pointing past its end (measured: a resume on a full disk made the file
#: unopenable, "addr overflow"). Enough for the metadata and new chunks of a few commits.
_SPACE_MARGIN = 1 << 20


#: Free space enough to rewrite a file's status attributes (a full disk's last write).
_ATTRIBUTES_ROOM = 1 << 16


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


#: Saved states are written ahead of the next checkpoint once the buffer holds this many
#: bytes of them (a resume drops such rows until a checkpoint covers them): thousands of
#: small states per write, a large one at once.
_BUFFER_BYTES = 1 << 16


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


def _file_id(f: h5py.File) -> tuple[int, int]:
    """(device, inode) of the file HDF5 is writing."""
    try:
        st = os.fstat(int(f.id.get_vfd_handle()))
    except (OSError, TypeError, ValueError, AttributeError):  # pragma: no cover - other drivers
        st = os.stat(f.filename)
    return st.st_dev, st.st_ino


def _exists_error(out: Path, from_config: bool) -> ConfigError:
    """``out`` exists; the fix in the words of the caller (``lieflow run``'s flags, or
    :func:`lieflow.integrate`'s arguments)."""
    how = ("pass --resume to continue it, --force to replace it, or choose another output"
           if from_config else
           "pass resume=True to continue it, replace=True to replace it, or choose another "
           "out")  # fmt: skip
    return ConfigError(
        f"{_where(out)} already exists (another run may have created it since this one "
        f"started). To fix: {how}.",
        "[run] output",
    )


def _publish(tmp: Path, out: Path, replace: bool, from_config: bool) -> None:
    """Give the finished file ``tmp`` the name ``out``: atomically replacing an existing file
    if ``replace``, else only if ``out`` does not exist (a hard link is an atomic exclusive
    create; where links are not supported, an O_EXCL placeholder is replaced)."""
    if replace:
        os.replace(tmp, out)
        return
    try:
        os.link(tmp, out)
    except FileExistsError:
        raise _exists_error(out, from_config) from None
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK):
            raise
        try:
            os.close(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644))
        except FileExistsError:
            raise _exists_error(out, from_config) from None
        os.replace(tmp, out)
    else:
        tmp.unlink()


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
                raise _exists_error(out, bool(setup.config_source))
            tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
            try:
                f = h5py.File(tmp, "w", rdcc_nbytes=_CHUNK_CACHE_BYTES)
                try:
                    _initialise(f, setup)
                except BaseException:
                    _close_quietly(f)
                    raise
                f.close()
                _publish(tmp, out, setup.replace, bool(setup.config_source))
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
        entry = (chunk.index[keep], to_host(chunk.states(keep)), to_host(chunk.iterations),
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
            self._mark_stopped()
            self.abandon()
            raise _disk_full(self._path, self._step) from None

    def _mark_stopped(self) -> None:
        """On a full disk: record status "interrupted" at the last checkpoint (what the file
        is: resumable from it), where the space kept in reserve (:data:`_SPACE_MARGIN`) left
        room for a few attributes; else (HDF5's own write failed) it stays "running", as a
        killed run's file does."""
        try:
            st = os.statvfs(self._path.parent)
            if st.f_bavail * st.f_frsize < _ATTRIBUTES_ROOM:
                return
            self._f.attrs["completed_steps"] = self._step
            self._f.attrs["status"] = "interrupted"
            self._f.flush()
        except (*_WRITE_ERRORS, ValueError, AttributeError):
            pass

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
        for path, leaf in tree.paths(state):  # a device's warm start comes to the host here
            host = to_host(leaf) if is_foreign_array(leaf) else leaf
            items[f"{_STATE}/{path}" if path else _STATE] = host
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
    path: Path,
    run: RunInfo,
    *,
    resume: bool = False,
    replace: bool = False,
    make_directory: bool = False,
) -> TrajectoryWriter:
    """The sink factory registered for ``.h5`` (:func:`lieflow.sinks.open_sink`): a
    :class:`TrajectoryWriter` on ``path`` for ``run`` — continuing the file from its last
    checkpoint with ``resume`` (if it exists), else creating it (an existing file only with
    ``replace``; a missing directory only with ``make_directory``)."""
    fields = {f.name: getattr(run, f.name) for f in attrs.fields(RunInfo)}
    output = _as_path(path, "out")
    if not make_directory:  # a configuration's output was checked when it was read
        output = check_output_path(output, "out")  # not a directory, writable
    header = TrajectoryHeader(**fields, output=output, replace=replace,
                              make_directory=make_directory)  # fmt: skip
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
    H0 = np.asarray(system.hamiltonian(W0), dtype=np.float64)
    C0 = np.asarray(system.casimirs(W0), dtype=np.float64)
    batch = W0.shape[:-2]
    labels = [
        _ensemble_labels(header.config_text, n) if len(batch) == 1 else np.arange(n) for n in batch
    ]
    casimir_labels = np.asarray(powers if len(powers) == C0.shape[-1] else
                                np.arange(C0.shape[-1]), dtype=np.int64)  # fmt: skip
    _lay_out(f, meta, W0, H0, C0, labels, casimir_labels)
    extra, _ = driver.extra_hook(system, header.save_every)
    if extra is not None:
        _append_extra(f, [(0, 0.0, extra(W0))])


def _lay_out(
    f: h5py.File,
    meta: Mapping[str, Any],
    W0: Array,
    H0: Array,
    C0: Array,
    labels: list[Array],
    casimir_labels: Array,
) -> None:
    """Write the header attributes ``meta``, the dimensions, the variables and step 0 of a
    new file (format version 2): the initial state ``W0``, its energy ``H0`` and Casimirs
    ``C0``, the labels of its ensemble axes and of its Casimirs; both checkpoint slots hold
    ``W0`` at step 0. What :meth:`TrajectoryWriter.create` writes, and what
    :func:`lieflow.app.salvage.salvage` rebuilds a damaged file on."""
    for key, value in meta.items():
        f.attrs[key] = value
    h5py = _h5py()
    props = (
        f"version=2,lieflow={meta.get('lieflow_version', '')},"
        f"hdf5={h5py.version.hdf5_version},h5py={h5py.__version__}"
    )
    f.attrs["_NCProperties"] = np.array(props, dtype=h5py.string_dtype("ascii", len(props)))
    # dimensions: the two unlimited axes first (ids 0, 1), then the fixed ones
    time = _coordinate(_growable(f, "time", np.float64(0), np.float64), 0)
    step = _coordinate(_growable(f, "step", np.int64(0), np.int64), 1)
    dimid = 2
    ens = []
    for name, values in zip(_batch_dims(len(labels)), labels, strict=True):
        values = np.asarray(values, dtype=np.int64)
        ens.append(_coordinate(f.create_dataset(name, data=values, **_checked(values)), dimid))
        dimid += 1
    row = _dimension(f, "row", W0.shape[-2], dimid=dimid)
    col = _dimension(f, "col", W0.shape[-1], dimid=dimid + 1)
    casimir_labels = np.asarray(casimir_labels, dtype=np.int64)
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
    initial.attrs[_HEADER_COPY] = np.bytes_(_header_copy(meta).encode())
    rows = {
        time: 0.0, step: 0, saved: 0, W: W0,
        variables["energy"]: H0, variables["energy_error"]: np.zeros_like(H0),
        variables["casimirs"]: C0, variables["casimir_drift"]: np.zeros_like(C0),
        variables["iterations"]: 0, variables["residual"]: np.nan,
    }  # fmt: skip
    for ds, value in rows.items():
        ds.resize(1, axis=0)
        ds[0] = value
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
