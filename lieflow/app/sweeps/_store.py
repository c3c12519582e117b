"""The sweep's Zarr store (``store="zarr"``): each run's group written by its worker as it
steps (:class:`~lieflow.app.zarr_sink.ZarrSink`, next to the run's file), rebuilt from
the file where it could not be, complete runs the store lacks copied in, and the
metadata consolidated."""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from ...errors import LieflowError
from ._grid import SweepRun


def _store_sink(task: Mapping[str, Any], opened: list[Any]) -> Any:
    """The run's sinks besides its file (:func:`lieflow.app.io.run`'s ``more_sinks``): with a
    Zarr store (``task["store"]``), a :class:`~lieflow.app.zarr_sink.ZarrSink` writing the
    run's group as it steps (appended to ``opened``); else None."""
    if not task.get("store"):
        return None
    from ..zarr_sink import ZarrSink

    def more_sinks(writer: Any) -> tuple[Any, ...]:
        sink = ZarrSink.open(task["store"], task["id"], writer)
        opened.append(sink)
        return (sink,)

    return more_sinks


def _store_run(task: Mapping[str, Any], out: dict[str, Any], opened: Sequence[Any]) -> None:
    """Make the run's group of the sweep's Zarr store (``task["store"]``) hold its file's
    steps: its :class:`~lieflow.app.zarr_sink.ZarrSink` wrote them as it stepped; only where
    it could not (the group was not at the file's checkpoint on a resume, a write failed)
    is the group rebuilt from the file. A failure is recorded in ``out["store_error"]``,
    never the run's failure (the dataset then reads the run from its file)."""
    if not task.get("store") or (opened and opened[-1].in_sync):
        return
    from ..datasets import write_zarr_run

    try:
        write_zarr_run(task["output"], task["store"], task["id"])
    except Exception as exc:
        out["store_error"] = f"{type(exc).__name__}: {exc}"


def _consolidate(store: Path) -> None:
    """Consolidate the store's metadata (one read opens it), if it exists."""
    if not store.is_dir():
        return
    with contextlib.suppress(Exception), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "not part of the Zarr format 3 specification"
        import zarr

        zarr.consolidate_metadata(str(store))


def _store_complete_runs(
    store: Path, runs: Sequence[SweepRun], records: Sequence[Mapping[str, Any]]
) -> None:
    """Create the Zarr store and write into it the complete runs it lacks (``records``: the
    manifest's records of ``runs``; a sweep run before without ``store``); the runs still to
    run are written by their workers."""
    import zarr

    from ..datasets import _STORED, write_zarr_run

    root = zarr.open_group(str(store), mode="a")
    for spec, rec in zip(runs, records, strict=True):
        if rec["status"] != "complete":
            continue
        group = root.get(spec.id)
        if group is not None and group.attrs.get(_STORED) == rec["completed_steps"]:
            continue
        with contextlib.suppress(LieflowError, OSError):
            write_zarr_run(spec.output, store, spec.id)
