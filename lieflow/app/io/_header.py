"""What a trajectory file records about its run: :class:`TrajectoryHeader` (the run's
identity, configuration and settings, written as the file's root attributes) and the
platform and package versions (:func:`environment`).
"""

from __future__ import annotations

import platform
import sys
from pathlib import Path

import attrs
import numpy as np

from ...sinks import RunInfo
from ..config import BuiltRun

#: Default seconds between the checkpoints of a trajectory file (:class:`TrajectoryHeader`).
CHECKPOINT_SECONDS = 1.0


@attrs.frozen(eq=False)
class TrajectoryHeader(RunInfo):
    """What a :class:`TrajectoryWriter` needs to know about a run: the file's header, the
    run's :class:`~lieflow.sinks.RunInfo` (system, names, ``h``, ``save_every``,
    ``requested_steps``, ``identity``, ``W0``) and where and how to write it.

    ``lieflow run`` builds it from its configuration (:meth:`of`), :func:`lieflow.integrate`
    with ``out=`` from its arguments (:func:`trajectory_sink`).

    Attributes
    ----------
    output : Path
        The trajectory file.
    replace : bool
        Whether a new run may replace an existing ``output``.
    make_directory : bool
        Whether a missing directory of ``output`` is created (``lieflow run``: yes, as
        ``--out results/run.h5`` promises) or refused (:func:`lieflow.integrate`: a library
        call creates no directory tree its caller did not ask for).
    config_text, config_source : str
        The configuration's text and where it came from (empty for ``integrate``).
    checkpoint_seconds : float or None
        Seconds between checkpoints (the resume point, flushed and fsync'd; and the last
        one when the run ends however it ends): saved states and diagnostics are buffered
        and written in blocks in between. ``0``: after every chunk of steps; ``None``:
        after every chunk that holds a saved state (``[run] checkpoint = "saves"``).
    device : str
        Where the steps run (``[run] device``, :func:`lieflow.backends.place`): the state and
        the warm start read from a checkpoint are placed there once.
    """

    output: Path
    replace: bool = False
    config_text: str = attrs.field(default="", repr=False)
    make_directory: bool = False
    config_source: str = ""
    checkpoint_seconds: float | None = CHECKPOINT_SECONDS
    device: str = "cpu"

    @classmethod
    def of(cls, setup: BuiltRun) -> TrajectoryHeader:
        """The trajectory file's header for the run ``setup`` (:func:`lieflow.app.config.build`)."""
        cfg = setup.config
        return cls(
            system=setup.system,
            system_name=cfg.system.name,
            scheme=cfg.scheme.name,
            solver=cfg.solver.name,
            h=cfg.run.h,
            save_every=cfg.run.save_every,
            requested_steps=cfg.run.steps,
            identity=cfg.identity(),
            W0=setup.W0,
            output=setup.output,
            replace=setup.replace,
            make_directory=True,
            config_text=cfg.text,
            config_source=cfg.source,
            checkpoint_seconds=cfg.run.checkpoint,
            device=cfg.run.device,
        )


def _header(run: TrajectoryHeader | BuiltRun) -> TrajectoryHeader:
    """``run`` as a :class:`TrajectoryHeader` (:meth:`TrajectoryHeader.of` a :class:`BuiltRun`)."""
    return run if isinstance(run, TrajectoryHeader) else TrajectoryHeader.of(run)


def environment() -> dict[str, str]:
    """Versions and platform recorded in every output (lieflow, Python, numpy, scipy, h5py)."""
    import scipy

    from ... import __version__

    info = {
        "lieflow_version": __version__,
        "python": sys.version.split()[0],
        "platform": platform.platform(),
        "machine": platform.machine(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }
    try:
        import h5py

        info["h5py"] = h5py.__version__
        info["hdf5"] = h5py.version.hdf5_version
    except ImportError:  # pragma: no cover
        pass
    return info
