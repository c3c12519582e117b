"""Isospectral Lie–Poisson systems: the abstract base and the built-ins."""

from __future__ import annotations

from typing import Any

from .base import IsospectralSystem
from .rigid_body import GeneralizedRigidBody, RigidBody, hat, vee
from .toda import PAPER_W0, PeriodicToda


def get(name: str, **params: Any) -> IsospectralSystem:
    """Build the registered system ``name`` (built-in or from a plugin) with ``params``."""
    from ..plugins import default_registry

    system: IsospectralSystem = default_registry().create("system", name, **params)
    return system


def available() -> list[str]:
    """Names of the registered systems."""
    from ..plugins import default_registry

    return sorted(default_registry().systems)


__all__ = [
    "PAPER_W0",
    "GeneralizedRigidBody",
    "IsospectralSystem",
    "PeriodicToda",
    "RigidBody",
    "available",
    "get",
    "hat",
    "vee",
]
