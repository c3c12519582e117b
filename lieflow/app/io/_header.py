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
    """What a :class:`TrajectoryWriter` needs to know about a run: the run's
    :class:`~lieflow.sinks.RunInfo` (system, names, ``h``, ``save_every``,
    ``requested_steps``, ``identity``, ``W0``, configuration),
    written as the file's header, and where and how to write it.

    ``lieflow run`` builds it from its configuration (:meth:`of`), :func:`lieflow.integrate`
    with ``out=`` from its arguments (:func:`trajectory_sink`); both open the file through
    :func:`lieflow.sinks.open_sink`.

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
    """

    output: Path = attrs.field(kw_only=True)
    replace: bool = attrs.field(default=False, kw_only=True)
    make_directory: bool = attrs.field(default=False, kw_only=True)

    @classmethod
    def of(cls, setup: BuiltRun) -> TrajectoryHeader:
        """The trajectory file's header for the run ``setup`` (:func:`lieflow.app.config.build`):
        its :meth:`~lieflow.app.config.BuiltRun.info`, written to its ``output``, whose
        directory is made if missing."""
        return cls.from_info(setup.info(), output=setup.output, replace=setup.replace,
                             make_directory=True)  # fmt: skip

    @classmethod
    def from_info(
        cls, info: RunInfo, *, output: Path, replace: bool = False, make_directory: bool = False
    ) -> TrajectoryHeader:
        """``info`` written to ``output`` (see the attributes)."""
        fields = {f.name: getattr(info, f.name) for f in attrs.fields(RunInfo)}
        return cls(**fields, output=output, replace=replace, make_directory=make_directory)


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
