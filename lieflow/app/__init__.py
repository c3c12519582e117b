"""The application built on lieflow's numerical core: command line, files, studies.

``lieflow`` itself holds the numerics (algebras, systems, tableaus, schemes, solvers, flows,
the driver and :func:`~lieflow.integrate`); this subpackage holds what turns them into runs
on disk and figures:

- :mod:`~lieflow.app.config` — TOML run configurations (``lieflow run``);
- :mod:`~lieflow.app.io` — trajectory files: writing as a run goes, resuming, reading;
- :mod:`~lieflow.app.datasets` — runs and sweeps as labelled :mod:`xarray` datasets;
- :mod:`~lieflow.app.sweeps` — grids of runs on a process pool, Dask, or any executor;
- :mod:`~lieflow.app.plotting` — figures of runs and sweeps;
- :mod:`~lieflow.app.progress` — progress bars;
- :mod:`~lieflow.app.reproduce` — the paper's experiments (``lieflow reproduce``);
- :mod:`~lieflow.app.cli` — the ``lieflow`` command.

The core's modules never import this package at module level; the few entry points that
reach it (``integrate(out=...)``, ``progress=True``, :meth:`~lieflow.Solution.to_xarray`)
import it when called. The user-facing names (:func:`lieflow.open_run`,
:func:`lieflow.open_sweep`, :func:`lieflow.sweep`, ...) are re-exported by ``lieflow``'s
``__init__``; none of these modules imports h5py, matplotlib, xarray or dask before it is
used.
"""
