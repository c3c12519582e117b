r"""The compiled engine of :func:`lieflow.integrate`: many steps per call for small systems.

For tiny matrices (the so(3) rigid body, ensembles of them) a step costs a few hundred
floating-point operations and numpy's per-call overhead (microseconds per product, norm and
array) dominates by two orders of magnitude. This engine runs the same fixed-point
iterations in loops compiled with numba (``pip install 'lieflow[fast]'``), advancing a chunk
of steps per call, for the case where that is simple and exact:

* the system's ``B`` is an entrywise product with a constant matrix,
  :math:`B(W) = S \odot W` (:attr:`IsospectralSystem.hadamard_factor`: rigid bodies and the
  periodic Toda lattice, SPEC §3), so ``B`` is evaluated inside the loops;
* the scheme is a composition of midpoint steps (:class:`~lieflow.schemes.SyDIRK`, minimal
  variable form, SPEC §4.1–4.2) or the reduced stage form of a symplectic tableau
  (:class:`~lieflow.schemes.BlockGauss` with ``form="reduced"``, SPEC §4.5);
* the solver is plain :class:`~lieflow.solvers.FixedPoint` iteration (no Anderson), or
  :class:`~lieflow.solvers.Auto` whose first solver is one (SPEC §5);
* the data are real ``float64``.

Same maps, same stopping rule (``rtol``, ``atol``, ``max_iter``, stagnation, divergence),
same warm starts (:class:`~lieflow.flows.WarmStart`) as the numpy path. A step the
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
from types import ModuleType
from typing import Literal

import attrs
import numpy as np

from . import driver
from .algebras import Array
from .flows import SchemeFlow, WarmStart
from .schemes.base import Scheme
from .schemes.block import BlockGauss
from .schemes.sydirk import SyDIRK
from .solvers.base import Solver
from .solvers.fixed_point import FixedPoint
from .solvers.newton import Auto
from .systems.base import IsospectralSystem

#: ``engine="auto"`` picks the compiled engine for matrix sizes ``n <= AUTO_MAX_N`` ...
AUTO_MAX_N = 128
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
    from . import _kernels

    if _kernels.numba is None:
        raise ImportError("No module named 'numba'")
    return _kernels


@attrs.frozen
class Chunk:
    """What one call of :meth:`CompiledPlan.advance` computed.

    Attributes
    ----------
    states : ndarray
        The states after each completed step, ``(done, *batch, n, n)``.
    iterations : ndarray
        Fixed-point updates per completed step (max over an ensemble), ``(done,)``.
    last, previous : ndarray or None
        Warm-start offsets after the last completed step (:class:`WarmStart` fields).
    trusted : bool
        Whether the warm-start prediction is trusted for the next step.
    complete : bool
        Whether all requested steps completed; if not, the next step was not accepted and
        must be handed to the numpy path.
    """

    states: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    last: Array | None = attrs.field(repr=False)
    previous: Array | None = attrs.field(repr=False)
    trusted: bool
    complete: bool

    @property
    def done(self) -> int:
        """Completed steps."""
        return int(self.iterations.shape[0])


@attrs.frozen(eq=False)
class CompiledPlan:
    """A supported case (see the module docstring), ready to advance.

    Build it with :func:`plan`. ``kind`` selects the loop; ``b`` (and ``A`` for the reduced
    form) are the tableau's coefficients; ``rule = (rtol, atol, roundoff_floor,
    divergence_factor)`` and ``irule = (max_iter, patience, window, project, retry_cold)``
    are the fixed-point stopping rule (:class:`~lieflow.solvers.StoppingRule`); ``retry_cold``
    repeats a failed warm-started solve from the cold guess, as
    :func:`lieflow.schemes.base.solve` does (not under ``Auto``, which hands a failed solve to
    Newton first).
    """

    kind: Literal["sydirk", "reduced"]
    S: Array = attrs.field(repr=False)
    skew: bool
    A: Array = attrs.field(repr=False)
    b: Array = attrs.field(repr=False)
    rule: Array = attrs.field(repr=False)
    irule: Array = attrs.field(repr=False)
    solver_name: str

    @property
    def n(self) -> int:
        """Matrix size."""
        return int(self.S.shape[0])

    def warm_shape(self) -> tuple[int, ...]:
        """Core shape of the warm-start offsets of one trajectory."""
        s, n = self.b.size, self.n
        return (s, n, n) if self.kind == "sydirk" else (2, s, n, n)

    def advance(
        self,
        W: Array,
        h: float,
        steps: int,
        last: Array | None = None,
        previous: Array | None = None,
        trusted: bool = True,
        warm_start: bool = True,
    ) -> Chunk:
        """Advance ``W`` (``(*batch, n, n)``) by up to ``steps`` steps of size ``h`` from the
        warm-start state ``(last, previous, trusted)`` (:class:`~lieflow.WarmStart`)."""
        k = kernels()
        batch, n = W.shape[:-2], self.n
        K = int(np.prod(batch, dtype=np.int64))
        core = self.warm_shape()
        Wk = np.ascontiguousarray(W, dtype=np.float64).reshape(K, n, n)

        size = int(np.prod(core))

        def unpack(a: Array | None) -> Array:
            if a is None:
                return np.zeros((K, size))
            return np.array(a, dtype=np.float64, order="C").reshape(K, size)

        lastk, prevk = unpack(last), unpack(previous)
        flags = np.array([last is not None, previous is not None, trusted], dtype=np.int64)
        irule = np.append(self.irule, np.int64(warm_start))
        states = np.empty((steps, K, n, n))
        iters = np.zeros(steps, dtype=np.int64)
        if self.kind == "sydirk":
            done = k.sydirk_advance(
                Wk, self.S, self.b, h, self.skew, self.rule, irule, lastk, prevk, flags,
                states, iters,
            )  # fmt: skip
        else:
            done = k.reduced_advance(
                Wk, self.S, h * self.A, h * self.b, self.skew, self.rule, irule, lastk, prevk,
                flags, states, iters,
            )  # fmt: skip
        shape = (*batch, *core)
        return Chunk(
            states[:done].reshape(done, *batch, n, n),
            iters[:done],
            lastk.reshape(shape) if flags[0] else None,
            prevk.reshape(shape) if flags[1] else None,
            bool(flags[2]),
            done == steps,
        )


@attrs.frozen(eq=False)
class CompiledSchemeFlow(SchemeFlow):
    """A :class:`~lieflow.flows.SchemeFlow` whose steps the compiled loops take, a chunk per
    call (:meth:`step_many`, used by :func:`lieflow.driver.advance`); :meth:`step` (the
    numpy path) takes any step they do not accept. Build it with
    :func:`lieflow.integrate.scheme_flow`.

    The states of a chunk are mapped onto the phase space afterwards
    (:meth:`~lieflow.IsospectralSystem.project`) and the next chunk starts from the last
    projected state; iterations and warm starts are the numpy path's. The per-step
    residual is not recorded by the compiled loops (``nan``).
    """

    plan: CompiledPlan = attrs.field(kw_only=True)

    def step_many(
        self, W: Array, start: int, h: float, steps: int, state: WarmStart | None
    ) -> driver.Chunk:
        """Up to ``steps`` steps after step ``start`` (fewer if one is not accepted)."""
        warm = WarmStart() if state is None else state
        c = self.plan.advance(
            W, h, steps, warm.last, warm.previous, warm.trusted, warm_start=self.warm_start
        )
        new = WarmStart(c.last, c.previous, c.trusted) if state is not None else None
        return driver.Chunk(
            start,
            h,
            self.system.project(c.states) if c.done else c.states,
            c.iterations,
            np.full(c.done, np.nan),
            (self.plan.solver_name,) * c.done,
            new,
        )


def _fixed_point_of(solver: Solver) -> tuple[FixedPoint, bool] | None:
    """The plain fixed-point iteration a solver runs first, and whether a failed warm
    solve is retried cold by that same iteration (``None`` if not supported)."""
    if type(solver) is Auto:
        first = solver.first
        if type(first) is FixedPoint and first.anderson == 0:
            return first, False
        return None
    if type(solver) is FixedPoint and solver.anderson == 0:
        return solver, True
    return None


def plan(
    system: IsospectralSystem, scheme: Scheme, solver: Solver, W0: Array
) -> CompiledPlan | str:
    """A :class:`CompiledPlan` for this case, or the reason it is not supported.

    Checks the system's :attr:`~IsospectralSystem.hadamard_factor` against ``system.B(W0)``
    (bit for bit) so that a subclass overriding ``B`` cannot be integrated wrongly.
    """
    S = system.hadamard_factor
    if S is None:
        return f"{system.name} does not expose B(W) = S ⊙ W (hadamard_factor is None)"
    if W0.dtype != np.float64:
        return f"only real float64 data are compiled, got {W0.dtype}"
    S = np.ascontiguousarray(S, dtype=np.float64)
    if S.shape != W0.shape[-2:] or not np.array_equal(system.B(W0), S * W0):
        return f"{system.name}.hadamard_factor does not reproduce {system.name}.B"
    if type(scheme) is SyDIRK:
        kind: Literal["sydirk", "reduced"] = "sydirk"
    elif type(scheme) is BlockGauss and scheme.form == "reduced":
        kind = "reduced"
    else:
        return (
            f"scheme {scheme.name!r} is not compiled (only midpoint compositions, SyDIRK, "
            "and the reduced stage form of BlockGauss are)"
        )
    fp = _fixed_point_of(solver)
    if fp is None:
        return (
            f"solver {getattr(solver, 'name', type(solver).__name__)!r} is not compiled "
            "(only FixedPoint without Anderson acceleration, alone or first in Auto)"
        )
    fixed, retry_cold = fp
    r = fixed.rule
    return CompiledPlan(
        kind=kind,
        S=S,
        skew=bool(system.algebra.skew),
        A=np.ascontiguousarray(scheme.tableau.A, dtype=np.float64),
        b=np.ascontiguousarray(scheme.tableau.b, dtype=np.float64),
        rule=np.array([r.rtol, r.atol, r.roundoff_floor, r.divergence_factor], dtype=float),
        irule=np.array([r.max_iter, r.patience, r.window, r.project, retry_cold], dtype=np.int64),
        solver_name=fixed.name,
    )


def wins(compiled: CompiledPlan, steps: int, trajectories: int = 1) -> bool:
    """Whether ``engine="auto"`` should pick the compiled engine for ``steps`` steps of
    ``trajectories`` trajectories: ``n <= AUTO_MAX_N`` and
    ``steps * trajectories >= AUTO_MIN_WORK``.

    Measured on the generalized rigid body (fixed point at rtol 1e-14, h = 0.01), numpy
    time / compiled time per step for midpoint, Gauss-3, 7-stage SyDIRK: n = 10: 42, 18,
    107; n = 20: 16, 5.8, 25; n = 50: 4.9, 2.2, 5.4; n = 64: 3.1, 1.9, 4.5; n = 96: 2.2,
    1.6, 2.6; n = 128: 2.5, 1.0, 1.7; n = 256: 1.4, 1.2, 1.2. Above n = 8 the compiled loops
    call BLAS for their products, so the gain at large n is numpy's per-call overhead and
    temporaries; it fades from n ~ 128 on, hence the cut there. Ensembles gain less (numpy
    batches their products): 1.2-1.7 for n = 10-64, 2-5 at n = 3.
    """
    return compiled.n <= AUTO_MAX_N and steps * trajectories >= AUTO_MIN_WORK
