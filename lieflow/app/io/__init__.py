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

The package's modules, one concern each: ``_format`` (format name and version, the two
layouts, the checkpoint digest, netCDF-4 dimensions), ``_lock`` (the output lock; busy,
damaged and full-disk errors), ``_header`` (what a file records about its run), ``_reader``
(reading and the checks of a resume), ``_disk`` (space kept in reserve, publishing a new
file, fsync), ``_new_file`` (a new file's layout and step 0), ``_slots`` (checkpoint slots),
``_writer`` (:class:`TrajectoryWriter`) and ``_run`` (:func:`run`). Every public name is
imported from here.
"""

from __future__ import annotations

# Besides ``__all__``, re-exported as before the split (``name as name``): the public
# CHECKPOINT_SECONDS and TrajectorySink, and the private helpers lieflow.app.datasets and
# lieflow.app.sweeps read as ``io._name``; other code imports a private helper from the
# module that defines it. salvage_fix and trajectory_sink (the ``app`` plugin's ``.h5``
# sink), public functions of the module before the split, are in ``__all__`` so that the
# API page still documents them.
from ...stepping import Monitor
from ._format import FORMAT, FORMAT_VERSION, checkpoint_digest
from ._format import _as_path as _as_path
from ._format import _h5py as _h5py
from ._header import CHECKPOINT_SECONDS as CHECKPOINT_SECONDS
from ._header import TrajectoryHeader, environment
from ._lock import DamagedOutputError, DiskFullError, OutputBusyError, salvage_fix
from ._lock import _open as _open
from ._lock import _OutputLock as _OutputLock
from ._lock import _Reading as _Reading
from ._new_file import _ensemble_labels as _ensemble_labels
from ._reader import (
    Checkpoint,
    Trajectory,
    TrajectoryDiagnostics,
    format_version,
    read_checkpoint,
    read_diagnostics,
    read_extra,
    read_trajectory,
)
from ._reader import _check_format as _check_format
from ._reader import _check_lengths as _check_lengths
from ._reader import _header_attributes as _header_attributes
from ._reader import _read_checkpoint as _read_checkpoint
from ._run import TrajectorySummary, run
from ._writer import TrajectorySink as TrajectorySink
from ._writer import TrajectoryWriter, trajectory_sink

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "Checkpoint",
    "DamagedOutputError",
    "DiskFullError",
    "Monitor",
    "OutputBusyError",
    "Trajectory",
    "TrajectoryDiagnostics",
    "TrajectoryHeader",
    "TrajectorySummary",
    "TrajectoryWriter",
    "checkpoint_digest",
    "environment",
    "format_version",
    "read_checkpoint",
    "read_diagnostics",
    "read_extra",
    "read_trajectory",
    "run",
    "salvage_fix",
    "trajectory_sink",
]
