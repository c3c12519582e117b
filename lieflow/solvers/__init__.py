"""Nonlinear solvers behind the :class:`Solver` protocol."""

from __future__ import annotations

from typing import Any

from .base import ImplicitProblem, Solver, SolveResult
from .fixed_point import FixedPoint, FrozenB, StoppingRule
from .newton import Auto, Newton


def get(name: str, **params: Any) -> Solver:
    """Build the registered solver ``name`` with ``params``."""
    from ..plugins import default_registry

    solver: Solver = default_registry().create("solver", name, **params)
    return solver


def available() -> list[str]:
    """Names of the registered solvers."""
    from ..plugins import default_registry

    return sorted(default_registry().solvers)


__all__ = [
    "Auto",
    "FixedPoint",
    "FrozenB",
    "ImplicitProblem",
    "Newton",
    "SolveResult",
    "Solver",
    "StoppingRule",
    "available",
    "get",
]
