"""The application built on lieflow's numerical core: command line, files, studies.

``lieflow`` itself holds the numerics (algebras, systems, tableaus, schemes, solvers, flows,
the stepping loop and :func:`~lieflow.integrate`); this subpackage holds what turns them into runs
on disk and figures:

- :mod:`~lieflow.app.config` — TOML run configurations (``lieflow run``);
- :mod:`~lieflow.app.io` — trajectory files: writing as a run goes, resuming, reading;
- :mod:`~lieflow.app.datasets` — runs and sweeps as labelled :mod:`xarray` datasets;
- :mod:`~lieflow.app.sweeps` — grids of runs on a process pool, Dask, or any executor;
- :mod:`~lieflow.app.plotting` — figures of runs and sweeps;
- :mod:`~lieflow.app.plugin` — what the application registers (the ``.h5`` trajectory sink);
- :mod:`~lieflow.app.reproduce` — the paper's experiments (``lieflow reproduce``);
- :mod:`~lieflow.app.cli` — the ``lieflow`` command.

The core never imports this package: ``integrate(out="run.h5")`` finds the trajectory
writer through the plugin registry (the entry point ``app``), and ``import lieflow`` loads
none of these modules. The user-facing names (:func:`lieflow.open_run`,
:func:`lieflow.open_sweep`, :func:`lieflow.sweep`, ...) are re-exported by ``lieflow``'s
``__init__`` on first use (PEP 562); none of these modules imports h5py, matplotlib, xarray
or dask before it is used, and each is imported on first access (``lieflow.app.io``).
"""

import importlib
from typing import Any

_SUBMODULES = ("cli", "config", "datasets", "io", "plotting", "plugin", "reproduce", "sweeps")


def __getattr__(name: str) -> Any:
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
