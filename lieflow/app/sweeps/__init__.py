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

The package's modules, one concern each: ``_grid`` (the grid and its runs), ``_worker``
(one run on a worker), ``_files`` (what a run's file says), ``_store`` (the Zarr store),
``_executors`` (process pool, Dask), ``_coordinator`` (submitting, collecting, the
manifest), ``_progress`` (monitors) and ``_sweep`` (:func:`sweep`).
"""

from __future__ import annotations

from ..datasets import MANIFEST, SWEEP_FORMAT
from ._coordinator import STATUSES, SWEEP_FORMAT_VERSION
from ._files import file_status
from ._grid import Axis, Sweep, SweepRun, load_sweep, parse_sweep, run_id
from ._progress import SweepMonitor, SweepProgress
from ._sweep import STORES, SweepResult, sweep
from ._worker import run_task

__all__ = [
    "MANIFEST",
    "STATUSES",
    "STORES",
    "SWEEP_FORMAT",
    "SWEEP_FORMAT_VERSION",
    "Axis",
    "Sweep",
    "SweepMonitor",
    "SweepProgress",
    "SweepResult",
    "SweepRun",
    "file_status",
    "load_sweep",
    "parse_sweep",
    "run_id",
    "run_task",
    "sweep",
]
