"""The file's own word on a run of a sweep: its status and steps, read from its trajectory
file (what decides which runs a sweep skips, resumes or records)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._grid import SweepRun


def _file_state(spec: SweepRun) -> dict[str, Any] | None:
    """The status and step counts a run's file records, or None (missing, locked,
    unreadable: the run is then attempted, and the attempt reports what is wrong)."""
    if not spec.output.exists():
        return None
    try:
        import h5py

        from ..io._format import _plain

        with h5py.File(spec.output, "r") as f:
            a = f.attrs
            return {
                "status": str(_plain(a.get("status", ""))),
                "completed_steps": int(a.get("completed_steps", 0)),
                "requested_steps": int(a.get("requested_steps", 0)),
                "identity": str(_plain(a.get("identity", ""))),
                "wall_time": float(a.get("wall_time", 0.0)),
            }
    except Exception:
        return None


def file_status(spec: SweepRun) -> str:
    """What a run's file says: ``"complete"``, ``"to run"`` (no file yet), or its status
    and steps (``"interrupted 120/400"``; ``"other config"`` when it is the file of another
    configuration); nothing is written."""
    state = _file_state(spec)
    if state is None:
        return "unreadable" if spec.output.exists() else "to run"
    if _is_complete(spec, state):
        return "complete"
    if state["identity"] != spec.config.identity():
        return "other config"
    return f"{state['status']} {state['completed_steps']}/{spec.config.run.steps}"


def _max_energy_error(path: Path) -> float | None:
    try:
        from ..io import read_diagnostics

        return float(np.max(read_diagnostics(path).energy_error))
    except Exception:
        return None


def _is_complete(spec: SweepRun, state: Mapping[str, Any] | None) -> bool:
    return (
        state is not None
        and state["status"] == "complete"
        and state["completed_steps"] == spec.config.run.steps
        and state["identity"] == spec.config.identity()
    )
