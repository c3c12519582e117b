"""Fixed-point iteration (the paper's solver), optionally Anderson-accelerated, and the
frozen-B quasi-Newton iteration of SPEC §5."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import attrs
import numpy as np

from ..algebras import Array
from ..backends import (
    HYPOT_SIZE,
    device_norms,
    is_numpy,
    machine_epsilon,
    namespace,
    to_numpy,
    vdot,
)
from ..errors import InputError
from . import anderson, arguments
from .base import (
    DOT_SIZE,
    ImplicitProblem,
    SolveResult,
    batch_norm,
    squared_norm,
)

_EPS = float(np.finfo(float).eps)


@attrs.frozen
class StoppingRule:
    """When an iteration has converged, stalled or diverged (SPEC §5).

    * **converged**: ``||x_{k+1} - x_k|| <= atol + rtol ||x_{k+1}||`` for every problem in
      the batch;
    * **non_finite**: an iterate (or its norm) is NaN/Inf;
    * **diverged**: the iterate has grown by more than ``divergence_factor`` over the
      initial guess;
    * **stalled** / **roundoff**: the relative update ``r_k`` set no new minimum for
      ``patience`` iterations — accepted as ``"roundoff"`` when the best ``r`` is below
      ``roundoff_floor`` (no floating-point iteration can do better; the floor is given for
      double precision and scaled by the ratio of machine epsilons for single-precision
      iterates, see :class:`IterationMonitor`), ``"diverged"`` if the
      iterate has grown tenfold meanwhile, ``"stalled"`` otherwise;
    * **stalled** (too slow): with ``project=True``, once ``window`` iterations are done,
      the contraction rate measured over the last ``window`` iterations predicts that
      ``rtol`` will not be reached within ``max_iter`` (fail early instead of burning the
      budget, so a fallback solver can take over);
    * **max_iterations**: ``max_iter`` updates without any of the above — unless the last
      relative update is below ``roundoff_floor``: a slowly contracting iteration (rate
      0.76 on a point-vortex block-form step at ``h = 0.25``) that reaches the cap at
      roundoff is accepted as ``"roundoff"``, not given up on.
    """

    rtol: float = attrs.field(default=1e-14, validator=arguments.non_negative)
    atol: float = attrs.field(default=0.0, validator=arguments.non_negative)
    max_iter: int = attrs.field(default=100, validator=arguments.integer_at_least(1))
    patience: int = attrs.field(default=6, validator=arguments.integer_at_least(1))
    roundoff_floor: float = attrs.field(default=256 * _EPS, validator=arguments.positive)
    divergence_factor: float = attrs.field(default=100.0, validator=arguments.positive)
    project: bool = attrs.field(default=True, validator=attrs.validators.instance_of(bool))
    window: int = attrs.field(default=10, validator=arguments.integer_at_least(2))

    #: What the lean single-problem check reads (:func:`lean_check`), derived once per
    #: rule (after validation) rather than on every solve: :func:`stopping_verdict`'s
    #: arguments after ``growth``; ``atol``, ``rtol`` and ``divergence_factor``; and how
    #: many updates an unmet, finite, bounded update surely goes on
    #: (``min(patience, window, max_iter - 1)``).
    _lean: tuple[tuple[Any, ...], float, float, float, int] = attrs.field(
        init=False, eq=False, repr=False
    )

    @classmethod
    def of(cls, solver: Any, divergence_factor: float, project: bool = True) -> StoppingRule:
        """The rule of ``solver``: its ``rtol``, ``atol``, ``max_iter``, ``patience`` and
        ``roundoff_floor`` (the fields every iterative solver has), with
        ``divergence_factor`` and ``project`` as given."""
        return cls(
            solver.rtol, solver.atol, solver.max_iter, solver.patience, solver.roundoff_floor,
            divergence_factor, project=project,
        )  # fmt: skip

    def __attrs_post_init__(self) -> None:
        if self.rtol == 0 and self.atol == 0:
            raise InputError("rtol and atol cannot both be zero: the iteration could never stop")
        args = (
            self.rtol, self.roundoff_floor, self.divergence_factor, self.max_iter,
            self.patience, self.window, self.project,
        )  # fmt: skip
        quiet = min(self.patience, self.window, self.max_iter - 1)
        # frozen: set once here, as attrs documents for derived values
        object.__setattr__(
            self, "_lean", (args, self.atol, self.rtol, self.divergence_factor, quiet)
        )

    def verdict(self, residuals: list[float], met: bool, growth: float) -> str | None:
        """``None`` to go on, else the reason to stop.

        ``residuals`` are the relative updates so far, ``met`` whether the last one meets
        the tolerance, ``growth`` the largest ``||x_k|| / ||x_0||`` over the batch. The rule
        itself is :func:`stopping_verdict`, which the compiled engine runs too.
        """
        code = stopping_verdict(
            residuals, len(residuals), met, growth, self.rtol, self.roundoff_floor,
            self.divergence_factor, self.max_iter, self.patience, self.window, self.project,
        )  # fmt: skip
        return REASONS[code]


#: The reasons :func:`stopping_verdict` returns, by code (0: go on).
REASONS: tuple[str | None, ...] = (
    None, "converged", "roundoff", "non_finite", "diverged", "stalled", "max_iterations",
)  # fmt: skip
GO, CONVERGED, ROUNDOFF, NON_FINITE, DIVERGED, STALLED, MAX_ITERATIONS = range(7)


def stopping_verdict(
    res: Any,
    k: int,
    met: bool,
    growth: float,
    rtol: float,
    floor: float,
    divergence: float,
    max_iter: int,
    patience: int,
    window: int,
    project: bool,
) -> int:
    """The stopping rule of :class:`StoppingRule` on the relative updates ``res[:k]``: the
    code of the reason to stop (an index into :data:`REASONS`), :data:`GO` to go on.

    One source for both engines: :meth:`StoppingRule.verdict` calls it as plain Python (on
    a list), and :mod:`lieflow.engines.compiled` compiles this very function with numba (on an
    array); hence scalars, indexing and ``math`` only. ``met``: the last update meets the
    tolerance; ``growth``: the largest ``||x_k|| / ||x_0||``; ``floor``: the roundoff floor;
    ``divergence``: the divergence factor; the rest as in :class:`StoppingRule`.
    """
    r = res[k - 1]
    if not (math.isfinite(r) and math.isfinite(growth)):
        return NON_FINITE
    if met:
        return CONVERGED
    if growth > divergence:
        return DIVERGED
    best_at = 0
    for i in range(1, k):
        if res[i] < res[best_at]:
            best_at = i
    best = res[best_at]
    if k - 1 - best_at >= patience:
        if best <= floor:
            return ROUNDOFF
        return DIVERGED if growth > 10.0 else STALLED
    if project and k > window and best > floor:
        earlier = res[0]
        for i in range(1, k - window):
            earlier = min(earlier, res[i])
        if earlier > 0.0:
            rate = (best / earlier) ** (1.0 / window)
            if rate >= 1.0:
                return STALLED
            if rate > 0.0 and k + math.log(max(rtol, floor) / best) / math.log(rate) > max_iter:
                return STALLED
    if k >= max_iter:
        # A contracting iteration whose update is already at roundoff is done: with
        # contraction rho the error is below r rho / (1 - rho), a few ulps of the floor.
        return ROUNDOFF if r <= floor else MAX_ITERATIONS
    return GO


def lean_check(
    rule: StoppingRule, core_ndim: int, x0: Array, residuals: list[float]
) -> Callable[..., str | None] | None:
    """The stopping test of one problem (no batch axes) of real or complex NumPy iterates,
    as a function ``check(new, old, norms=None)`` -> ``None`` to go on, else the reason to
    stop; it appends each relative update to ``residuals``. ``None`` for any other ``x0``
    (a batch, an array of another library): :class:`IterationMonitor` judges those.
    ``norms``: ``(||new||², ||new - old||²)`` where the caller has them already (Anderson's
    update computes both: :attr:`lieflow.solvers.anderson.AndersonState.gnorm2`,
    ``norm2``), so the test reads neither array again.

    The same numbers as :meth:`IterationMonitor.check` on a batch of one, as Python floats:
    a few NumPy calls instead of a dozen array reductions per update, and the rule's
    constants (:attr:`StoppingRule._lean`) and the reference size held in the function's
    closure rather than read from an object on every update (so(3): 1.3 µs less per solve
    of 5 updates). Growth is measured against ``max(||x0||, ||F(x0)||)`` (the first update
    is from ``x0``: its ``old``), so a zero initial guess works; the roundoff floor of
    single-precision iterates is scaled by the ratio of machine epsilons
    (:class:`StoppingRule`).
    """
    if not (type(x0) is np.ndarray or is_numpy(x0)) or x0.ndim != core_ndim:
        return None
    dtype = x0.dtype
    eps = _EPS if dtype.char in "dD" else _eps(dtype)  # np.finfo costs µs per call
    if eps > _EPS:  # single precision: the floor scales with machine epsilon
        rule = attrs.evolve(rule, roundoff_floor=rule.roundoff_floor * (eps / _EPS))
    args, atol, rtol, divergence, quiet = rule._lean
    # a small real array (up to DOT_SIZE numbers): its squared norms by vdot, inline; a
    # tiny one (so(3), so(4)...): by math.hypot of its entries as Python floats, no NumPy
    # reduction at all (9 entries: 0.2 µs against 1.1 µs for einsum), never overflowing;
    # anything else (complex, large): squared_norm
    hypot = dtype.kind == "f" and x0.size <= HYPOT_SIZE
    dot = dtype.kind == "f" and x0.size <= DOT_SIZE
    # the reference size of the growth test, max(||x0||, ||F(x0)||), set by the first update
    size0 = _TINY
    # hypot mode: the last iterate judged and its entries, which the next update's step
    # reuses when that update starts from it (``old is last``, as in FixedPoint.solve)
    last: Array | None = None
    last_entries: list[float] = []

    def check(new: Array, old: Array, norms: tuple[float, float] | None = None) -> str | None:
        nonlocal size0, last, last_entries
        # ||new|| first: when it is finite, ``new - old`` raises no floating-point warning
        # (``old`` is the last finite iterate or the guess; inf or nan there propagate
        # quietly), so no ``np.errstate`` (a context switch per update) is needed.
        if norms is not None:
            size2 = norms[0]
            step = math.sqrt(norms[1]) if size2 < _INF else _NAN
            size = math.sqrt(size2)
        elif hypot:
            # (a norm whose square overflows counts as infinite, as the sums below)
            entries = new.ravel().tolist()
            size = math.hypot(*entries)
            size2 = size * size
            if size2 < _INF:
                # ||new - old|| by math.dist of the entries: the differences rounded as
                # NumPy's, the norm by hypot's own algorithm (CPython's vector_norm, the
                # same bits as math.hypot of new - old), without a NumPy subtraction;
                # old's entries from the last update when old is its iterate
                before = last_entries if old is last else old.ravel().tolist()
                step = math.dist(entries, before)
            else:
                step = _NAN
            last, last_entries = new, entries
            if step * step == _INF:
                step = _INF
        elif dot:
            # squared_norm's own fast path, inline (two calls per update less; measured
            # ~3 % of an so(10) step): vdot, BLAS ddot (ndarray.dot's bits) that never warns
            # where squares of finite entries overflow, the blow-up this check reports
            flat = new.ravel()
            size2 = float(vdot(flat, flat))
            if size2 < _INF:
                flat = (new - old).ravel()
                step = math.sqrt(float(vdot(flat, flat)))
            else:
                step = _NAN
            size = math.sqrt(size2)
        else:
            size2 = squared_norm(new)
            step = math.sqrt(squared_norm(new - old)) if size2 < _INF else _NAN
            size = math.sqrt(size2)
        if not (step < _INF and size2 < _INF):
            residuals.append(_NAN)
            return "non_finite"
        if not residuals:  # the first update, from x0: ||x0|| as the iterates' norms
            if hypot and norms is None:  # (its entries, read for the step above)
                norm0 = math.hypot(*before)
            elif dot and norms is None:
                flat = old.ravel()
                norm0 = math.sqrt(float(vdot(flat, flat)))
            else:
                norm0 = math.sqrt(squared_norm(old))
            size0 = max(norm0, size, _TINY)
        r = step / (size if size > _TINY else _TINY)  # max(size, tiny): size is finite here
        residuals.append(r)
        met = step <= atol + rtol * size
        growth = size / size0
        # Two shortcuts, each what stopping_verdict returns in its case (it checks finiteness
        # first, then the tolerance, then divergence, and judges stagnation only after
        # more than ``patience``, the contraction rate after more than ``window`` updates,
        # the cap at ``max_iter``).
        if r < _INF and growth < _INF:
            if met:
                return "converged"
            if len(residuals) <= quiet and growth <= divergence:
                return None
        return REASONS[stopping_verdict(residuals, len(residuals), met, growth, *args)]

    return check


class IterationMonitor:
    """The bookkeeping of one solve for a :class:`StoppingRule`: the history of relative
    updates and the growth of the iterate. Local to a ``solve`` call (never shared).

    One NumPy problem is judged by :func:`lean_check`; a batch (or arrays of another
    library) by :meth:`check`'s array reductions, with the same numbers."""

    def __init__(self, rule: StoppingRule, core_ndim: int, x0: Array, check_every: int = 1) -> None:
        self.residuals: list[float] = []
        self.core = core_ndim
        self._lean = lean_check(rule, core_ndim, x0, self.residuals)
        dtype = x0.dtype
        host = is_numpy(x0)
        # arrays of another library (lieflow.backends): norms on their device, one small
        # copy to the host per ``check_every`` updates (the stopping rule's only
        # synchronisation); NumPy arrays are judged after every update
        self._host = host
        self._every = 1 if host else check_every
        self._pending: list[Any] = []
        eps = _eps(dtype) if host else machine_epsilon(dtype, x0)
        if eps > _EPS:  # single precision: the floor scales with machine epsilon
            rule = attrs.evolve(rule, roundoff_floor=rule.roundoff_floor * (eps / _EPS))
        self.rule = rule
        if self._lean is None:
            self._size0 = (
                batch_norm(x0, core_ndim)
                if host
                else np.asarray(to_numpy(device_norms(x0, core_ndim)), dtype=np.float64)
            )

    def check(self, new: Array, old: Array) -> str | None:
        """Record the update ``old -> new``; ``None`` to go on, else the reason to stop.

        Growth is measured against ``max(||x0||, ||F(x0)||)`` so a zero initial guess works.
        Arrays of another library: the norms stay on the device until ``check_every``
        updates (or ``max_iter`` in all) are pending, then come to the host in one copy and
        are judged in order; the first reason found is returned (the later updates of the
        group are recorded too: the iterate returned is the latest).
        """
        if self._lean is not None:
            return self._lean(new, old)
        if self._host:
            with np.errstate(invalid="ignore", over="ignore"):
                step = batch_norm(new - old, self.core)
                size = batch_norm(new, self.core)
            return self._judge(step, size)
        xp = namespace(new)
        pending = self._pending
        pending.append(xp.stack((device_norms(new - old, self.core), device_norms(new, self.core))))
        if len(pending) < self._every and len(self.residuals) + len(pending) < self.rule.max_iter:
            return None
        norms = np.asarray(to_numpy(xp.stack(pending)), dtype=np.float64)
        pending.clear()
        reason = None
        for step, size in norms:
            verdict = self._judge(step, size)
            reason = reason or verdict
        return reason

    def _judge(self, step: Array, size: Array) -> str | None:
        """The verdict on one update of norms ``step = ||new - old||``, ``size = ||new||``
        (host arrays of the batch shape)."""
        rule = self.rule
        with np.errstate(invalid="ignore", over="ignore"):
            if not (np.all(np.isfinite(step)) and np.all(np.isfinite(size))):
                self.residuals.append(float("nan"))
                return "non_finite"
            if not self.residuals:
                self._size0 = np.maximum(np.maximum(self._size0, size), np.finfo(float).tiny)
            rel = float(np.max(step / np.maximum(size, np.finfo(float).tiny)))
        self.residuals.append(rel)
        met = bool(np.all(step <= rule.atol + rule.rtol * size))
        return rule.verdict(self.residuals, met, float(np.max(size / self._size0)))


#: How many of the last map values a single-problem solve replays into Anderson's history
#: when the history starts (two secant columns; the older values are from the fast first
#: updates of a warm-started solve, and each replayed value costs an update of the
#: history: replaying all ``depth + 1`` cost 5–10 % more per step at N = 256, the same
#: updates).
_REPLAY = 3

_TINY = float(np.finfo(float).tiny)
_INF = math.inf
_NAN = math.nan


def _eps(dtype: np.dtype) -> float:
    """Machine epsilon of a floating dtype (of float64 for any other)."""
    return float(np.finfo(dtype).eps) if dtype.kind in "fc" else _EPS


@attrs.frozen
class FixedPoint:
    """Fixed-point iteration ``x <- F(x)`` with the stopping rule of :class:`StoppingRule`.

    Parameters
    ----------
    rtol, atol, max_iter
        Stopping tolerances and the iteration cap (see :class:`StoppingRule`).
    anderson : int
        Depth ``m`` of Anderson acceleration (:mod:`lieflow.solvers.anderson`); 0 (default)
        is the plain iteration. With ``m > 0`` an update mixes the map value with the
        differences of the last ``m`` updates, ``O(m · size)`` work, once the contraction
        is slow (``anderson.ENGAGE``) on problems of at least ``anderson.MIN_SIZE``
        numbers; anywhere else it is the plain iteration, bit for bit. Iterations still
        count map evaluations.
    patience, roundoff_floor, divergence_factor
        Stagnation and divergence detection (see :class:`StoppingRule`).
    check_every : int
        Arrays of another library (a GPU's): read the stopping test on the host once every
        ``check_every`` updates (default 1). The norms of each update are computed on the
        device either way and judged in order; the copy to the host, which waits for the
        device, happens once per group, so the host can queue the next updates while the
        device works. The solve ends at the end of the group in which the rule fires and
        returns the latest iterate (up to ``check_every - 1`` updates more than needed,
        counted in ``iterations``; they only bring a converging iterate closer). NumPy
        arrays are judged after every update (there is nothing to wait for).
    """

    # the stopping rule's arguments are validated by StoppingRule (built in __init__)
    rtol: float = 1e-14
    atol: float = 0.0
    max_iter: int = 100
    anderson: int = attrs.field(default=0, kw_only=True, validator=arguments.integer_at_least(0))
    patience: int = attrs.field(default=6, kw_only=True)
    roundoff_floor: float = attrs.field(default=256 * _EPS, kw_only=True)
    divergence_factor: float = attrs.field(default=100.0, kw_only=True)
    check_every: int = attrs.field(
        default=1,
        kw_only=True,
        validator=arguments.integer_at_least(1),
        metadata={"identity": False},  # when the host looks, not what is computed
    )

    name = "fixed_point"

    rule: StoppingRule = attrs.field(init=False, repr=False, eq=False)

    @rule.default
    def _rule(self) -> StoppingRule:
        return StoppingRule.of(self, self.divergence_factor)

    def _map(self, problem: ImplicitProblem) -> Callable[[Array], Array]:
        return problem.map

    def _map_with_norms(
        self, problem: ImplicitProblem
    ) -> Callable[[Array], tuple[Array, tuple[float, float] | None]] | None:
        """The problem's ``map_with_norms`` (the map and the stopping test's squared norms
        from one pass, where it has one: :meth:`MidpointProblem.map_with_norms
        <lieflow.schemes.sydirk.MidpointProblem.map_with_norms>`), else ``None``."""
        return getattr(problem, "map_with_norms", None)

    def solve(self, problem: ImplicitProblem) -> SolveResult:
        """Iterate the scheme's map from ``problem.x0`` until the stopping rule fires."""
        F = self._map(problem)
        x = problem.x0
        res: list[float] = []
        # one NumPy problem: the lean check alone (no monitor object per solve)
        lean = lean_check(self.rule, problem.core_ndim, x, res)
        check: Callable[[Array, Array], str | None]
        if lean is not None:
            check = lean
        else:
            monitor = IterationMonitor(self.rule, problem.core_ndim, x, self.check_every)
            check, res = monitor.check, monitor.residuals
        # Anderson acceleration (lieflow.solvers.anderson), where it can pay (problems of
        # anderson.MIN_SIZE numbers or more): one problem starts its history only once the
        # contraction is slow enough for it to engage, replaying the last _REPLAY map values
        # (the plain updates before cost nothing extra); a batch starts it at once
        depth = self.anderson
        if depth and not anderson.accelerates(x, problem.core_ndim):
            depth = 0
        state: anderson.AndersonState | None = None
        # the unknowns are skew(-Hermitian) matrices: Anderson may read half of each
        skew = bool(getattr(problem, "skew_unknowns", False))
        pairs: list[tuple[Array, Array]] = []
        one = x.ndim == problem.core_ndim
        # one NumPy problem, plain updates: the stopping test's norms from the map's own
        # last pass where it computes them (no pass over g and x, no g - x)
        fused = self._map_with_norms(problem) if lean is not None else None
        while True:
            if fused is not None and lean is not None and state is None:
                g, norms = fused(x)
                reason = lean(g, x, norms)
            elif lean is not None and state is not None:
                g = F(x)
                # one NumPy problem, accelerated: the update first, its norms judged (the
                # last update of a solve is then computed and dropped: cheaper than the
                # test's own pass over both arrays on every update)
                state, x_next = anderson.update(state, x, g, skew)
                reason = lean(g, x, (float(state.gnorm2), float(state.norm2)))
            else:
                g = F(x)
                reason = check(g, x)
            if reason is not None:
                ok = reason in ("converged", "roundoff")
                return SolveResult(g if ok else x, ok, len(res), tuple(res), reason, self.name)
            if not depth:
                x = g
            elif lean is not None and state is not None:
                x = x_next
            elif state is not None:
                state, x = anderson.update(state, x, g, skew)
            elif one and not (len(res) > 1 and res[-1] > anderson.ENGAGE * res[-2]):
                pairs.append((x, g))
                del pairs[: -min(depth + 1, _REPLAY)]
                x = g
            else:
                state = anderson.start(x, depth, problem.core_ndim)
                for old in pairs:
                    state, _ = anderson.update(state, *old, skew)
                pairs.clear()
                state, x = anderson.update(state, x, g, skew)


@attrs.frozen
class FrozenB(FixedPoint):
    """Frozen-B quasi-Newton iteration (SPEC §5): evaluate ``B`` at the current iterate, then
    solve the equation — linear once ``B`` is fixed — exactly, e.g. for the block algorithm

    .. math:: M \\leftarrow (I - hA\\mathbf B_k)^{-1} \\mathbf W_0 (I + h\\mathbf B_k A^T)^{-1}.

    It converges for steps where plain fixed-point iteration diverges, at the price of
    small dense linear solves per iteration.
    """

    name = "frozen_b"

    def _map(self, problem: ImplicitProblem) -> Callable[[Array], Array]:
        return problem.frozen_map

    def _map_with_norms(self, problem: ImplicitProblem) -> None:
        return None
