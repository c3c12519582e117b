"""Engines: how a scheme's steps are computed, chosen once per run.

One source of the numerics — the schemes' maps, the systems' ``B`` and projections, written
against the array API — and three ways to run it:

* ``"numpy"``, the eager engine: :class:`~lieflow.flows.SchemeFlow`, one array operation at
  a time, on NumPy or on the library of the array passed in (CuPy, PyTorch, JAX,
  ``array_api_strict``). Every system, scheme, solver and dtype.
* ``"compiled"``: numba-compiled loops for small NumPy systems
  (:mod:`lieflow.engines.compiled`), many steps per call.
* ``"jax"``, the traced engine (:mod:`lieflow.engines.traced`): the whole step compiled by
  ``jax.jit`` and run on the array's device, a chunk of steps per call with no host round
  trip per update — for JAX arrays and, through DLPack, CuPy and PyTorch arrays on a GPU;
  for NumPy arrays on JAX's CPU backend when asked by name.

``"auto"`` (the default) picks the compiled loops for small NumPy runs where they win
(:func:`lieflow.engines.compiled.wins`), the traced engine for arrays of a device library where it
runs the case, and the eager engine otherwise. :func:`scheme_flow` makes the choice; a step
an engine cannot finish is handed to the eager engine, so failures read the same on all.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from ..algebras import Array
from ..backends import is_numpy
from ..errors import InputError
from ..flows import SchemeFlow
from ..schemes.base import Scheme
from ..solvers.base import Solver
from ..systems.base import IsospectralSystem

__all__ = ["ENGINES", "Engine", "scheme_flow"]

#: The engines by name (``integrate(..., engine=...)``, ``[run] engine``).
ENGINES = ("auto", "numpy", "compiled", "jax")

Engine = Literal["auto", "numpy", "compiled", "jax"]


def scheme_flow(
    system: IsospectralSystem,
    scheme: Scheme,
    solver: Solver,
    W0: Array,
    steps: int,
    *,
    engine: Engine = "auto",
    warm_start: bool | int = True,
) -> SchemeFlow:
    """The :class:`SchemeFlow` that runs ``scheme`` on ``system`` with ``engine``.

    ``"numpy"``: a plain :class:`SchemeFlow` (eager, on the array's own library).
    ``"compiled"``: the numba loops
    (:class:`lieflow.engines.compiled_plan.CompiledSchemeFlow`), NumPy arrays only.
    ``"jax"``: the traced engine (:class:`lieflow.engines.traced.TracedSchemeFlow`).
    Both raise :class:`InputError` naming what is missing or unsupported. ``"auto"``: for
    NumPy arrays the compiled loops where supported, installed and faster
    (:func:`lieflow.engines.compiled.wins`, judged for ``steps`` steps of ``W0``), else
    eager; for arrays of another library the traced engine where JAX runs the case on the
    array's device, else eager. The flow is built once, of the class it ends up with.
    """
    if engine not in ENGINES:
        raise InputError(f"engine must be one of {', '.join(map(repr, ENGINES))}, got {engine!r}")
    if engine == "numpy":
        return SchemeFlow(system, scheme, solver, warm_start)
    if engine == "jax" or (engine == "auto" and not is_numpy(W0)):
        return _traced(system, scheme, solver, W0, engine, warm_start)
    if not is_numpy(W0):  # engine == "compiled"
        raise InputError(
            f"engine='compiled' runs NumPy arrays only, got a {type(W0).__module__} array; "
            "use engine='jax' (the traced engine) or 'auto'"
        )
    from . import compiled

    n = W0.shape[-1]
    K = W0.size // max(n * n, 1)
    # judged before plan(), which loads the system's compiled B, and before looking for
    # numba (a search of the import path: ~60 µs of a one-step call)
    if engine == "auto" and not (
        compiled.wins(n, steps, K, np.iscomplexobj(W0)) and compiled.available()
    ):
        return SchemeFlow(system, scheme, solver, warm_start)
    plan = compiled.plan(system, scheme, solver, W0)  # names a missing numba too
    if isinstance(plan, str):
        if engine == "compiled":
            raise InputError(f"engine='compiled' cannot run this case: {plan}; use engine='auto'")
        return SchemeFlow(system, scheme, solver, warm_start)
    return plan.flow(system, scheme, solver, warm_start)


def _traced(
    system: IsospectralSystem,
    scheme: Scheme,
    solver: Solver,
    W0: Array,
    engine: Engine,
    warm_start: bool | int,
) -> SchemeFlow:
    """The traced engine's flow, or (``"auto"``) the eager one where it cannot run."""
    from . import traced

    if engine == "auto" and not _on_jax_device(W0):
        return SchemeFlow(system, scheme, solver, warm_start)
    reason = traced.plan(system, scheme, solver, W0)
    if reason is None:
        return traced.TracedSchemeFlow(system, scheme, solver, warm_start)
    if engine == "jax":
        raise InputError(f"engine='jax' cannot run this case: {reason}; use engine='auto'")
    return SchemeFlow(system, scheme, solver, warm_start)


def _on_jax_device(W0: Array) -> bool:
    """Whether JAX can run on the device ``W0`` lives on: a JAX array, or a CuPy or PyTorch
    array on a device JAX also runs on (so DLPack shares it without a copy)."""
    try:
        import jax
    except ImportError:
        return False
    if isinstance(W0, jax.Array):
        return True
    try:
        platform = {"cpu": "cpu", "cuda": "gpu", "rocm": "gpu"}.get(_platform_of(W0), "")
        return bool(platform) and platform != "cpu" and bool(jax.devices(platform))
    except RuntimeError:  # JAX has no backend for that platform
        return False


def _platform_of(W0: Array) -> str:
    """``"cuda"``, ``"rocm"`` or ``"cpu"`` for a CuPy or PyTorch array ('' if unknown)."""
    device = getattr(W0, "device", None)
    kind = getattr(device, "type", None)  # torch.device
    if isinstance(kind, str):
        return kind
    if type(W0).__module__.startswith("cupy"):
        return "cuda"
    return ""
