"""Running a sweep: :func:`sweep` (the grid, the executor, the sweep directory's lock) and
how it ended (:class:`SweepResult`)."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import attrs

from ...errors import InputError, LieflowError
from ..datasets import MANIFEST, ZARR_STORE
from ._coordinator import STATUSES, _Coordinator
from ._executors import _dask_executor, _executor_of, _LocalPool, _require, _thread_env
from ._grid import Sweep, load_sweep
from ._progress import SweepMonitor

#: Stores :func:`sweep` can write besides the trajectory files (``store=``).
STORES = ("zarr",)


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
        from ..datasets import open_sweep

        return open_sweep(self.manifest, **kwargs)


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
    from ..io import OutputBusyError, _OutputLock

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
