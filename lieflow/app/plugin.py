"""The application's registrations, through the ``lieflow`` entry point ``app`` exactly as a
third-party plugin registers its own: the HDF5 trajectory sink for ``.h5`` files, so that
``lieflow.integrate(..., out="run.h5")`` writes the format ``lieflow run`` writes without
the core importing the application."""

from __future__ import annotations

from typing import Any

from ..plugins import RegistryBuilder, hookimpl


def _trajectory_sink(
    path: Any,
    run: Any,
    *,
    resume: bool = False,
    replace: bool = False,
    make_directory: bool = False,
) -> Any:
    """HDF5 (netCDF-4) trajectory file, as ``lieflow run`` writes (:mod:`lieflow.app.io`)."""
    from .io import trajectory_sink  # h5py and the file machinery on first use only

    return trajectory_sink(path, run, resume=resume, replace=replace,
                           make_directory=make_directory)  # fmt: skip


@hookimpl
def lieflow_register(registry: RegistryBuilder) -> None:
    """Register the application's file sinks."""
    registry.add_sink(".h5", _trajectory_sink)
