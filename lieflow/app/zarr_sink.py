"""A sweep's runs written straight into its Zarr store: :class:`ZarrSink`.

A sweep with ``store="zarr"`` feeds each run's steps to two sinks of one
:func:`lieflow.stepping.run` call: the run's trajectory file (the
:class:`~lieflow.app.io.TrajectoryWriter`, the resume point: checkpoints with the flow's
state, checksums, the lock) and a :class:`ZarrSink` writing the run's group of the store
(``DIRECTORY/runs.zarr/<id>``) as the steps come. The group holds what
:func:`~lieflow.app.datasets.write_zarr_run` would copy from the finished file — the same
arrays, dtypes and attributes — so :func:`lieflow.open_sweep` gives the same dataset; the
file is not read back.

The sink checkpoints when the file does (the stepping loop calls both), so the group's
``lieflow_stored_steps`` (written last, in one write with the header) equals the file's
checkpoint. A resume continues the group when it holds exactly the file's checkpoint;
otherwise (a worker killed between the two checkpoints, a store added later) the sink
writes nothing and :attr:`ZarrSink.in_sync` is false: the sweep then rebuilds the group
from the file. A failure to write the store is never the run's failure: it is kept in
:attr:`ZarrSink.error` and the sink stops writing.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .. import _signals
from ..algebras import Array
from ..chunks import Chunk, ChunkDiagnostics, Diagnostics
from ..errors import ConvergenceError
from ..sinks import Ending, to_host
from .datasets import (
    _CHUNK_BYTES,
    _DIAGNOSTICS,
    _LABELS,
    _SAVED,
    _SAVED_MAX,
    _STORED,
    _jsonable,
    _zarr,
)

if TYPE_CHECKING:
    from .io import TrajectoryWriter

__all__ = ["ZarrSink"]

#: Saved states are written ahead of the next checkpoint once the buffer holds this many
#: bytes of them (rows past ``lieflow_stored_steps`` are never read).
_BUFFER_BYTES = 4 << 20


def _rows(length: int, row: Array) -> int:
    """Rows per chunk of an array of ``length`` rows like ``row`` (as
    :func:`~lieflow.app.datasets.write_zarr_run`: about 8 MiB, at most the array)."""
    return max(1, min(length, _CHUNK_BYTES // max(1, row.nbytes)))


def _saved_states(steps: int, save_every: int) -> int:
    """States a complete run of ``steps`` saves: every ``save_every``-th and the last."""
    return steps // save_every + 1 + (steps % save_every != 0)


class ZarrSink:
    """Writes one run of a sweep into its group ``name`` of the Zarr store ``store``, next
    to the run's trajectory file (``writer``): a :class:`~lieflow.sinks.Sink`.

    Open it with :meth:`open` once ``writer`` has created or reopened the file (a resume
    continues at ``writer.start``).
    """

    def __init__(self, store: Path, name: str, writer: TrajectoryWriter) -> None:
        self.path = Path(store) / name
        self._writer = writer
        header = writer.header
        self._h = header.h
        self._system = header.system
        self._W0 = np.asarray(header.W0)
        self._save_every = header.save_every
        self._group: Any = None
        self._arrays: dict[str, Any] = {}
        #: arrays not created yet: their step-0 rows and expected length
        self._first: dict[str, tuple[Array, int]] = {}
        #: why the sink stopped writing (a failed write, a group not at the file's
        #: checkpoint), or ``""``
        self.error = ""
        self._buffer: list[tuple[Array, Array, Array, Array, ChunkDiagnostics]] = []
        self._buffered = 0
        self._last: tuple[int, Array] | None = None  # (step, state) last recorded
        self._step = 0  # the group's stored steps
        self._n_diag = 1  # rows of the per-step arrays (steps 0..n-1)
        self._n_saved = 1
        self._saved_to = 0  # the last saved step
        self._saved: list[int] = [0]  # saved steps (for the group's attribute)
        self._diagnostics: Diagnostics | None = None
        self._ensemble = self._labels()

    @classmethod
    def open(cls, store: Path | str, name: str, writer: TrajectoryWriter) -> ZarrSink:
        """The sink of ``writer``'s run in group ``name`` of ``store``: a new group for a new
        file, the group continued at the file's checkpoint for a resumed one."""
        sink = cls(Path(store), name, writer)
        try:
            if writer.start is None:
                sink._create()
            else:
                sink._continue(writer.start.step)
        except Exception as exc:
            sink._fail(exc)
        return sink

    @property
    def in_sync(self) -> bool:
        """Whether the group holds the file's steps (its checkpoint) and nothing failed."""
        return not self.error and self._step == self._writer.completed_steps

    # -- opening ---------------------------------------------------------------------------

    def _create(self) -> None:
        """A new group with the header; its arrays start with step 0 (as the file's
        ``_initialise``), chunked for the steps asked for, and are created with the first
        rows written after it (one write each, as a copy of the file would)."""
        zarr = _zarr()
        system, W0 = self._system, self._W0
        header = self._writer.header
        H0 = np.asarray(system.hamiltonian(W0), dtype=np.float64)
        C0 = np.asarray(system.casimirs(W0), dtype=np.float64)
        steps = header.requested_steps + 1
        saved = _saved_states(header.requested_steps, self._save_every)
        first: dict[str, tuple[Array, int]] = {
            "saved_step": (np.zeros(1, dtype=np.int64), saved),
            "time": (np.zeros(1), saved),
            "W": (W0[None], saved),
            "energy": (H0[None], steps),
            "energy_error": (np.zeros_like(H0)[None], steps),
            "casimirs": (C0[None], steps),
            "casimir_drift": (np.zeros_like(C0)[None], steps),
            "iterations": (np.zeros(1, dtype=np.int64), steps),
            "residual": (np.full(1, np.nan), steps),
        }
        labels = self._ensemble
        if labels is not None:
            first["ensemble"] = (labels, len(labels))
        self._group = zarr.open_group(str(self.path), mode="w", attributes=self._header())
        self._first = first

    def _continue(self, step: int) -> None:
        """Continue the group at the file's checkpoint ``step`` (rows past it dropped), if
        it holds that many steps; else stop writing (:attr:`in_sync` false)."""
        zarr = _zarr()
        try:
            group = zarr.open_group(str(self.path), mode="r+")
        except Exception:  # no group yet (a store added to a sweep begun without one)
            group = None
        stored = None if group is None else group.attrs.get(_STORED)
        if stored != step:
            self.error = f"the store's group holds {stored} steps, the file {step}"
            return
        names = ("saved_step", "time", "W", *_DIAGNOSTICS)
        self._arrays = {key: group[key] for key in names}
        saved = np.asarray(self._arrays["saved_step"][...])
        n = int(np.searchsorted(saved, step, side="right"))
        for key in names:
            rows = n if key in ("saved_step", "time", "W") else step + 1
            array = self._arrays[key]
            array.resize((rows, *array.shape[1:]))
        self._group = group
        self._step, self._n_diag, self._n_saved = step, step + 1, n
        self._saved = [int(k) for k in saved[:n]]
        self._saved_to = self._saved[-1]

    def _labels(self) -> Array | None:
        """The ensemble's labels, as the file stores them (one batch axis only)."""
        from .io import _ensemble_labels

        batch = self._W0.shape[:-2]
        if len(batch) != 1:
            return None
        return np.asarray(_ensemble_labels(self._writer.header.config_text, batch[0]))

    def _header(self) -> dict[str, Any]:
        return {key: _jsonable(value) for key, value in self._writer.attributes().items()}

    # -- the Sink protocol -----------------------------------------------------------------

    def record(self, chunk: Chunk, keep: Array, diagnostics: ChunkDiagnostics | None) -> None:
        """Buffer the chunk's kept states and its per-step rows (written ahead once the
        buffered states reach 64 KiB; never read before :meth:`checkpoint` covers them)."""
        if self._group is None:
            return
        if diagnostics is None:
            if self._diagnostics is None:
                self._diagnostics = Diagnostics.of(self._system, self._W0,
                                                   save_every=self._save_every)  # fmt: skip
            diagnostics = self._diagnostics.of_chunk(chunk)
        keep = np.asarray(keep, dtype=bool)
        states = to_host(chunk.states(keep))
        self._buffer.append((chunk.index[keep], states, to_host(chunk.iterations),
                             to_host(chunk.residuals), diagnostics))  # fmt: skip
        self._last = (chunk.stop, np.array(to_host(chunk.W[-1])))
        if keep.any():
            self._saved_to = int(chunk.index[keep][-1])
            self._buffered += states.nbytes
            if self._buffered >= _BUFFER_BYTES:
                with _signals.deferred():
                    self._guard(self._write_rows)

    def checkpoint(self, *, keep_last: bool = False) -> None:
        """Write the buffered rows (and the last state, with ``keep_last``), then the
        header with the steps held (one write, the last)."""
        if self._group is None or self._last is None:
            return

        def write() -> None:
            self._write_rows(keep_last=keep_last)
            self._commit()

        with _signals.deferred():
            self._guard(write)

    def close(self, status: Ending, failure: ConvergenceError | None, wall_time: float) -> None:
        """Write the header as the file was closed (status, wall time, failure)."""
        if self._group is not None:
            self._guard(self._commit)
        self._buffer, self._last, self._group = [], None, None

    def result(self) -> None:
        """Nothing: the run's result comes from its file."""
        return None

    # -- writing ---------------------------------------------------------------------------

    def _guard(self, write: Callable[[], None]) -> None:
        try:
            write()
        except Exception as exc:
            self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        self.error = f"{type(exc).__name__}: {exc}"
        self._group, self._buffer, self._last = None, [], None

    def _write_rows(self, *, keep_last: bool = False) -> None:
        buf, n0 = self._buffer, self._n_diag
        steps = np.zeros(0, dtype=np.int64)
        kept: list[Array] = []
        if buf:
            columns = {
                "energy": [b[4].energy for b in buf],
                "energy_error": [b[4].energy_error for b in buf],
                "casimirs": [b[4].casimirs for b in buf],
                "casimir_drift": [b[4].casimir_drift for b in buf],
                "iterations": [b[2] for b in buf],
                "residual": [b[3] for b in buf],
            }
            for key, parts in columns.items():
                # on the host: the stepping loop hands sinks host chunks, their diagnostics too
                self._append(key, n0, np.concatenate(parts))
            self._n_diag = n0 + sum(len(b[2]) for b in buf)
            steps = np.concatenate([b[0] for b in buf]).astype(np.int64)
            kept = [b[1] for b in buf]
        if keep_last and self._last is not None and self._saved_to != self._last[0]:
            steps = np.append(steps, np.int64(self._last[0]))
            kept.append(self._last[1][None])
            self._saved_to = self._last[0]
        if steps.size:
            n = self._n_saved
            for key, value in (("saved_step", steps), ("time", steps * self._h),
                               ("W", np.concatenate(kept))):  # fmt: skip
                self._append(key, n, value)
            self._n_saved = n + steps.size
            self._saved.extend(int(k) for k in steps)
        self._buffer, self._buffered = [], 0

    def _append(self, key: str, at: int, values: Array) -> None:
        """Write ``values`` as rows ``at:`` of array ``key`` (creating it: its first rows)."""
        if key in self._first:
            self._materialize(key, values)
            return
        array = self._arrays[key]
        array.resize((at + len(values), *array.shape[1:]))
        array[at:] = values.astype(array.dtype, copy=False)

    def _materialize(self, key: str, more: Array | None = None) -> None:
        """Create array ``key``: its step-0 rows, then ``more``."""
        head, length = self._first.pop(key)
        value = head if more is None else np.concatenate([head, more.astype(head.dtype)])
        chunks = (_rows(length, head[:1]), *head.shape[1:])
        array = self._group.create_array(key, shape=value.shape, dtype=head.dtype, chunks=chunks)
        array[...] = value
        self._arrays[key] = array

    def _commit(self) -> None:
        """The header and the steps held, in one write (the group's last)."""
        header = self._header()
        if not header:  # the file was abandoned (a full disk): its header is unknown
            raise OSError("the run's file was abandoned")
        for key in list(self._first):
            self._materialize(key)
        if self._last is not None:
            self._step = self._last[0]
        done: dict[str, Any] = {_STORED: self._step}
        labels = self._ensemble
        if labels is not None:
            done[_LABELS] = labels.tolist()
        if self._n_saved <= _SAVED_MAX:
            done[_SAVED] = [self._saved, [k * self._h for k in self._saved]]
        self._group.attrs.put({**header, **done})
