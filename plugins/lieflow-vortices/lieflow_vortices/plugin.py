"""The ``lieflow`` entry point of this distribution: registers ``"point_vortices"``."""

from __future__ import annotations

import lieflow

from .system import PointVortices


@lieflow.hookimpl
def lieflow_register(registry: lieflow.RegistryBuilder) -> None:
    """Register :class:`~lieflow_vortices.PointVortices` as the system ``"point_vortices"``."""
    registry.add_system(
        "point_vortices", PointVortices, "K point vortices on the unit sphere, so(3)^K"
    )
