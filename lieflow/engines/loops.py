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
from ..solvers.newton import Auto

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
    """How one traced solve iterates: the map to iterate (``"map"`` or ``"frozen_map"`` of
    the problem) and the stopping rule, with the solver's name."""

    name: str
    map_name: str
    rule: StoppingRule


def _iteration(solver: Solver) -> Iteration | None:
    """The traced iteration of a plain fixed-point solver (or its frozen-B form)."""
    if type(solver).solve is not FixedPoint.solve or getattr(solver, "anderson", False):
        return None
    if isinstance(solver, FrozenB) and type(solver)._map is FrozenB._map:
        return Iteration(solver.name, "frozen_map", solver.rule)
    if isinstance(solver, FixedPoint) and type(solver)._map is FixedPoint._map:
        return Iteration(solver.name, "map", solver.rule)
    return None


def supported(solver: Solver) -> str | None:
    """``None`` if a traced engine runs ``solver``, else the reason it does not."""
    if isinstance(solver, Auto) and type(solver).solve is Auto.solve:
        return supported(solver.first) or supported(solver.fallback)
    if _iteration(solver) is None:
        return (
            f"solver {getattr(solver, 'name', type(solver).__name__)!r} has no traced form "
            "(FixedPoint, FrozenB, and Auto of them)"
        )
    return None


def _fixed_point(problem: ImplicitProblem, it: Iteration) -> tuple[Traced, Traced, Traced, Traced]:
    """One traced solve: ``(x, iterations, last relative update, verdict code)``."""
    import jax.numpy as jnp
    from jax import lax

    F: Callable[[Traced], Traced] = getattr(problem, it.map_name)
    rule = it.rule
    x0 = problem.x0
    core = problem.core_ndim
    eps = float(jnp.finfo(x0.dtype).eps)
    floor = rule.roundoff_floor * max(eps / _EPS, 1.0)
    tiny = float(np.finfo(float).tiny)
    res0 = jnp.full((rule.max_iter,), jnp.inf, dtype=jnp.float64)
    quiet = min(rule.patience, rule.window, rule.max_iter - 1)
    norm0 = _norms(x0, core).astype(jnp.float64)

    def body(carry: tuple[Any, ...]) -> tuple[Any, ...]:
        x, _, k, res, size0, _ = carry
        g = F(x)
        step = _norms(g - x, core).astype(jnp.float64)
        size = _norms(g, core).astype(jnp.float64)
        size0 = jnp.where(k == 0, jnp.maximum(jnp.maximum(size0, size), tiny), size0)
        finite = jnp.all(jnp.isfinite(step)) & jnp.all(jnp.isfinite(size))
        r = jnp.max(step / jnp.maximum(size, tiny))
        res = res.at[k].set(jnp.where(finite, r, jnp.nan))
        met = jnp.all(step <= rule.atol + rule.rtol * size)
        growth = jnp.max(size / size0)
        # the scalar rule's two shortcuts (lean_check): a met tolerance converges; an unmet,
        # finite, bounded update within the first ``quiet`` goes on — the whole rule only
        # otherwise
        plain = finite & (met | ((k + 1 <= quiet) & (growth <= rule.divergence_factor)))
        code = lax.cond(
            plain,
            lambda: jnp.where(met, CONVERGED, GO).astype(jnp.int64),
            lambda: verdict(rule, floor, res, k + 1, met, growth).astype(jnp.int64),
        )
        return g, g, k + 1, res, size0, code

    start = (x0, x0, jnp.asarray(0, jnp.int64), res0, norm0, jnp.asarray(GO, jnp.int64))
    _, g, k, res, _, code = lax.while_loop(lambda c: c[5] == GO, body, start)
    return g, k, res[k - 1], code


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
        x, k, r, code = _fixed_point(problem, first)
        which = jnp.asarray(0, jnp.int64)
        for index, it in enumerate(self._chain[1:], start=1):

            def again(
                carry: tuple[Any, ...], it: Iteration = it, index: int = index
            ) -> tuple[Any, ...]:
                x2, k2, r2, code2 = _fixed_point(problem, it)
                return x2, carry[1] + k2, r2, code2, jnp.asarray(index, jnp.int64)

            x, k, r, code, which = lax.cond(
                ok(code), lambda carry: carry, again, (x, k, r, code, which)
            )
        self.verdicts.append((ok(code), which))
        return SolveResult(x, True, k, (r,), "converged", self.names[0])  # traced values
