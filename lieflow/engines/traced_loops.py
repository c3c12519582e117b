r"""The solvers' iterations as traced loops: one ``jax.lax.while_loop`` per solve, the stopping
rule judged on the device, nothing returned to Python between updates.

A scheme's step (:meth:`Scheme.step <lieflow.schemes.Scheme.step>`) is written once against
the array API and asks its solver to ``solve`` the problem it poses. Traced by ``jax.jit``,
that step receives a :class:`TracedSolver` instead of the user's solver: the same iteration
— the problem's map (:class:`~lieflow.solvers.FixedPoint`) or frozen-B map
(:class:`~lieflow.solvers.FrozenB`), :class:`~lieflow.solvers.Auto`'s fallback — as a loop
of the traced program, stopped by :func:`verdict`, which is
:func:`~lieflow.solvers.fixed_point.stopping_verdict` on arrays: the relative updates in a
buffer of ``max_iter`` entries, the minimum and the stagnation counters by masked
reductions, every branch of the rule a ``where`` in the rule's order of precedence (the
same codes, tested against the scalar rule on random histories).

The norms are those of :class:`~lieflow.solvers.fixed_point.IterationMonitor`: per problem
of a stack, ``r_k = max ||x_{k+1} - x_k|| / ||x_{k+1}||``, growth against
``max(||x_0||, ||F(x_0)||)``, converged when every problem meets ``atol + rtol ||x||``, the
roundoff floor scaled to the iterate's precision.

A solve that does not converge does not raise here (a traced program cannot): the solver
reports its verdict to the engine (:attr:`TracedSolver.verdicts`), which ends its chunk
before that step and hands it to the eager engine, where the error is raised as on every
engine.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import attrs
import numpy as np

from ..solvers import anderson
from ..solvers.base import ImplicitProblem, Solver, SolveResult
from ..solvers.fixed_point import (
    _EPS,
    CONVERGED,
    DIVERGED,
    GO,
    MAX_ITERATIONS,
    NON_FINITE,
    ROUNDOFF,
    STALLED,
    FixedPoint,
    FrozenB,
    StoppingRule,
)
from ..solvers.newton import (
    Auto,
    Newton,
    dense_direction,
    gmres_direction,
    line_search,
    real_size,
    total_norm,
)

__all__ = ["TracedSolver", "supported", "verdict"]

#: A value of a traced program (a JAX tracer), or a concrete JAX array.
Traced = Any


def verdict(
    rule: StoppingRule, floor: float, res: Traced, k: Traced, met: Traced, growth: Traced
) -> Traced:
    """:func:`~lieflow.solvers.fixed_point.stopping_verdict` of ``rule`` on the relative
    updates ``res[:k]`` (``res``: a buffer of ``rule.max_iter`` entries, ``+inf`` from
    ``k`` on), traced: the code of the reason to stop, :data:`GO` to go on. ``floor`` is the
    roundoff floor scaled to the iterate's precision."""
    import jax.numpy as jnp

    idx = jnp.arange(res.shape[0])
    r = res[k - 1]
    finite = jnp.isfinite(r) & jnp.isfinite(growth)
    masked = jnp.where(idx < k, res, jnp.inf)
    best_at = jnp.argmin(masked)  # the first minimum, as the scalar rule's strict <
    best = masked[best_at]
    stagnant = k - 1 - best_at >= rule.patience
    stagnant_code = jnp.where(best <= floor, ROUNDOFF, jnp.where(growth > 10.0, DIVERGED, STALLED))
    earlier = jnp.min(jnp.where(idx < k - rule.window, res, jnp.inf))
    judged = rule.project & (k > rule.window) & (best > floor) & (earlier > 0.0)
    rate = (best / jnp.where(judged, earlier, 1.0)) ** (1.0 / rule.window)
    safe_rate = jnp.where((rate > 0.0) & (rate < 1.0), rate, 0.5)
    needed = k + jnp.log(max(rule.rtol, floor) / jnp.where(judged, best, 1.0)) / jnp.log(safe_rate)
    too_slow = judged & ((rate >= 1.0) | ((rate > 0.0) & (needed > rule.max_iter)))
    code = jnp.where(k >= rule.max_iter, jnp.where(r <= floor, ROUNDOFF, MAX_ITERATIONS), GO)
    code = jnp.where(too_slow, STALLED, code)
    code = jnp.where(stagnant, stagnant_code, code)
    code = jnp.where(growth > rule.divergence_factor, DIVERGED, code)
    code = jnp.where(met, CONVERGED, code)
    return jnp.where(finite, code, NON_FINITE)


def _norms(x: Traced, core_ndim: int) -> Traced:
    """Frobenius norms over the trailing ``core_ndim`` axes (the batch shape)."""
    import jax.numpy as jnp

    axes = tuple(range(x.ndim - core_ndim, x.ndim))
    return jnp.sqrt(jnp.sum(jnp.real(x * jnp.conj(x)), axis=axes))


@attrs.frozen
class Iteration:
    """How one traced solve iterates: ``kind`` — ``"map"`` (fixed-point iteration of the
    problem's map), ``"frozen_map"`` (of its frozen-B map) or ``"newton"`` — with the
    solver it restates (its stopping rule, name and options)."""

    kind: str
    solver: Any

    @property
    def name(self) -> str:
        """The solver's name (what a step's stats record)."""
        return str(self.solver.name)


def _iteration(solver: Solver) -> Iteration | None:
    """The traced iteration of ``solver``: plain fixed-point iteration (or its frozen-B
    form) and Newton's method, as the classes define them (a subclass that changes
    ``solve`` or the map has none)."""
    if isinstance(solver, Newton):
        return Iteration("newton", solver) if type(solver).solve is Newton.solve else None
    if type(solver).solve is not FixedPoint.solve:
        return None
    if isinstance(solver, FrozenB) and type(solver)._map is FrozenB._map:
        return Iteration("frozen_map", solver)
    if isinstance(solver, FixedPoint) and type(solver)._map is FixedPoint._map:
        return Iteration("map", solver)
    return None


def supported(solver: Solver) -> str | None:
    """``None`` if a traced engine runs ``solver``, else the reason it does not."""
    if isinstance(solver, Auto) and type(solver).solve is Auto.solve:
        return supported(solver.first) or supported(solver.fallback)
    if _iteration(solver) is None:
        return (
            f"solver {getattr(solver, 'name', type(solver).__name__)!r} has no traced form "
            "(FixedPoint, with Anderson acceleration or without, FrozenB, Newton, and Auto of them)"
        )
    return None


@attrs.frozen
class _Judge:
    """The stopping test of one solve (:class:`~lieflow.solvers.fixed_point.IterationMonitor`'s
    numbers, traced): ``rule``, its roundoff floor scaled to the iterate's precision and
    the number of updates the scalar rule's shortcut lets go on unjudged."""

    rule: StoppingRule
    core: int
    floor: float
    quiet: int

    @classmethod
    def of(cls, rule: StoppingRule, x0: Traced, core: int) -> _Judge:
        import jax.numpy as jnp

        eps = float(jnp.finfo(x0.dtype).eps)
        quiet = min(rule.patience, rule.window, rule.max_iter - 1)
        return cls(rule, core, rule.roundoff_floor * max(eps / _EPS, 1.0), quiet)

    def start(self, x0: Traced) -> tuple[Traced, Traced, Traced]:
        """``(relative updates, reference sizes, count)`` before the first update."""
        import jax.numpy as jnp

        res = jnp.full((self.rule.max_iter,), jnp.inf, dtype=jnp.float64)
        return res, _norms(x0, self.core).astype(jnp.float64), jnp.asarray(0, jnp.int64)

    def __call__(
        self, new: Traced, old: Traced, res: Traced, size0: Traced, k: Traced
    ) -> tuple[Traced, Traced, Traced, Traced]:
        """Record the update ``old -> new`` as the ``k``-th: ``(res, size0, code, r)``."""
        import jax.numpy as jnp
        from jax import lax

        rule, tiny = self.rule, float(np.finfo(float).tiny)
        step = _norms(new - old, self.core).astype(jnp.float64)
        size = _norms(new, self.core).astype(jnp.float64)
        size0 = jnp.where(k == 0, jnp.maximum(jnp.maximum(size0, size), tiny), size0)
        finite = jnp.all(jnp.isfinite(step)) & jnp.all(jnp.isfinite(size))
        r = jnp.where(finite, jnp.max(step / jnp.maximum(size, tiny)), jnp.nan)
        res = res.at[k].set(r)
        met = jnp.all(step <= rule.atol + rule.rtol * size)
        growth = jnp.max(size / size0)
        # the scalar rule's two shortcuts (lean_check): a met tolerance converges; an unmet,
        # finite, bounded update within the first ``quiet`` goes on — the whole rule only
        # otherwise
        plain = finite & (met | ((k + 1 <= self.quiet) & (growth <= rule.divergence_factor)))
        code = lax.cond(
            plain,
            lambda: jnp.where(met, CONVERGED, GO).astype(jnp.int64),
            lambda: verdict(rule, self.floor, res, k + 1, met, growth).astype(jnp.int64),
        )
        return res, size0, code, r


def _fixed_point(problem: ImplicitProblem, it: Iteration) -> tuple[Traced, Traced, Traced, Traced]:
    """One traced fixed-point solve: ``(x, iterations, last relative update, code)``."""
    import jax.numpy as jnp
    from jax import lax

    F: Callable[[Traced], Traced] = getattr(problem, it.kind)
    x0 = problem.x0
    core = problem.core_ndim
    judge = _Judge.of(it.solver.rule, x0, core)
    # Anderson acceleration (FixedPoint(anderson=m)): its history carried by the loop, the
    # next iterate its update of (x, F(x)); never where it never mixes (small problems)
    depth = int(getattr(it.solver, "anderson", 0)) if it.kind == "map" else 0
    mixing = depth > 0 and anderson.accelerates(x0, core)

    def body(carry: tuple[Any, ...]) -> tuple[Any, ...]:
        x, _, k, res, size0, _, _, history = carry
        g = F(x)
        res, size0, code, r = judge(g, x, res, size0, k)
        if mixing:
            history, x_next = anderson.update(history, x, g)
        else:
            x_next = g
        return x_next, g, k + 1, res, size0, code, r, history

    res0, size0, k0 = judge.start(x0)
    go = jnp.asarray(GO, jnp.int64)
    history0 = anderson.start(x0, depth, core) if mixing else None
    start = (x0, x0, k0, res0, size0, go, jnp.asarray(0.0, jnp.float64), history0)
    _, g, k, _, _, code, r, _ = lax.while_loop(lambda c: c[5] == GO, body, start)
    return g, k, r, code


def _newton(problem: ImplicitProblem, it: Iteration) -> tuple[Traced, Traced, Traced, Traced]:
    """One traced solve by :class:`~lieflow.solvers.Newton`'s iteration (its
    :meth:`~lieflow.solvers.Newton.solve`, with the loops of the line search and of GMRES
    traced too): ``(x, linear solves, last relative residual, code)``."""
    import jax.numpy as jnp
    from jax import lax

    newton: Newton = it.solver
    core = problem.core_ndim
    x0 = problem.x0
    judge = _Judge.of(newton.rule, x0, core)
    m_real = real_size(x0, core)
    dense = newton.linear == "dense" or (newton.linear == "auto" and m_real <= newton.dense_max)
    trials = max(newton.max_halvings, 1)

    def checked(x: Traced, Fx: Traced, res: Traced, size0: Traced, k: Traced) -> tuple:
        res, size0, code, r = judge(Fx, x, res, size0, k)
        # below the roundoff floor and no longer converging quadratically: at roundoff
        previous = res[jnp.maximum(k - 1, 0)]
        flat = (code == GO) & (k >= 1) & (judge.floor >= r) & (r >= 0.5 * previous)
        return res, size0, jnp.where(flat, ROUNDOFF, code), r

    def body(carry: tuple[Any, ...]) -> tuple[Any, ...]:
        x, Fx, k, res, size0, _, r = carry
        rhs = Fx - x
        if dense:
            d = dense_direction(problem, x, rhs)
        else:  # forcing term min(0.1, ||R||): quadratic convergence is kept
            forcing = jnp.maximum(jnp.minimum(0.1, r), 1e-15)
            d = gmres_direction(problem, x, rhs, forcing=forcing, while_loop=lax.while_loop)
        xn, Fn, descent = line_search(
            problem, x, d, total_norm(rhs), trials=trials, while_loop=lax.while_loop
        )

        def frozen(_: Any) -> tuple[Traced, Traced]:  # outside Newton's basin: one frozen step
            y = problem.frozen_map(x)
            return y, problem.map(y)

        x, Fx = lax.cond(descent, lambda _: (xn, Fn), frozen, None)
        res, size0, code, r = checked(x, Fx, res, size0, k)
        return x, Fx, k + 1, res, size0, code, r

    res0, size0, k0 = judge.start(x0)
    F0 = problem.map(x0)
    res0, size0, code0, r0 = checked(x0, F0, res0, size0, k0)
    start = (x0, F0, k0 + 1, res0, size0, code0, r0)
    _, Fx, k, _, _, code, r = lax.while_loop(lambda c: c[5] == GO, body, start)
    return Fx, k - 1, r, code


def _solve(problem: ImplicitProblem, it: Iteration) -> tuple[Traced, Traced, Traced, Traced]:
    return _newton(problem, it) if it.kind == "newton" else _fixed_point(problem, it)


def ok(code: Traced) -> Traced:
    """Whether a verdict code accepts the solve (converged, or at roundoff)."""
    return (code == CONVERGED) | (code == ROUNDOFF)


class TracedSolver:
    """The solver a traced step calls: ``solver``'s iteration as a traced loop.

    Every solve appends ``(accepted, solver index)`` to :attr:`verdicts` (traced booleans
    and integers: the engine reads them after the step) and returns a
    :class:`~lieflow.solvers.SolveResult` marked converged, so that the scheme's step goes
    on (a scheme retries or raises only on the eager engine). ``names`` are the names a
    step's solver index refers to (``Auto``: its first solver's, then its fallback's)."""

    def __init__(self, solver: Solver) -> None:
        self.solver = solver
        self.name = str(solver.name)
        self.verdicts: list[tuple[Traced, Traced]] = []
        if isinstance(solver, Auto):
            first, fallback = _iteration(solver.first), _iteration(solver.fallback)
            assert first is not None and fallback is not None
            self._chain: tuple[Iteration, ...] = (first, fallback)
        else:
            single = _iteration(solver)
            assert single is not None
            self._chain = (single,)
        self.names = tuple(it.name for it in self._chain)

    def solve(self, problem: ImplicitProblem) -> SolveResult:
        """Solve ``problem`` with the first iteration of the chain; where it fails, with
        the next one from the same guess (``Auto``), its updates counted too."""
        import jax.numpy as jnp
        from jax import lax

        first = self._chain[0]
        x, k, r, code = _solve(problem, first)
        which = jnp.asarray(0, jnp.int64)
        for index, it in enumerate(self._chain[1:], start=1):

            def again(
                carry: tuple[Any, ...], it: Iteration = it, index: int = index
            ) -> tuple[Any, ...]:
                x2, k2, r2, code2 = _solve(problem, it)
                return x2, carry[1] + k2, r2, code2, jnp.asarray(index, jnp.int64)

            x, k, r, code, which = lax.cond(
                ok(code), lambda carry: carry, again, (x, k, r, code, which)
            )
        self.verdicts.append((ok(code), which))
        return SolveResult(x, True, k, (r,), "converged", self.names[0])  # traced values
