"""The ``lieflow`` entry point of this distribution: registers ``"euler_zeitlin"`` and its
``lieflow plot`` figures (vorticity snapshots, energy and enstrophy drift)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lieflow

from .system import EulerZeitlin


def plot_run(trajectory: Any, out_dir: Path, stem: str) -> list[Path]:
    """Vorticity snapshots and drift of an ``euler_zeitlin`` run (imports matplotlib lazily:
    :func:`lieflow_zeitlin.plotting.plot_run`)."""
    from .plotting import plot_run as plot

    return plot(trajectory, out_dir, stem)


@lieflow.hookimpl
def lieflow_register(registry: lieflow.RegistryBuilder) -> None:
    """Register :class:`~lieflow_zeitlin.EulerZeitlin` as the system ``"euler_zeitlin"`` and
    its ``lieflow plot`` figures."""
    registry.add_system(
        "euler_zeitlin",
        EulerZeitlin,
        "Euler equations on the sphere, Zeitlin's su(N) model (Hoppe–Yau Laplacian)",
    )
    registry.add_plotter(
        "euler_zeitlin", plot_run, "vorticity snapshots on the sphere, energy/enstrophy drift"
    )
