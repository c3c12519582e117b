"""A case the compiled engine runs (:class:`CompiledPlan`, made by
:func:`lieflow.engines.compiled.plan`): the loops' arguments that do not change from call to
call, the call that advances a chunk of steps (:meth:`CompiledPlan.advance`), what it returns
(:class:`CompiledSteps`), and the flow that steps through it (:class:`CompiledSchemeFlow`)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import ModuleType
from typing import TYPE_CHECKING, Any, NamedTuple

import attrs
import numpy as np

from .. import chunks
from ..algebras import Array
from ..flows import SchemeFlow, StepStats
from ..schemes.base import Scheme
from ..schemes.block import reduced_coefficients
from ..schemes.sydirk import midpoint_coefficients
from ..solvers.base import Solver
from ..solvers.fixed_point import StoppingRule
from ..systems.base import IsospectralSystem
from ..warm_start import DEFAULT_DEPTH, WarmStart, extrapolation_matrix

if TYPE_CHECKING:
    from ._compiled_loops import LoopArguments


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
    one warm-start depth (made once per plan and depth): the entry point, its arguments of
    that kind (:class:`lieflow.engines._compiled_loops.LoopArguments`: writable copies of the
    plan's values, which nothing outside the plan sees), the warm offsets' core shape and
    size, and ``max_iter``."""

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

    Build it with :func:`~lieflow.engines.compiled.plan`. ``kind`` selects the formulation
    (``Scheme.compiled_form``); ``A``, ``b`` are the tableau's coefficients; ``B``/``B_params`` the
    system's compiled ``B`` (:meth:`~lieflow.IsospectralSystem.compiled_B`) and
    ``project``/``project_params`` its compiled projection onto the phase space (``None``: each
    chunk is projected by ``system.project`` afterwards); ``rule`` is the fixed-point stopping rule
    (:class:`~lieflow.solvers.StoppingRule`); ``retry_cold``: a failed warm-started solve is retried
    from the cold guess inside the loops (:func:`lieflow.schemes.base.retries_cold`; not under
    ``Auto``, which hands a failed solve to Newton first: the step is handed to the numpy path).
    ``conjugation``: the scheme's ``update`` is ``"conjugation"`` (SPEC §4.7). The arrays are
    read-only: a plan is kept by the engine (:func:`~lieflow.engines.compiled.plan`) and serves
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
    #: The compiled loops' module (:func:`lieflow.engines.compiled.kernels`).
    loops: ModuleType = attrs.field(kw_only=True, repr=False)
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
        :func:`~lieflow.engines.compiled.plan` returned it for them): the one built last when they
        are the same objects (a flow is an immutable value; ~1 µs a call saved), else a new one."""
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
        k, shape = self.loops, (*batch, *fixed.core)
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
        k, size = self.loops, fixed.size
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
        k = self.loops
        tolerances, settings = k.stopping_arrays(self.rule, self.retry_cold, depth > 0)
        blas = self.n > k.LOOP_PRODUCTS_MAX_N  # else the loops' own products, no BLAS
        run = k.entry(f"{self.kind}_advance", self.dtype, self.conjugation, blas, self.skew)
        signature = k.map_signature(self.dtype)
        B = k.address(self.B, signature)
        P = B if self.project is None else k.address(self.project, signature)
        gemm = k.gemm(self.dtype) if blas else None
        core = self.warm_shape()
        return _Fixed(
            run, B, self.B_params.copy(), P, self.project_params.copy(), tolerances,
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
