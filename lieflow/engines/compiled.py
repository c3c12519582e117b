r"""The compiled engine of :func:`lieflow.integrate`: many steps per call for small systems.

For tiny matrices (the so(3) rigid body, ensembles of them) a step costs a few hundred
floating-point operations and numpy's per-call overhead (microseconds per product, norm and
array) dominates by two orders of magnitude. This engine runs the same fixed-point
iterations in loops compiled with numba (``pip install 'lieflow[fast]'``), advancing a chunk
of steps per call, for the case where that is simple and exact:

* the system supplies its ``B`` compiled (:meth:`IsospectralSystem.compiled_B
  <lieflow.IsospectralSystem.compiled_B>`): by default every system whose ``B`` is an
  entrywise product :math:`B(W) = S \odot W` (:attr:`~lieflow.IsospectralSystem.hadamard_factor`:
  rigid bodies and the periodic Toda lattice, SPEC §3); any other system (a plugin's) by
  overriding the hook, as the point-vortex plugin does. ``B`` enters the loops as a typed
  compiled function, so they stay in numba's disk cache whatever the system;
* the scheme has a compiled form (:meth:`Scheme.compiled_form
  <lieflow.schemes.Scheme.compiled_form>`): compositions of midpoint steps
  (:class:`~lieflow.schemes.SyDIRK` and its subclasses, minimal variable form, SPEC
  §4.1–4.2) and the reduced stage form of a symplectic tableau
  (:class:`~lieflow.schemes.BlockGauss` with ``form="reduced"``, SPEC §4.5);
* the solver is plain :class:`~lieflow.solvers.FixedPoint` iteration (a subclass that
  keeps its map; with Anderson acceleration where it never engages, problems below
  :data:`lieflow.solvers.anderson.MIN_SIZE` numbers: the same iteration), or
  :class:`~lieflow.solvers.Auto` whose first solver is one (SPEC §5);
* the data are real ``float64``, or ``complex128`` on a skew-Hermitian algebra (u(n),
  su(N): Euler–Zeitlin), where every transpose of the real loops is a conjugate transpose.

Same maps, same stopping rule (the very function the numpy path calls,
:func:`lieflow.solvers.fixed_point.stopping_verdict`, compiled), same warm starts
(:class:`~lieflow.warm_start.WarmStart`) and the same per-step projection onto the phase space
(:meth:`IsospectralSystem.compiled_project <lieflow.IsospectralSystem.compiled_project>`;
without one, each chunk's states are projected by ``system.project`` afterwards) as the
numpy path. A step the
compiled solve does not accept is handed to the numpy path from the last good state and warm
state, so failures (:class:`~lieflow.errors.ConvergenceError` with its step index) and
``Auto``'s Newton fallback behave exactly as with ``engine="numpy"``.

Ensembles ``(K, n, n)`` are advanced trajectory by trajectory inside each step; each
trajectory's iteration stops by its own test (numpy stops a batch when all have converged),
the recorded iteration count of a step is the maximum over the ensemble, and the warm-start
trust is decided for the whole stack, as numpy does.
"""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable
from types import ModuleType
from typing import Any, TypeVar

import numpy as np

from ..algebras import Array
from ..schemes.base import Scheme
from ..solvers import anderson
from ..solvers.base import Solver
from ..solvers.fixed_point import FixedPoint
from ..solvers.newton import Auto
from ..systems.base import IsospectralSystem
from .compiled_plan import CompiledPlan
from .map_checks import _KEPT, MAPS, _system_maps

#: ``engine="auto"`` picks the compiled engine for matrix sizes ``n <= AUTO_MAX_N`` (real
#: data) or ``n <= AUTO_MAX_N_COMPLEX`` (complex data) ...
AUTO_MAX_N = 128
AUTO_MAX_N_COMPLEX = 96
#: ... and runs of at least this many trajectory-steps (``steps * K``): below it, importing
#: numba and loading the cached loops (~0.4 s) costs more than numpy's steps.
AUTO_MIN_WORK = 1000


def available() -> bool:
    """Whether numba can be found (without importing it)."""
    try:
        return importlib.util.find_spec("numba") is not None
    except (ImportError, ValueError):  # a broken or blocked installation
        return False


def kernels() -> ModuleType:
    """The compiled loops (imports numba; raises ``ImportError`` without it)."""
    loaded = sys.modules.get(f"{__package__}._compiled_loops")  # no import statement once loaded
    if loaded is None:
        from . import _compiled_loops

        loaded = _compiled_loops
    if loaded.numba is None:
        raise ImportError("No module named 'numba'")
    return loaded


_F = TypeVar("_F", bound=Callable[..., Any])


def compiled_map(func: _F) -> _F:
    """Decorator: ``func(W, params, out)`` as a system's compiled map — what
    :meth:`~lieflow.IsospectralSystem.compiled_B` and
    :meth:`~lieflow.IsospectralSystem.compiled_project` return with their ``params``.

    ``func`` writes its result into ``out``; ``W`` and ``out`` are C-contiguous ``(n, n)``
    arrays of the run's dtype (``float64``, or ``complex128`` on u(n) and su(N));
    ``params`` is a ``float64`` vector of the system's constants. It is compiled with numba
    and cached on disk like lieflow's own loops, for :func:`map_signature` of the dtype when
    :func:`plan` first asks for it (not at import). Decorate at module level, in a module
    that the system's hook imports (numba stays optional). Raises ``ImportError`` without
    numba.
    """
    decorated: _F = kernels().compiled_map(func)
    return decorated


def map_signature(dtype: Any) -> Any:
    """numba's signature of a compiled map for data of ``dtype`` (``float64`` or
    ``complex128``): ``(W, params, out)`` with ``W``, ``out`` C-contiguous 2-D arrays of
    ``dtype`` and ``params`` a 1-D ``float64`` array; returns nothing."""
    return kernels().map_signature(np.dtype(dtype))


def linked_function(symbol: str, function: Any, signature: Any) -> Any:
    """For a compiled map (:func:`compiled_map`) that calls another compiled function
    (``function``, a numba dispatcher, compiled here for ``signature``): an intrinsic
    ``f(like)`` giving that function as numba's first-class function, called through the
    linker's name ``symbol`` (unique to the function) rather than linked into the caller,
    which numba would optimize and generate a second time (a first run's compile time,
    issue 37 item 11). Call at import of the caller's module, before it compiles:
    ``sweeps = linked_function("pkg_sweeps_f8", sweeps_dispatcher, sig)``, then
    ``sweeps(x)(args...)`` in compiled code."""
    return kernels().linked_function(symbol, function, signature)


def __getattr__(name: str) -> Any:
    """lieflow's own compiled maps (:data:`MAPS`), loaded with the loops on first use."""
    if name in MAPS:
        return getattr(kernels(), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _fixed_point_of(
    solver: Solver, shape: tuple[int, ...], dtype: np.dtype
) -> tuple[FixedPoint, bool] | None:
    """The plain fixed-point iteration a solver runs first on one problem's unknowns of
    ``shape`` and ``dtype``, and whether a failed warm solve is retried cold by that same
    iteration (``None`` if not supported).

    A subclass of :class:`FixedPoint` (or :class:`Auto`) qualifies as long as it keeps the
    iteration: the same ``solve`` and map (:class:`~lieflow.solvers.FrozenB` changes the
    map, so it does not); with Anderson acceleration only where it never engages
    (:func:`lieflow.solvers.anderson.accelerates`: the plain iteration, bit for bit).
    """
    if isinstance(solver, Auto) and type(solver).solve is Auto.solve:
        fp = _fixed_point_of(solver.first, shape, dtype)
        return None if fp is None else (fp[0], False)
    if (
        isinstance(solver, FixedPoint)
        and type(solver).solve is FixedPoint.solve
        and type(solver)._map is FixedPoint._map
        and (
            solver.anderson == 0
            or not anderson.accelerates(np.broadcast_to(np.zeros((), dtype), shape))
        )
    ):
        return solver, True
    return None


def plan(
    system: IsospectralSystem, scheme: Scheme, solver: Solver, W0: Array
) -> CompiledPlan | str:
    """A :class:`CompiledPlan` for this case, or the reason it is not supported.

    Checks the system's compiled ``B`` (:meth:`~lieflow.IsospectralSystem.compiled_B`)
    against ``system.B(system.project_stage(W0))``, and its compiled projection against
    ``system.project(W0)``, to roundoff, so that a subclass overriding ``B`` without its
    compiled form cannot be integrated wrongly — once per system and dtype while the hooks
    return the same maps (:func:`_system_maps`). The last plan per system and dtype is kept
    by the engine (:data:`_KEPT`) and returned while it is for the same checked maps and the
    same values of everything else it holds.
    """
    dtype = np.dtype(W0.dtype)
    # by the dtype's character code: float64 "d", complex128 "D" (comparisons with dtype
    # objects build them on every call)
    if dtype.char == "D" and not system.algebra.skew:
        return "complex128 data are compiled on skew-Hermitian algebras only (u(n), su(N))"
    if dtype.char not in ("d", "D") or not dtype.isnative:
        return f"only float64 and complex128 data are compiled, got {dtype}"
    if system.underflow_guard:
        return (
            "the underflow guard (system.underflow_guard, lieflow.underflow) runs on the "
            "numpy engine only: set it to 0 for the compiled engine"
        )
    form = scheme.compiled_form()
    if form is None:
        return (
            f"scheme {scheme.name!r} is not compiled (only midpoint compositions, SyDIRK, "
            "and the reduced stage form of BlockGauss are)"
        )
    n = int(W0.shape[-1])
    stages = 1 if form[0] == "sydirk" else len(form[2])  # one problem: a (sub-)step's unknown
    fp = _fixed_point_of(solver, (stages, n, n), dtype)
    if fp is None:
        return (
            f"solver {getattr(solver, 'name', type(solver).__name__)!r} is not compiled "
            "(only FixedPoint, alone or first in Auto, without Anderson acceleration on "
            f"problems of {anderson.MIN_SIZE} numbers or more: use engine='numpy')"
        )
    try:
        loops = kernels()
    except ImportError as exc:
        return f"it needs numba: pip install 'lieflow[fast]' (importing it failed: {exc})"
    maps = _system_maps(system, W0, dtype, loops)
    if isinstance(maps, str):
        return maps
    (B, params), P = maps
    kind, A, b = form
    if kind not in ("sydirk", "reduced"):
        return f"scheme {scheme.name!r}: unknown compiled form {kind!r}"
    # the last plan made for this system and dtype, while it is for the same checked maps
    # and the same values of everything else it holds (a scheme or solver built anew for
    # each call, e.g. by lf.schemes.get, still finds it)
    fixed, retry_cold = fp
    r = fixed.rule
    conjugation = getattr(scheme, "update", "commutator") == "conjugation"
    same = (n, kind, A.tobytes(), b.tobytes(), A.shape, conjugation, fixed.name, retry_cold, r)
    values = _KEPT.of(system)
    key = ("compiled plan", dtype)
    kept = values.get(key)
    if kept is not None and kept[1] is maps and kept[0] == same:
        made: CompiledPlan = kept[2]
        return made
    made = CompiledPlan(
        kind=kind,
        n=n,
        dtype=dtype,
        skew=bool(system.algebra.skew),
        A=A,
        b=b,
        B=B,
        B_params=params,
        project=None if P is None else P[0],
        project_params=np.zeros(0) if P is None else P[1],
        rule=r,
        retry_cold=retry_cold,
        solver_name=fixed.name,
        conjugation=conjugation,
        loops=loops,
    )
    values[key] = (same, maps, made)
    return made


def wins(n: int, steps: int, trajectories: int = 1, complex_data: bool = False) -> bool:
    """Whether ``engine="auto"`` should pick the compiled engine for ``steps`` steps of
    ``trajectories`` trajectories of ``n x n`` matrices: ``n <= AUTO_MAX_N`` (complex data:
    ``AUTO_MAX_N_COMPLEX``) and ``steps * trajectories >= AUTO_MIN_WORK``.

    A function of the run alone — not of what the process ran before — so that the same
    run gives the same bits wherever it runs (resume in another process, a sweep worker).
    For a short run in a process that has the loops loaded already, pass
    ``engine="compiled"``.

    Measured on the rigid body (n = 3) and the generalized rigid body (fixed point at rtol
    1e-14, h = 0.01, one BLAS thread, an idle machine), numpy time / compiled time per step
    for midpoint, Gauss-3, 7-stage SyDIRK: n = 3: 78, 50, 127; n = 10: 27, 9.0, 22;
    n = 20: 8.1, 3.3, 6.1; n = 64: 2.5, 1.4, 1.9; n = 128: 1.3, 1.2, 1.4; n = 256 and 400:
    1.1. Above n = 8 the compiled loops call BLAS for their products, so the gain at large n
    is numpy's per-call overhead and temporaries; it fades from n ~ 128 on, hence the cut
    there. Ensembles gain less (numpy batches their products): 2.3 for K = 10,000 at
    n = 3 (midpoint, h = 0.1).

    Complex data (Euler–Zeitlin, rms-1 vorticity, h = 1/N, rtol 1e-14), the same ratios for
    midpoint, Gauss-2, Gauss-4 with the Casimir shift: N = 32: 2.6, 2.0, 1.5; N = 64: 1.9,
    1.4, 1.5; N = 96: 1.4, 1.2, 1.2; N = 128: 1.3, 1.1, 0.95 (a complex product costs four
    real ones, so the overhead numpy adds fades sooner), hence the cut at 96.
    """
    top = AUTO_MAX_N_COMPLEX if complex_data else AUTO_MAX_N
    return n <= top and steps * trajectories >= AUTO_MIN_WORK
