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

import functools
import importlib.util
import math
import sys
import weakref
from collections.abc import Callable, Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any, NamedTuple, TypeVar

import attrs
import numpy as np

from .. import chunks
from ..algebras import Array
from ..flows import SchemeFlow, StepStats
from ..schemes.base import Scheme
from ..schemes.block import reduced_coefficients
from ..schemes.sydirk import midpoint_coefficients
from ..solvers import anderson
from ..solvers.base import Solver
from ..solvers.fixed_point import FixedPoint, StoppingRule
from ..solvers.newton import Auto
from ..systems.base import IsospectralSystem
from ..warm_start import DEFAULT_DEPTH, WarmStart, extrapolation_matrix

if TYPE_CHECKING:
    from ._compiled_loops import LoopArguments

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


# ------------------------------------------------------------ a system's compiled maps

#: lieflow's own compiled maps ``f(W, params, out)``, attributes of this module (loaded,
#: with numba, on first use) for a system's :meth:`~lieflow.IsospectralSystem.compiled_B`
#: and :meth:`~lieflow.IsospectralSystem.compiled_project` to return, or for its own
#: compiled map to call: ``hadamard_B`` (``out = S ⊙ W``, ``params = S.ravel()``),
#: ``hadamard_B_skew`` (``S ⊙ (W - W^T)/2``), ``hadamard_B_symmetric``
#: (``S ⊙ (W + W^T)/2``), ``symmetric_part`` (``(W + W^T)/2``) and ``skew_hermitian_part``
#: (``(W - W^†)/2``, minus its trace over ``n`` on the diagonal if ``params[0]``: the
#: projection onto u(n) or su(N)). The engine evaluates the Hadamard maps inline.
MAPS = (
    "hadamard_B",
    "hadamard_B_skew",
    "hadamard_B_symmetric",
    "symmetric_part",
    "skew_hermitian_part",
)

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


@attrs.frozen
class CompiledSteps:
    """The steps one call of :meth:`CompiledPlan.advance` took in the compiled loops (the
    flow turns them into a :class:`lieflow.chunks.Chunk`).

    Attributes
    ----------
    states : ndarray
        The states after each completed step, ``(done, *batch, n, n)``.
    iterations : ndarray
        Fixed-point updates per completed step (max over an ensemble), ``(done,)``.
    history : tuple of ndarray
        The warm-start offsets of the last completed steps, most recent first
        (:meth:`WarmStart.history <lieflow.warm_start.WarmStart.history>`).
    trusted : int
        How many of them the next step's prediction extrapolates from.
    complete : bool
        Whether all requested steps completed; if not, the next step was not accepted and
        must be handed to the numpy path.
    """

    states: Array = attrs.field(repr=False)
    iterations: Array = attrs.field(repr=False)
    history: tuple[Array, ...] = attrs.field(repr=False)
    trusted: int
    complete: bool

    @property
    def done(self) -> int:
        """Completed steps."""
        return int(self.iterations.shape[0])


def _read_only(values: Any) -> Array:
    """A C-contiguous read-only float64 copy of ``values``: what a plan shows of its
    coefficients and ``params`` (the loops get copies of their own, :class:`_Fixed`)."""
    out = np.array(values, dtype=np.float64, order="C")
    out.setflags(write=False)
    return out


class _Fixed(NamedTuple):
    """What :meth:`CompiledPlan.loop_call` passes the loops unchanged from call to call for
    one warm-start depth (made once per plan and depth): the loops' module and entry point,
    their arguments of that kind (:class:`lieflow.engines._compiled_loops.LoopArguments`: writable
    copies
    of the plan's values, which nothing outside the plan sees), the warm offsets' core
    shape and size, and ``max_iter``."""

    kernels: ModuleType
    run: Any
    B: int
    B_params: Array
    project: int
    project_params: Array
    tolerances: Array
    settings: Array
    extrapolation: Array
    gemm: int
    core: tuple[int, ...]
    size: int
    max_iter: int


@attrs.frozen(eq=False)
class CompiledPlan:
    """A supported case (see the module docstring), ready to advance.

    Build it with :func:`plan`. ``kind`` selects the formulation (``Scheme.compiled_form``);
    ``A``, ``b`` are the tableau's coefficients; ``B``/``B_params`` the system's compiled
    ``B`` (:meth:`~lieflow.IsospectralSystem.compiled_B`) and ``project``/``project_params``
    its compiled projection onto the phase space (``None``: each chunk is projected by
    ``system.project`` afterwards); ``rule`` is the fixed-point stopping rule
    (:class:`~lieflow.solvers.StoppingRule`); ``retry_cold``: a failed warm-started solve is
    retried from the cold guess inside the loops (:func:`lieflow.schemes.base.retries_cold`;
    not under ``Auto``, which hands a failed solve to Newton first: the step is handed to
    the numpy path). ``conjugation``: the scheme's ``update`` is ``"conjugation"`` (SPEC
    §4.7). The arrays are read-only: a plan is kept by the engine (:func:`plan`) and serves
    every call of its case.
    """

    kind: str
    n: int
    dtype: np.dtype
    skew: bool
    A: Array = attrs.field(repr=False, converter=_read_only)
    b: Array = attrs.field(repr=False, converter=_read_only)
    B: Any = attrs.field(repr=False)
    B_params: Array = attrs.field(repr=False, converter=_read_only)
    project: Any = attrs.field(repr=False)
    project_params: Array = attrs.field(repr=False, converter=_read_only)
    rule: StoppingRule
    retry_cold: bool
    solver_name: str
    conjugation: bool = attrs.field(default=False, kw_only=True)
    #: The loops' unchanging arguments per warm-start depth (:class:`_Fixed`, made on first
    #: use and kept with the plan).
    _fixed: dict[int, _Fixed] = attrs.field(init=False, factory=dict, eq=False, repr=False)
    #: The last flow built on this plan (:meth:`flow`) and the step size of the last call
    #: with its coefficients ``(h, coefficients, weights)`` (:meth:`loop_call`): values, kept.
    _kept: dict[str, Any] = attrs.field(init=False, factory=dict, eq=False, repr=False)

    def flow(
        self, system: IsospectralSystem, scheme: Scheme, solver: Solver, warm_start: bool | int
    ) -> CompiledSchemeFlow:
        """The :class:`CompiledSchemeFlow` of this plan for these (the plan's own case, as
        :func:`plan` returned it for them): the one built last when they are the same
        objects (a flow is an immutable value; ~1 µs a call saved), else a new one."""
        last = self._kept.get("flow")
        if (
            last is not None
            and last.system is system
            and last.scheme is scheme
            and last.solver is solver
            and type(last.warm_start) is type(warm_start)
            and last.warm_start == warm_start
        ):
            kept: CompiledSchemeFlow = last
            return kept
        made = CompiledSchemeFlow(system, scheme, solver, warm_start, plan=self)
        self._kept["flow"] = made
        return made

    def warm_shape(self) -> tuple[int, ...]:
        """Core shape of the warm-start offsets of one trajectory."""
        s, n = self.b.size, self.n
        return (s, n, n) if self.kind == "sydirk" else (2, s, n, n)

    def coefficients(self, h: float) -> tuple[Array, Array]:
        """The loops' stage ``coefficients`` and ``weights`` (``h b``) for step size ``h``
        (:class:`~lieflow.engines._compiled_loops.LoopArguments`), by the derivations the numpy
        path uses:
        rows ``(q, q^2)`` of :func:`~lieflow.schemes.sydirk.midpoint_coefficients` of each
        sub-step, or ``(C_G; C_P)`` of :func:`~lieflow.schemes.block.reduced_coefficients`.
        Those of the last step size are kept."""
        kept = self._kept.get("h")
        if kept is not None and kept[0] == h:
            return kept[1], kept[2]
        weights = h * self.b
        if self.kind == "sydirk":
            coefficients = np.array([midpoint_coefficients(w) for w in weights.tolist()])
        else:
            coefficients = np.concatenate(reduced_coefficients(h, self.A, self.skew))
        self._kept["h"] = (h, coefficients, weights)
        return coefficients, weights

    def advance(
        self,
        W: Array,
        h: float,
        steps: int,
        history: Sequence[Array] = (),
        depth: int = DEFAULT_DEPTH,
        trusted: int = 1,
    ) -> CompiledSteps:
        """Advance ``W`` (``(*batch, n, n)``) by up to ``steps`` steps of size ``h`` from the
        warm-start state: the kept solutions ``history`` (most recent first), how many are
        kept (``depth``; 0: no warm starts) and how many the next prediction uses
        (``trusted``), as in :class:`~lieflow.warm_start.WarmStart`."""
        run, args = self.loop_call(W, h, steps, history, depth, trusted)
        done = run(*args)
        states, iterations, counts = args.states, args.iterations, args.warm_counts
        if done < steps:
            states, iterations = states[:done], iterations[:done]
        batch, n = W.shape[:-2], self.n
        fixed = self._fixed[depth]
        k, shape = fixed.kernels, (*batch, *fixed.core)
        return CompiledSteps(
            states.reshape(done, *batch, n, n),
            iterations,
            tuple([args.history[j].reshape(shape) for j in range(int(counts[k.FILLED]))]),
            int(counts[k.TRUSTED]),
            done == steps,
        )

    def loop_call(
        self,
        W: Array,
        h: float,
        steps: int,
        history: Sequence[Array] = (),
        depth: int = DEFAULT_DEPTH,
        trusted: int = 1,
    ) -> tuple[Any, LoopArguments]:
        """The compiled loop that :meth:`advance` calls and its arguments, ``(run, args)``:
        ``run(*args)`` takes the steps (it returns how many it accepted and writes the
        states into ``args.states``, the updates per step into ``args.iterations``). With
        ``depth=0`` (cold starts) the call reads nothing it writes, so it may be repeated:
        what the fixed-cost benchmark times as the bare compiled step
        (``benchmarks/suites/call_cost.py``)."""
        batch, n, dtype = W.shape[:-2], self.n, self.dtype
        K = math.prod(batch)
        fixed = self._fixed.get(depth)
        if fixed is None:
            fixed = self._fixed[depth] = self._fixed_arguments(depth)
        k, size = fixed.kernels, fixed.size
        Wk = np.ascontiguousarray(W, dtype=dtype).reshape(K, n, n)
        keep = max(depth, 1)
        kept = np.zeros((keep, K, size), dtype=dtype)
        filled = min(len(history), keep) if depth else 0
        for j in range(filled):
            kept[j] = np.asarray(history[j], dtype=dtype).reshape(K, size)
        # one allocation: the warm counts, then the updates per step
        counts = np.zeros(2 + steps, dtype=np.int64)
        warm_counts, iterations = counts[:2], counts[2:]
        warm_counts[k.FILLED], warm_counts[k.TRUSTED] = filled, int(trusted)
        states = np.empty((steps, K, n, n), dtype=dtype)
        work, real_work = k.workspace(dtype, K, size, self.b.size, n, keep, fixed.max_iter)
        coefficients, weights = self.coefficients(h)
        # (positional: a NamedTuple's keywords cost 2 µs a call)
        args = k.LoopArguments(
            Wk, coefficients, weights, fixed.B, fixed.B_params, fixed.project,
            fixed.project_params, self.project is not None, fixed.tolerances, fixed.settings,
            kept, fixed.extrapolation, warm_counts, states, iterations, fixed.gemm, work,
            real_work,
        )  # fmt: skip
        return fixed.run, args

    def _fixed_arguments(self, depth: int) -> _Fixed:
        """The loops' arguments that depend on the warm-start ``depth`` alone
        (:class:`_Fixed`): the stopping rule's arrays, the extrapolation weights (a writable
        copy: the loops' type), and the addresses of ``B``, the projection (``B``'s when
        there is none: not called) and the BLAS product (0 up to ``n =``
        :data:`~lieflow.engines._numba_jit.LOOP_PRODUCTS_MAX_N`, whose entry points
        multiply in plain loops and never read it), each checked to be a resolved function
        of the signature the loops call it with
        (:func:`lieflow.engines._compiled_maps.address`; the loops take bare integers)."""
        k = kernels()
        tolerances, settings = k.stopping_arrays(self.rule, self.retry_cold, depth > 0)
        blas = self.n > k.LOOP_PRODUCTS_MAX_N  # else the loops' own products, no BLAS
        run = k.entry(f"{self.kind}_advance", self.dtype, self.conjugation, blas, self.skew)
        signature = k.map_signature(self.dtype)
        B = k.address(self.B, signature)
        P = B if self.project is None else k.address(self.project, signature)
        gemm = k.gemm(self.dtype) if blas else None
        core = self.warm_shape()
        return _Fixed(
            k, run, B, self.B_params.copy(), P, self.project_params.copy(), tolerances,
            settings, np.array(extrapolation_matrix(max(depth, 1))),
            0 if gemm is None else k.address(gemm, gemm.signature()), core, math.prod(core),
            self.rule.max_iter,
        )  # fmt: skip


@attrs.frozen(eq=False)
class CompiledSchemeFlow(SchemeFlow):
    """A :class:`~lieflow.flows.SchemeFlow` whose steps the compiled loops take, a chunk per
    call (:meth:`step_many`, used by :func:`lieflow.stepping.advance`); :meth:`step` (the
    numpy path) takes any step they do not accept. Build it with
    :func:`lieflow.engines.scheme_flow`.

    Each new state is mapped onto the phase space inside the loops, as the numpy path does
    (:meth:`~lieflow.IsospectralSystem.compiled_project`), or, for a system without a
    compiled projection, by :meth:`~lieflow.IsospectralSystem.project` once the chunk is
    done. Iterations and warm starts are the numpy path's. The per-step residual is not
    recorded by the compiled loops (``nan``).
    """

    plan: CompiledPlan = attrs.field(kw_only=True)

    def step(
        self, W: Array, t: float, h: float, state: WarmStart | None
    ) -> tuple[Array, WarmStart | None, StepStats]:
        """One step on the compiled loops (a chunk of one step), so that the flow stays
        compiled wherever it is stepped alone — inside a :class:`~lieflow.flows.Splitting`
        or a :class:`~lieflow.flows.Projected`, whose sub-steps are taken one at a time; a
        step the loops do not accept is taken by the numpy path
        (:meth:`SchemeFlow.step <lieflow.flows.SchemeFlow.step>`) from the same state."""
        chunk = self.step_many(W, 0, h, 1, state)
        if not chunk.size:
            return SchemeFlow.step(self, W, t, h, state)
        return (
            chunk.W[0],
            chunk.state,
            StepStats(int(chunk.iterations[0]), chunk.solvers[0], math.nan),
        )

    def step_many(
        self, W: Array, start: int, h: float, steps: int, state: WarmStart | None
    ) -> chunks.Chunk:
        """Up to ``steps`` steps after step ``start`` (fewer if one is not accepted)."""
        if state is None:
            c = self.plan.advance(W, h, steps, depth=0)
            new = None
        else:
            c = self.plan.advance(W, h, steps, state.history(), state.depth, int(state.trusted))
            new = state.replaced(c.history, c.trusted) if c.done else state
        states = c.states
        if c.done and self.plan.project is None:
            states = self.system.project(states)
        residuals = np.empty(c.done)  # not recorded by the loops
        residuals.fill(np.nan)  # (np.full's wrapper: 0.4 µs more)
        return chunks.Chunk(
            start,
            h,
            states,
            c.iterations,
            residuals,
            (self.plan.solver_name,) * c.done,
            new,
        )


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


def _checked_map(
    what: str,
    got: tuple[Any, Array] | None,
    checks: Sequence[tuple[Array, Array]],
    dtype: np.dtype,
) -> tuple[Any, Array] | str:
    """``(function, params)`` of a system's compiled map, compiled for
    :func:`~lieflow.engines._numba_jit.map_signature` of ``dtype`` and checked on each ``(W,
    want)``
    of ``checks`` against ``want`` (the numpy result) to roundoff; or the reason it cannot
    be used (which names the check: ``"on W0"``, then ``"off W0"``)."""
    k = kernels()
    tiny = np.finfo(float).tiny
    if not (isinstance(got, tuple) and len(got) == 2):
        return f"{what} must return (function, params), got {got!r}"
    fn, params = got
    params = np.array(params, dtype=np.float64, order="C").reshape(-1)  # a writable copy
    signature = k.map_signature(dtype)
    for i, (W, want) in enumerate(checks):
        try:
            if (
                i == 0
                and hasattr(fn, "compile")
                and not any(sig == signature.args for sig in getattr(fn, "signatures", ()))
            ):
                fn.compile(signature)
            out = np.zeros(W.shape, dtype=dtype)
            fn(np.array(W, dtype=dtype, order="C"), params, out)
        except Exception as exc:
            return (
                f"{what} does not compile for (W, params, out) with {dtype} data: "
                f"{type(exc).__name__}: {exc}"
            )
        # the arrays' own max (not np.max's Python wrapper: 1 µs less a call)
        scale = max(float(np.abs(want).max(initial=0.0)), tiny)
        if not float(np.abs(out - want).max(initial=0.0)) <= 1e-12 * scale:
            return f"{what} does not reproduce the numpy result {'on' if i == 0 else 'off'} W0"
    try:
        return k.function_pointer(fn, dtype), params
    except Exception as exc:
        return (
            f"{what} does not compile for (W, params, out) with {dtype} data: "
            f"{type(exc).__name__}: {exc}"
        )


@functools.cache
def _wave(shape: tuple[int, ...], complex_data: bool) -> Array:
    """The direction ``cos(j) (+ i sin(j))`` (``j``: the entries' flat indices) along which
    :func:`plan` checks a system's compiled maps off ``W0``; read-only, one per shape
    (a function of its immutable arguments alone, cached)."""
    wave = np.arange(math.prod(shape)).reshape(shape)
    off = np.cos(wave) + (1j * np.sin(wave) if complex_data else 0.0)
    off.setflags(write=False)
    return off


def _identity(got: Any, dtype: np.dtype) -> tuple[Any, Any, bytes | None]:
    """What the cache of checked maps compares of a hook's ``(function, params)``: the
    function, its compiled code for the data's dtype (a numba dispatcher's overload for
    :func:`~lieflow.engines._numba_jit.map_signature`: a recompiled function is checked and
    resolved
    again) and the ``params`` as float64 bytes; ``(got, None, None)`` if malformed (never
    taken from the cache)."""
    if got is None:
        return None, None, b""
    if not (isinstance(got, tuple) and len(got) == 2):
        return got, None, None
    fn = got[0]
    overloads = getattr(fn, "overloads", None)
    code = overloads.get(kernels().map_signature(dtype).args) if overloads is not None else None
    try:
        return fn, code, np.asarray(got[1], dtype=np.float64).tobytes()
    except (TypeError, ValueError):
        return got, None, None


def _unchanged(kept: tuple[Any, Any, bytes | None], got: Any) -> bool:
    """Whether a hook's ``(function, params)`` (``got``) is what was checked (``kept``, its
    :func:`_identity` then): the same function object, its checked compiled code still
    among its overloads (not recompiled), the same ``params``."""
    fn, code, params = kept
    if got is None or fn is None:
        return got is None and fn is None
    if params is None or not (isinstance(got, tuple) and len(got) == 2) or got[0] is not fn:
        return False
    overloads = getattr(fn, "overloads", None)
    # dict.values: an OrderedDict's own values() looks every key up again, hashing each
    # signature's numba types in Python (~1 µs a map and call)
    if overloads is not None:
        codes = dict.values(overloads) if isinstance(overloads, dict) else overloads.values()
        if not any(c is code for c in codes):
            return False
    try:
        return np.asarray(got[1], dtype=np.float64).tobytes() == params
    except (TypeError, ValueError):
        return False


def _by_name(got: Any) -> Any:
    """A hook's ``(function, params)`` with a function named by a string (one of
    lieflow's own maps, :data:`MAPS`) replaced by that map; a name that is none of them
    gives the reason (a string); anything else as it is (the checks that follow name what
    is wrong with it)."""
    if isinstance(got, tuple) and len(got) == 2 and isinstance(got[0], str):
        if got[0] not in MAPS:
            return f"no compiled map named {got[0]!r} (lieflow's own: {', '.join(MAPS)})"
        return getattr(kernels(), got[0]), got[1]
    return got


class _Kept:
    """What the compiled engine keeps of the systems it ran, held by the engine (:data:`_KEPT`)
    and never on a system: per live system, a dictionary of the values :func:`plan`
    derives from it (its checked compiled maps and its last plan, per dtype).

    Process-local values (compiled functions' addresses), so they cannot live in a system,
    which is copied, pickled and sent to other processes; and kept, because checking a
    system's maps again on every call would cost what the call-overhead benchmark
    (``benchmarks/suites/call_cost.py``) counts. A system is identified by its identity
    while it lives (a weak reference: an entry goes with its system; a copy or a pickle is
    another system and starts without one). Only :func:`plan` reads and writes it; what it
    hands out (a :class:`CompiledPlan`) is read-only.
    """

    def __init__(self) -> None:
        self._systems: dict[int, tuple[weakref.ref[Any], dict[Any, Any]]] = {}

    def of(self, system: IsospectralSystem) -> dict[Any, Any]:
        """The values kept for ``system`` (an empty dictionary the first time; a fresh one,
        not kept, for a system that cannot be referenced weakly)."""
        key = id(system)
        held = self._systems.get(key)
        if held is not None and held[0]() is system:
            return held[1]
        values: dict[Any, Any] = {}
        try:
            ref = weakref.ref(system, functools.partial(self._forget, key))
        except TypeError:  # not weakly referenceable (a class with __slots__): not kept
            return values
        self._systems[key] = (ref, values)
        return values

    def _forget(self, key: int, ref: weakref.ref[Any]) -> None:
        """Drop a collected system's values (its weak reference's callback)."""
        held = self._systems.get(key)
        if held is not None and held[0] is ref:
            del self._systems[key]


#: The compiled engine's values per system (:class:`_Kept`).
_KEPT = _Kept()


def _system_maps(
    system: IsospectralSystem, W0: Array, dtype: np.dtype
) -> tuple[tuple[Any, Array], tuple[Any, Array] | None] | str:
    """The system's compiled ``B`` as the loops take it (its address, and its ``params``
    led by :func:`~lieflow.engines._compiled_maps.inline_code`) and its compiled projection (or
    ``None``), checked against ``system.B(system.project_stage(V))`` and
    ``system.project(V)`` (:func:`_checked_map`) on ``V = W0`` and off it; or the reason
    they cannot be used.

    The check is of the system's maps, not of ``W0``: its result is kept by the engine
    (:data:`_KEPT`, per system and dtype) together with the maps and their ``params`` it was
    made for, and reused while :meth:`compiled_B` and :meth:`compiled_project` return the
    same functions and ``params``.
    """
    try:
        got_B = _by_name(system.compiled_B())
    except Exception as exc:  # a broken plugin: refuse the case, name the failure
        return f"{system.name}.compiled_B() raised {type(exc).__name__}: {exc}"
    if got_B is None:
        hint = " (hadamard_factor is None)" if system.hadamard_factor is None else ""
        return f"{system.name} has no compiled B{hint}: see IsospectralSystem.compiled_B"
    if isinstance(got_B, str):
        return f"{system.name}.compiled_B(): {got_B}"
    try:
        got_P = _by_name(system.compiled_project())
        P_error = (
            None if not isinstance(got_P, str) else f"{system.name}.compiled_project(): {got_P}"
        )
    except Exception as exc:  # reported after the check of B, as before
        got_P, P_error = (
            None,
            f"{system.name}.compiled_project() raised {type(exc).__name__}: {exc}",
        )
    values = _KEPT.of(system)
    key = ("compiled maps", dtype)
    kept = values.get(key)
    if (
        P_error is None
        and kept is not None
        and _unchanged(kept[0], got_B)
        and _unchanged(kept[1], got_P)
    ):
        return kept[2]
    k = kernels()
    W = np.ascontiguousarray(W0.reshape(-1, *W0.shape[-2:])[0])
    Wp = W + 1e-3 * float(np.abs(W).max(initial=1.0)) * _wave(W.shape, dtype.kind == "c")
    Bw = _checked_map(
        f"{system.name}.compiled_B()",
        got_B,
        [(V, system.B(system.project_stage(V))) for V in (W, Wp)],
        dtype,
    )
    if isinstance(Bw, str):
        return Bw
    if P_error is not None:
        return P_error
    P: tuple[Any, Array] | None = None
    if got_P is not None:
        Pw = _checked_map(
            f"{system.name}.compiled_project()", got_P, [(Wp, system.project(Wp))], dtype
        )
        if isinstance(Pw, str):
            return Pw
        P = Pw
    params = np.concatenate([[float(k.inline_code(got_B[0]))], Bw[1]])
    maps = ((Bw[0], params), P)
    # what the maps are now that the check compiled them
    values[key] = (_identity(got_B, dtype), _identity(got_P, dtype), maps)
    return maps


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
        kernels()
    except ImportError as exc:
        return f"it needs numba: pip install 'lieflow[fast]' (importing it failed: {exc})"
    maps = _system_maps(system, W0, dtype)
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
