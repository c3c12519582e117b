"""ISOSyRK schemes: the :class:`Scheme` interface and the built-in formulations."""

from __future__ import annotations

from typing import Any

from .base import Scheme, StageEquations, StepResult, TableauProblem, TableauScheme
from .block import BlockGauss, BlockProblem, ReducedProblem
from .modin_viviani import ModinViviani, ModinVivianiProblem
from .sydirk import MidpointProblem, SyDIRK


def get(name: str, **params: Any) -> Scheme:
    """Build the registered scheme ``name`` (e.g. ``"gauss3"``) with ``params``."""
    from ..plugins import default_registry

    scheme: Scheme = default_registry().create("scheme", name, **params)
    return scheme


def available() -> list[str]:
    """Names of the registered schemes."""
    from ..plugins import default_registry

    return sorted(default_registry().schemes)


__all__ = [
    "BlockGauss",
    "BlockProblem",
    "MidpointProblem",
    "ModinViviani",
    "ModinVivianiProblem",
    "ReducedProblem",
    "Scheme",
    "StageEquations",
    "StepResult",
    "SyDIRK",
    "TableauProblem",
    "TableauScheme",
    "available",
    "get",
]
