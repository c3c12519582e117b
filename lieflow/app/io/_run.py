"""Running a configuration into a trajectory file: :func:`run` (a
:class:`~lieflow.app.config.BuiltRun`), :func:`run_flow` (any flow) and their
:class:`TrajectorySummary`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import attrs
import numpy as np

from ... import _signals, driver, tree
from ...backends import place
from ...driver import Cadence, Diagnostics, Monitor
from ...errors import ConvergenceError, LieflowError
from ...sinks import Sink
from ..config import BuiltRun
from ._header import TrajectoryHeader
from ._writer import TrajectoryWriter

#: ``more_sinks(writer) -> sinks``: sinks a run writes besides its trajectory file (:func:`run`).
MoreSinks = Callable[[TrajectoryWriter], Sequence[Sink]]


@attrs.frozen
class TrajectorySummary:
    """How :func:`run` ended.

    Attributes
    ----------
    path : Path
        The trajectory file.
    status : str
        ``"complete"``, ``"interrupted"`` (Ctrl-C; resumable) or ``"failed"``.
    completed_steps, requested_steps : int
        Steps in the file and steps asked for.
    new_steps : int
        Steps computed by this call.
    wall_time : float
        Seconds this call spent stepping.
    max_energy_error : float
        Largest relative energy error in the file.
    failure : str
        The error message of a failed run.
    """

    path: Path
    status: str
    completed_steps: int
    requested_steps: int
    new_steps: int
    wall_time: float
    max_energy_error: float
    failure: str = ""


def run(
    setup: BuiltRun,
    *,
    resume: bool = False,
    monitor: Monitor | None = None,
    more_sinks: MoreSinks | None = None,
) -> TrajectorySummary:
    """Integrate ``setup`` and write the trajectory to ``setup.output`` as it proceeds.

    Parameters
    ----------
    setup : BuiltRun
        A validated run (:func:`lieflow.app.config.build`).
    resume : bool
        Continue the existing file from its last checkpoint (bit-for-bit the same as an
        uninterrupted run; ``[run] steps`` may have grown). Without an existing file the run
        starts afresh. Without ``resume`` an existing file is replaced.
    monitor : Monitor, optional
        Progress callbacks.
    more_sinks : callable, optional
        ``more_sinks(writer)``: more sinks fed the same steps as the file, opened once the
        file's :class:`TrajectoryWriter` is (a sweep's Zarr store).

    Returns
    -------
    TrajectorySummary
        ``status == "interrupted"`` after Ctrl-C (the file holds every step done).

    Raises
    ------
    ConfigError
        ``resume`` on a file of another configuration.
    LieflowError
        A step failed to converge (the file holds the steps before it, status "failed").
    """
    summary, _ = run_flow(TrajectoryHeader.of(setup), setup.flow(), resume=resume, monitor=monitor,
                          more_sinks=more_sinks)  # fmt: skip
    if summary.status == "failed":
        raise LieflowError(
            f"{summary.failure} The {summary.completed_steps} steps before the failure are "
            f"saved in {str(setup.output)!r} (status 'failed')."
        )
    return summary


def run_flow(
    header: TrajectoryHeader,
    flow: Any,
    *,
    resume: bool = False,
    monitor: Monitor | None = None,
    more_sinks: MoreSinks | None = None,
) -> tuple[TrajectorySummary, ConvergenceError | None]:
    """Advance ``flow`` and write the trajectory to ``header.output`` as it proceeds: the
    one consumer loop (:func:`lieflow.driver.run`) into a :class:`TrajectoryWriter`.

    Memory: the writer buffers each chunk's diagnostics (a few numbers per step) and only
    the states it will save; at every checkpoint (every ``header.checkpoint_seconds``, and
    at the end) they are written in one block.

    Returns
    -------
    (TrajectorySummary, ConvergenceError or None)
        How it ended (``"complete"``, ``"interrupted"`` after Ctrl-C, ``"failed"``), and
        the error of a failed step (the file then holds the steps before it).
    """
    with _signals.Interrupts() as stop:  # Ctrl-C held from here until stepping, raised there
        return _run_flow(header, flow, resume, monitor, stop, more_sinks)


def _run_flow(
    header: TrajectoryHeader,
    flow: Any,
    resume: bool,
    monitor: Monitor | None,
    interrupts: _signals.Interrupts,
    more_sinks: MoreSinks | None = None,
) -> tuple[TrajectorySummary, ConvergenceError | None]:
    target = header.requested_steps
    diagnostics = Diagnostics.of(header.system, header.W0, save_every=header.save_every)
    device = header.device
    # W0 placed before the file is opened: a device that is not there (its library missing,
    # no GPU) is refused with nothing written, so the corrected run needs no --force
    W0 = header.W0 if device == "cpu" else place(header.W0, device)
    writer = TrajectoryWriter.open(header, resume=resume)
    try:
        ck = writer.start
        if ck is None:
            W, state, done = W0, None, 0
        else:
            W, done = ck.W, ck.step
            state = ck.state(flow.init(W))
            if device != "cpu":  # placed once; chunks come back through the sinks
                W = place(W, device)
                state = tree.map_leaves(
                    lambda x: place(x, device) if isinstance(x, np.ndarray) else x, state
                )
        sinks = (writer, *(more_sinks(writer) if more_sinks is not None else ()))
    except BaseException:  # Ctrl-C before stepping: the file says so, and is resumable
        writer.close("interrupted", None, 0.0)
        raise
    outcome = driver.run(
        flow,
        W,
        header.h,
        target,
        sinks=sinks,
        diagnostics=diagnostics,
        save_every=header.save_every,
        start=done,
        state=state,
        monitor=monitor,
        checkpoint=Cadence(seconds=header.checkpoint_seconds),
        interrupts=interrupts,
    )
    completed = writer.completed_steps
    summary = TrajectorySummary(
        header.output,
        outcome.status,
        completed,
        target,
        completed - done,
        outcome.wall_time,
        writer.max_energy_error,
        "" if outcome.failure is None else str(outcome.failure),
    )
    return summary, outcome.failure
