"""Writing trajectory files as a run goes: :class:`TrajectoryWriter` (the ``.h5`` sink): the
write-ahead of per-step diagnostics and saved states, checkpoints, resume's truncation, and
stopping cleanly when the disk is full. A new file's layout is in ``_new_file``, the
checkpoint slots in ``_slots``, the disk in ``_disk``.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ... import _signals, state_trees
from ...algebras import Array
from ...backends import is_foreign_array
from ...chunks import Chunk, ChunkDiagnostics
from ...errors import ConvergenceError, LieflowError
from ...sinks import Ending, RunInfo, to_host
from ...solution import Solution, Status
from ..config import BuiltRun, check_output_path
from ._disk import (
    _ATTRIBUTES_ROOM,
    _close_quietly,
    _ensure_space,
    _exists_error,
    _file_id,
    _publish,
    _sync,
)
from ._format import (
    _EXTRA,
    _PER_STEP,
    _PER_UPDATE,
    _STATE,
    _as_path,
    _h5py,
    _is_scale,
    _Layout,
    _where,
)
from ._header import TrajectoryHeader, _header
from ._lock import (
    _CHUNK_CACHE_BYTES,
    _RESUME_FIX,
    _WRITE_ERRORS,
    _cannot_create,
    _disk_full,
    _no_space,
    _open,
    _OutputLock,
    _Reading,
    salvage_fix,
)
from ._new_file import _append_extra, _initialise
from ._reader import (
    Checkpoint,
    _check_format,
    _header_attributes,
    _verify_for_resume,
    read_diagnostics,
    read_extra,
)
from ._slots import _write_slot

if TYPE_CHECKING:  # pragma: no cover
    import h5py


#: Saved states are written ahead of the next checkpoint once the buffer holds this many
#: bytes of them (a resume drops such rows until a checkpoint covers them): thousands of
#: small states per write, a large one at once.
_BUFFER_BYTES = 1 << 16


class TrajectoryWriter:
    """Appends a run to an open trajectory file: the application's
    :class:`~lieflow.sinks.Sink` for ``.h5`` files (``TrajectorySink``).

    Create one with :meth:`create` (a new file), :meth:`reopen` (resume) or :meth:`open`
    (either). :func:`lieflow.stepping.run` feeds every :class:`~lieflow.chunks.Chunk` of steps
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
        self, f: h5py.File, header: TrajectoryHeader | BuiltRun, lock: _OutputLock | None = None
    ) -> None:
        header = _header(header)
        self._f = f
        self._lock = lock
        self._path = Path(f.filename)
        self._file_id = _file_id(f)
        self._layout = layout = _check_format(f, self._path)
        at = layout.paths
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
        return _header_attributes(self._f) if self._f.id.valid else dict(self._attributes)

    @property
    def max_energy_error(self) -> float:
        """Largest relative energy error recorded so far (buffered steps included)."""
        return self._max_error

    # -- creation --------------------------------------------------------------------------

    @classmethod
    def create(cls, run: TrajectoryHeader | BuiltRun) -> TrajectoryWriter:
        """Create ``run.output`` holding the header and step 0, and lock it (``run``: a
        :class:`TrajectoryHeader`, or a :class:`~lieflow.app.config.BuiltRun` for its header).

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
    def reopen(cls, run: TrajectoryHeader | BuiltRun) -> tuple[TrajectoryWriter, Checkpoint]:
        """Open ``run.output`` to resume, lock it, and return the writer and the last
        checkpoint; everything written after that checkpoint is dropped (``run``: a
        :class:`TrajectoryHeader`, or a :class:`~lieflow.app.config.BuiltRun` for its header).

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
    def open(cls, run: TrajectoryHeader | BuiltRun, *, resume: bool = False) -> TrajectoryWriter:
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
        """Buffer ``chunk``: its diagnostics, its states where ``keep`` is true, and its
        last state and flow state for the next checkpoint. Nothing is written until
        :meth:`checkpoint`."""
        if diagnostics is None:  # a file records every step's: the run computes them
            raise LieflowError(
                f"{self._path}: a trajectory file records every step's diagnostics, and the "
                "run passed none. To fix: run through lieflow.integrate(out=...) or "
                "lieflow.runs.RunSpec.execute, or pass stepping.run(diagnostics="
                "Diagnostics.of(system, W0, save_every=...))"
            )
        keep = np.asarray(keep, dtype=bool)
        entry = (chunk.index[keep], to_host(chunk.states(keep)), to_host(chunk.iterations),
                 to_host(chunk.residuals), diagnostics)  # fmt: skip
        last = (chunk.stop, chunk.h, np.array(to_host(chunk.W[-1])), chunk.state)
        # one append and one assignment: recorded entirely or not at all
        self._buffer.append(entry)
        self._last = last
        self._max_error = max(self._max_error, diagnostics.max_energy_error)
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
        for path, leaf in state_trees.paths(state):  # a device's warm start comes to the host here
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
            self._attributes = _header_attributes(f)
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
            extra=read_extra(self._path),
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
    output = _as_path(path, "out")
    if not make_directory:  # a configuration's output was checked when it was read
        output = check_output_path(output, "out")  # not a directory, writable
    header = TrajectoryHeader.from_info(run, output=output, replace=replace,
                                        make_directory=make_directory)  # fmt: skip
    return TrajectoryWriter.open(header, resume=resume)


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
