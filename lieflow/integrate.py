"""The one entry point that runs many steps: :func:`integrate`, and the step stream
:func:`iterate` it is built on (the command line's HDF5 runner consumes the same stream)."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator
from typing import Any, Literal

import attrs
import numpy as np
from numpy.typing import ArrayLike

from .algebras import Array
from .errors import ConvergenceError, InputError
from .progress import ProgressBar
from .schemes.base import Scheme, StepResult
from .solution import Solution, Status
from .solvers.base import Solver, batch_norm
from .solvers.fixed_point import FixedPoint
from .systems.base import IsospectralSystem


@attrs.frozen
class WarmStart:
    """Initial guesses from the previous steps' solutions (SPEC §5), as explicit state.

    The unknowns of consecutive steps, as offsets ``delta_k`` from their ``h = 0`` values,
    vary smoothly in time, so the next is predicted by linear extrapolation
    ``2 delta_k - delta_{k-1}`` (error ``O(h^3)`` against ``O(h)`` for the cold guess
    ``delta = 0``). The prediction is used only while it is *trusted*: after each step the
    prediction that was (or would have been) made is compared with the solution found, and
    it is trusted for the next step if it was closer than the cold guess. At large ``h``
    (where a step changes ``W`` a lot) this falls back to cold starts by itself.
    """

    last: Array | None = attrs.field(default=None, repr=False)
    previous: Array | None = attrs.field(default=None, repr=False)
    trusted: bool = True

    def prediction(self) -> Array | None:
        """The extrapolated offsets (``None`` before the first step)."""
        if self.last is None:
            return None
        return self.last if self.previous is None else 2.0 * self.last - self.previous

    def guess(self) -> Array | None:
        """The initial guess to use: the prediction if trusted, else ``None`` (cold)."""
        return self.prediction() if self.trusted else None

    def advance(self, solved: Array) -> WarmStart:
        """The state after a step whose solved offsets are ``solved``."""
        predicted = self.prediction()
        trusted = predicted is None or bool(
            batch_norm(solved - predicted, solved.ndim) < batch_norm(solved, solved.ndim)
        )
        return WarmStart(solved, self.last, trusted)


@attrs.frozen
class Step:
    """One completed step of :func:`iterate`: step ``index`` took ``t - h`` to ``t``.

    ``warm`` is the warm-start state after the step; with ``W``, ``index`` it is all a
    checkpoint needs to resume bit-for-bit (:func:`iterate` with ``start`` and ``warm``).
    """

    index: int
    t: float
    result: StepResult
    warm: WarmStart

    @property
    def W(self) -> Array:
        """The new state."""
        return self.result.W


def check_step_size(h: float) -> float:
    """Return ``h`` as a float, or raise :class:`InputError` unless it is positive and finite."""
    try:
        hf = float(h)
    except (TypeError, ValueError):
        raise InputError(f"step size h must be a real number, got {h!r}") from None
    if not math.isfinite(hf) or hf <= 0:
        raise InputError(f"step size h must be positive and finite, got {h!r}")
    return hf


def _check_types(system: object, scheme: object, solver: object) -> None:
    if not isinstance(system, IsospectralSystem):
        raise InputError(
            f"system must be an IsospectralSystem, got {type(system).__name__}; "
            "use lieflow.systems.get(name, ...) or subclass IsospectralSystem"
        )
    if not isinstance(scheme, Scheme):
        raise InputError(
            f"scheme must be a Scheme, got {type(scheme).__name__}; use lieflow.schemes.get(name)"
        )
    if not isinstance(solver, Solver):
        raise InputError(
            f"solver must implement the Solver protocol (name, solve), got {type(solver).__name__}"
        )


def iterate(
    system: IsospectralSystem,
    scheme: Scheme,
    W0: Array,
    h: float,
    solver: Solver,
    *,
    start: int = 0,
    warm: WarmStart | None = None,
    warm_start: bool = True,
) -> Iterator[Step]:
    """Yield steps ``start + 1, start + 2, ...`` from the (already validated) state ``W0``.

    ``t`` is computed as ``index * h`` (never accumulated). ``warm`` seeds the first step's
    initial guess (pass the last :attr:`Step.warm` to resume a run bit-for-bit). A failed
    step raises :class:`ConvergenceError` carrying its index and time; a step whose result is
    not finite raises it too (reason ``"non_finite"``).
    """
    W, k = W0, start
    warm = WarmStart() if warm is None else warm
    while True:
        try:
            res = scheme.step(system, W, h, solver, warm.guess() if warm_start else None)
        except ConvergenceError as exc:
            raise exc.at(k + 1, k * h) from exc
        if not np.all(np.isfinite(res.W)):
            raise ConvergenceError(
                "non_finite",
                solver=res.solver,
                iterations=res.iterations,
                residuals=(res.residual,),
                step=k + 1,
                t=k * h,
            )
        k += 1
        W, warm = res.W, warm.advance(res.warm)
        yield Step(k, k * h, res, warm)


def _resolve_steps(h: float, steps: int | None, t_final: float | None) -> int:
    if (steps is None) == (t_final is None):
        raise InputError("give exactly one of steps=N or t_final=T")
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 1:
            raise InputError(f"steps must be a positive integer, got {steps!r}")
        return int(steps)
    assert t_final is not None
    if not (math.isfinite(t_final) and t_final > 0):
        raise InputError(f"t_final must be positive and finite, got {t_final!r}")
    n = round(t_final / h)
    if n < 1 or abs(n * h - t_final) > 1e-9 * t_final:
        raise InputError(
            f"t_final = {t_final} is not a whole number of steps of h = {h}; "
            "choose h = t_final / N or pass steps=N"
        )
    return n


Engine = Literal["auto", "numpy", "compiled"]

#: At most this many steps per call of the compiled engine (a progress-bar tick each).
_CHUNK_STEPS = 1024
#: ... and at most this many float64 entries of saved states per call (8 MiB).
_CHUNK_ENTRIES = 1 << 20


@attrs.frozen
class _Chunk:
    """Consecutive completed steps ``start + 1 .. start + len(W)`` for :func:`integrate`."""

    start: int
    W: Array = attrs.field(repr=False)  # (m, *batch, n, n)
    iterations: Array = attrs.field(repr=False)  # (m,)
    solvers: tuple[str, ...]

    @classmethod
    def of(cls, step: Step) -> _Chunk:
        res = step.result
        return cls(step.index - 1, res.W[None], np.array([res.iterations]), (res.solver,))


def _numpy_chunks(
    system: IsospectralSystem, scheme: Scheme, W0: Array, h: float, solver: Solver,
    warm_start: bool, n_steps: int,
) -> Iterator[_Chunk]:  # fmt: skip
    for step in iterate(system, scheme, W0, h, solver, warm_start=warm_start):
        yield _Chunk.of(step)
        if step.index == n_steps:
            return


def _compiled_chunks(
    compiled: Any, system: IsospectralSystem, scheme: Scheme, W0: Array, h: float,
    solver: Solver, warm_start: bool, n_steps: int,
) -> Iterator[_Chunk]:  # fmt: skip
    """Chunks from the compiled engine (:mod:`lieflow.compiled`); a step it does not accept
    is taken by :func:`iterate` from the last good state and warm state (so errors and
    ``Auto``'s fallbacks are exactly the numpy path's), and the compiled engine resumes."""
    per_step = max(1, W0.size)
    size = max(1, min(_CHUNK_STEPS, _CHUNK_ENTRIES // per_step))
    W, k, warm = W0, 0, WarmStart()
    while k < n_steps:
        m = min(size, n_steps - k)
        chunk = compiled.advance(
            W, h, m, warm.last, warm.previous, warm.trusted, warm_start=warm_start
        )
        if chunk.done:
            yield _Chunk(k, chunk.states, chunk.iterations, (compiled.solver_name,) * chunk.done)
            W, k = chunk.states[-1], k + chunk.done
            warm = WarmStart(chunk.last, chunk.previous, chunk.trusted)
        if not chunk.complete:
            step = next(iterate(system, scheme, W, h, solver, start=k, warm=warm,
                                warm_start=warm_start))  # fmt: skip
            yield _Chunk.of(step)
            W, k, warm = step.W, step.index, step.warm


def _per_state(f: Callable[[Array], Array], W: Array) -> Array:
    """``f`` of each state in ``W`` (``(m, *batch, n, n)``), stacked: one vectorised call,
    or for a single state a call on that state (as before chunks existed)."""
    if W.shape[0] == 1:
        return np.asarray(f(W[0]))[None]
    return np.asarray(f(W))


def _select_engine(
    engine: str,
    system: IsospectralSystem,
    scheme: Scheme,
    solver: Solver,
    W0: Array,
    n_steps: int,
) -> Any:
    """The :class:`lieflow.compiled.CompiledPlan` to run, or ``None`` for numpy."""
    if engine == "numpy":
        return None
    if engine not in ("auto", "compiled"):
        raise InputError(f"engine must be 'auto', 'numpy' or 'compiled', got {engine!r}")
    from . import compiled

    if engine == "auto" and not compiled.available():
        return None
    plan = compiled.plan(system, scheme, solver, W0)
    if isinstance(plan, str):
        if engine == "compiled":
            raise InputError(f"engine='compiled' cannot run this case: {plan}; use engine='auto'")
        return None
    if engine == "auto" and not compiled.wins(plan, n_steps, W0.size // plan.n**2):
        return None
    try:
        compiled.kernels()
    except ImportError as exc:
        if engine == "compiled":
            raise InputError(
                "engine='compiled' needs numba: pip install 'lieflow[fast]' "
                f"(importing it failed: {exc})"
            ) from exc
        return None
    return plan


def integrate(
    system: IsospectralSystem,
    scheme: Scheme,
    W0: ArrayLike,
    h: float,
    *,
    steps: int | None = None,
    t_final: float | None = None,
    solver: Solver | None = None,
    save_every: int = 1,
    diagnostics: bool = True,
    warm_start: bool = True,
    on_failure: Literal["raise", "truncate"] = "raise",
    progress: bool = False,
    engine: Engine = "auto",
) -> Solution:
    """Integrate ``dW/dt = [B(W), W]`` from ``W0`` with a fixed step ``h``.

    Parameters
    ----------
    system, scheme : IsospectralSystem, Scheme
        What to integrate and how (``lieflow.systems.get``, ``lieflow.schemes.get``).
    W0 : array_like
        Initial condition in the system's algebra, shape ``(n, n)``; a stack of shape
        ``(..., n, n)`` is an ensemble advanced together.
    h : float
        Step size, positive.
    steps, t_final : int or float
        Number of steps, or final time (a whole number of steps).
    solver : Solver, optional
        Nonlinear solver; ``FixedPoint()`` (rtol 1e-14) by default.
    save_every : int
        Keep every ``save_every``-th state (the first and last are always kept).
    diagnostics : bool
        Record the relative energy error and Casimir drift at every step.
    warm_start : bool
        Start each solve from the previous step's solution (SPEC §5).
    on_failure : {"raise", "truncate"}
        On a failed step raise :class:`ConvergenceError` (default) or return the steps done,
        with ``status = FAILED`` and the error in ``failure``.
    progress : bool
        Show a progress bar (needs ``rich``).
    engine : {"auto", "numpy", "compiled"}
        How the steps are computed. ``"numpy"``: one vectorised numpy step at a time (any
        system, scheme, solver, dtype). ``"compiled"``: loops compiled with numba
        (``pip install 'lieflow[fast]'``) that advance many steps per call, for systems
        with ``B(W) = S ⊙ W`` (rigid bodies, periodic Toda), SyDIRK or reduced-form
        BlockGauss schemes, real data, and ``FixedPoint`` (or ``Auto``) solvers; same
        iterations and stopping rule, results equal to roundoff, and a step it cannot
        finish is handed to the numpy path (see :mod:`lieflow.compiled`); raises
        :class:`InputError` if numba is missing or the case is not supported. ``"auto"``
        (default): compiled where supported, numba is installed, and it is faster
        (``n <= 128`` and at least 1000 trajectory-steps, see
        :func:`lieflow.compiled.wins`), else numpy.
    """
    solver = FixedPoint() if solver is None else solver
    _check_types(system, scheme, solver)
    h = check_step_size(h)
    n_steps = _resolve_steps(h, steps, t_final)
    if (
        isinstance(save_every, bool)
        or not isinstance(save_every, (int, np.integer))
        or save_every < 1
    ):
        raise InputError(f"save_every must be a positive integer, got {save_every!r}")
    if on_failure not in ("raise", "truncate"):
        raise InputError(f"on_failure must be 'raise' or 'truncate', got {on_failure!r}")
    W0a = system.validate(W0)
    compiled = _select_engine(engine, system, scheme, solver, W0a, n_steps)

    saved_t, saved_W, saved_k = [np.zeros(1)], [W0a[None]], [np.zeros(1, dtype=np.int64)]
    iterations = np.zeros(n_steps, dtype=np.int64)
    solvers: list[str] = []
    H, C = [], []
    if diagnostics:
        H.append(_per_state(system.hamiltonian, W0a[None]))
        C.append(_per_state(system.casimirs, W0a[None]))
    failure: ConvergenceError | None = None
    bar = ProgressBar(n_steps) if progress else None
    done, last_W = 0, W0a
    if compiled is None:
        chunks = _numpy_chunks(system, scheme, W0a, h, solver, warm_start, n_steps)
    else:
        chunks = _compiled_chunks(compiled, system, scheme, W0a, h, solver, warm_start, n_steps)
    start = time.perf_counter()
    try:
        for chunk in chunks:
            m = chunk.iterations.shape[0]
            index = np.arange(chunk.start + 1, chunk.start + m + 1)
            iterations[chunk.start : chunk.start + m] = chunk.iterations
            solvers.extend(chunk.solvers)
            if diagnostics:
                H.append(_per_state(system.hamiltonian, chunk.W))
                C.append(_per_state(system.casimirs, chunk.W))
            keep = (index % save_every == 0) | (index == n_steps)
            if keep.any():
                saved_t.append(index[keep] * h)
                saved_W.append(chunk.W[keep])
                saved_k.append(index[keep])
            done, last_W = chunk.start + m, chunk.W[-1]
            if bar is not None:
                bar.advance(m, int(chunk.iterations.sum()))
    except ConvergenceError as exc:
        if on_failure == "raise":
            raise
        failure = exc
        if done and saved_k[-1][-1] != done:
            saved_t.append(np.array([done * h]))
            saved_W.append(last_W[None])
            saved_k.append(np.array([done]))
    finally:
        if bar is not None:
            bar.close()
    wall = time.perf_counter() - start

    energy_error = casimir_drift = None
    if diagnostics:
        Ha = np.concatenate(H).astype(float, copy=False)
        energy_error = np.abs(Ha - Ha[0]) / np.maximum(np.abs(Ha[0]), np.finfo(float).tiny)
        Ca = np.concatenate(C)
        casimir_drift = np.abs(Ca - Ca[0]) / system.casimir_scale(W0a)
    return Solution(
        system=system,
        scheme=scheme.name,
        h=h,
        t=np.concatenate(saved_t),
        W=np.concatenate(saved_W),
        saved_steps=np.concatenate(saved_k),
        iterations=iterations[:done],
        solvers=tuple(solvers),
        energy_error=energy_error,
        casimir_drift=casimir_drift,
        status=Status.SUCCESS if failure is None else Status.FAILED,
        failure=failure,
        wall_time=wall,
    )
