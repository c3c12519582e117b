"""Running a configuration into a trajectory file: :func:`run` (a
:class:`~lieflow.app.config.BuiltRun`) and its :class:`TrajectorySummary`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import attrs

from ... import _signals
from ...errors import LieflowError
from ...sinks import Sink, open_sink
from ...stepping import Monitor
from ..config import BuiltRun
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
    """Integrate ``setup`` and write the trajectory to ``setup.output`` as it proceeds: its
    :class:`~lieflow.runs.RunSpec` (``W0`` placed on the device before the file is opened:
    a device that is not there leaves no file), executed into the file's sink, opened
    through :func:`lieflow.sinks.open_sink` as :func:`lieflow.integrate` opens it.

    Memory: the writer buffers each chunk's diagnostics (a few numbers per step) and only
    the states it will save; at every checkpoint (every ``[run] checkpoint`` seconds, and
    at the end) they are written in one block.

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
    with _signals.Interrupts() as stop:  # Ctrl-C held from here until stepping, raised there
        spec = setup.spec()  # W0 on its device first: a device not there leaves no file
        info = spec.info(config_text=setup.config.text, config_source=setup.config.source)
        writer = open_sink(setup.output, info, resume=resume, replace=setup.replace,
                           make_directory=True)  # fmt: skip
        assert isinstance(writer, TrajectoryWriter)
        try:
            done = 0 if writer.start is None else writer.start.step
            sinks = (writer, *(more_sinks(writer) if more_sinks is not None else ()))
        except BaseException:  # Ctrl-C before stepping: the file says so, and is resumable
            writer.close("interrupted", None, 0.0)
            raise
        outcome = spec.execute(sinks, monitor=monitor, interrupts=stop)
    completed = writer.completed_steps
    summary = TrajectorySummary(
        setup.output,
        outcome.status,
        completed,
        spec.steps,
        completed - done,
        outcome.wall_time,
        writer.max_energy_error,
        "" if outcome.failure is None else str(outcome.failure),
    )
    if summary.status == "failed":
        raise LieflowError(
            f"{summary.failure} The {summary.completed_steps} steps before the failure are "
            f"saved in {str(setup.output)!r} (status 'failed')."
        )
    return summary
