"""lieflow: structure-preserving integrators for isospectral Lie–Poisson systems.

``dW/dt = [B(W), W]`` integrated with isospectral symplectic Runge–Kutta (ISOSyRK) schemes:
the midpoint rule, symplectic DIRK compositions, the block algorithm for any symplectic
tableau (Gauss–Legendre of any order) and the classic Modin–Viviani form, with fixed-point,
Newton and frozen-B solvers.

>>> import lieflow as lf
>>> system = lf.systems.get("rigid_body", inertia=(1.0, 2.0, 3.0))
>>> sol = lf.integrate(system, lf.schemes.get("gauss3"), system.algebra.random(seed=0),
...                    h=0.1, steps=100)
>>> bool(sol.energy_error.max() < 1e-6)
True
"""

from __future__ import annotations

import importlib
from importlib.metadata import PackageNotFoundError, version
from typing import TYPE_CHECKING, Any

from . import algebras, chunks, flows, schemes, sinks, solvers, stepping, systems, tableaus
from .algebras import GL, SO, SU, LieAlgebra, U
from .errors import (
    AlgebraError,
    ConvergenceError,
    InputError,
    LieflowError,
    PluginError,
    RegistryError,
    TableauError,
)
from .flows import Flow, Projected, SchemeFlow, Splitting, StepStats, WarmStart
from .integration import Step, integrate, iterate
from .plugins import Registry, RegistryBuilder, default_registry, hookimpl, load_registry
from .schemes import Scheme, StepResult
from .sinks import MemorySink, Sink
from .solution import Solution, Status
from .solvers import ImplicitProblem, Solver, SolveResult
from .systems import IsospectralSystem
from .tableaus import ButcherTableau

if TYPE_CHECKING:
    from .app.datasets import open_run, open_sweep
    from .app.sweeps import load_sweep, parse_sweep, sweep

#: The application's user-facing names, re-exported on first use (PEP 562): ``import
#: lieflow`` loads no ``lieflow.app`` module.
_APP_NAMES = {
    "open_run": "lieflow.app.datasets",
    "open_sweep": "lieflow.app.datasets",
    "load_sweep": "lieflow.app.sweeps",
    "parse_sweep": "lieflow.app.sweeps",
    "sweep": "lieflow.app.sweeps",
}


def __getattr__(name: str) -> Any:
    if name == "app":
        return importlib.import_module("lieflow.app")
    module = _APP_NAMES.get(name)
    if module is None:
        raise AttributeError(f"module 'lieflow' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


try:
    __version__ = version("lieflow")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0+unknown"

__all__ = [
    "GL",
    "SO",
    "SU",
    "AlgebraError",
    "ButcherTableau",
    "ConvergenceError",
    "Flow",
    "ImplicitProblem",
    "InputError",
    "IsospectralSystem",
    "LieAlgebra",
    "LieflowError",
    "MemorySink",
    "PluginError",
    "Projected",
    "Registry",
    "RegistryBuilder",
    "RegistryError",
    "Scheme",
    "SchemeFlow",
    "Sink",
    "Solution",
    "SolveResult",
    "Solver",
    "Splitting",
    "Status",
    "Step",
    "StepResult",
    "StepStats",
    "TableauError",
    "U",
    "WarmStart",
    "__version__",
    "algebras",
    "chunks",
    "default_registry",
    "flows",
    "hookimpl",
    "integrate",
    "iterate",
    "load_registry",
    "load_sweep",
    "open_run",
    "open_sweep",
    "parse_sweep",
    "schemes",
    "sinks",
    "solvers",
    "stepping",
    "sweep",
    "systems",
    "tableaus",
]
