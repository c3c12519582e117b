"""The ``lieflow`` entry point of this distribution: registers ``"euler_zeitlin"``."""

from __future__ import annotations

import lieflow

from .system import EulerZeitlin


@lieflow.hookimpl
def lieflow_register(registry: lieflow.RegistryBuilder) -> None:
    """Register :class:`~lieflow_zeitlin.EulerZeitlin` as the system ``"euler_zeitlin"``."""
    registry.add_system(
        "euler_zeitlin",
        EulerZeitlin,
        "Euler equations on the sphere, Zeitlin's su(N) model (Hoppe–Yau Laplacian)",
    )
