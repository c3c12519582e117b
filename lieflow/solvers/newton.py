"""Newton's method on ``R(x) = x - F(x)`` and the fixed-point-then-Newton fallback."""

from __future__ import annotations

import math

import attrs
import numpy as np

from ..algebras import Array
from ..errors import InputError
from . import arguments
from .base import ImplicitProblem, Solver, SolveResult, batch_norm
from .fixed_point import _EPS, FixedPoint, IterationMonitor, StoppingRule


def _to_real(x: Array, core_ndim: int) -> np.ndarray:
    """``(batch..., core...)`` -> ``(batch_size, m)`` real; complex as [Re, Im]."""
    core_size = math.prod(x.shape[x.ndim - core_ndim :])
    flat = x.reshape(-1, core_size)
    return np.concatenate([flat.real, flat.imag], axis=1) if np.iscomplexobj(x) else flat


def _from_real(v: np.ndarray, like: Array, core_ndim: int) -> Array:
    if np.iscomplexobj(like):
        half = v.shape[1] // 2
        v = v[:, :half] + 1j * v[:, half:]
    return v.reshape(like.shape).astype(like.dtype, copy=False)


@attrs.frozen
class Newton:
    """Newton's method for the scheme's equation ``R(x) = x - F(x) = 0`` (SPEC §5).

    Each iteration solves ``(I - F'(x)) d = F(x) - x`` with the exact Fréchet derivative
    supplied by the scheme (which uses the system's ``B_derivative``) and sets ``x <- x + d``.
    The linear system is assembled densely and solved directly when a problem has at most
    ``dense_max`` real unknowns, and solved matrix-free with GMRES otherwise
    (``linear="dense"`` / ``"gmres"`` override the choice). GMRES uses the forcing term
    ``min(0.1, ||R||)`` so that convergence stays quadratic. Complex unknowns are treated as
    pairs of reals, so ``F`` need only be real-differentiable.

    Globalised by backtracking: a step that does not decrease ``||R||`` is halved (at most
    ``max_halvings`` times), which makes Newton converge from the cold guess at step sizes
    where the plain iteration wanders; if no halving decreases ``||R||`` (the guess is
    outside Newton's basin), one frozen-B step (``problem.frozen_map``) is taken instead
    and Newton resumes from there. Stops when ``||R(x)|| <= atol + rtol ||x||``, or as
    ``"roundoff"`` once ``||R||`` is below the roundoff floor (scaled to the iterate's
    precision) and falls by less than half in an iteration (no longer quadratic: roundoff),
    returning ``F(x)``; ``iterations`` counts linear solves. Stagnation and divergence
    are detected as in :class:`StoppingRule`.
    """

    # the stopping rule's arguments are validated by StoppingRule (built in __init__)
    rtol: float = 1e-14
    atol: float = 0.0
    max_iter: int = 30
    linear: str = attrs.field(default="auto", kw_only=True)
    dense_max: int = attrs.field(default=800, kw_only=True, validator=arguments.integer_at_least(1))
    patience: int = attrs.field(default=8, kw_only=True)
    max_halvings: int = attrs.field(
        default=8, kw_only=True, validator=arguments.integer_at_least(0)
    )
    roundoff_floor: float = attrs.field(default=256 * _EPS, kw_only=True)

    name = "newton"

    rule: StoppingRule = attrs.field(init=False, repr=False, eq=False)

    @rule.default
    def _rule(self) -> StoppingRule:
        return StoppingRule(
            self.rtol,
            self.atol,
            self.max_iter,
            self.patience,
            self.roundoff_floor,
            1e6,
            project=False,
        )

    def __attrs_post_init__(self) -> None:
        if self.linear not in ("auto", "dense", "gmres"):
            raise InputError(f"linear must be 'auto', 'dense' or 'gmres', got {self.linear!r}")

    def solve(self, problem: ImplicitProblem) -> SolveResult:
        """Newton iteration from ``problem.x0``."""
        core = problem.core_ndim
        x = problem.x0
        monitor = IterationMonitor(self.rule, core, x)
        m_real = _to_real(x, core).shape[1]
        dense = self.linear == "dense" or (self.linear == "auto" and m_real <= self.dense_max)
        Fx = problem.map(x)
        floor = monitor.rule.roundoff_floor  # scaled to the iterate's precision
        while True:
            reason = monitor.check(Fx, x)
            res = monitor.residuals
            if reason is None and len(res) > 1 and floor >= res[-1] >= 0.5 * res[-2]:
                # below the roundoff floor and no longer converging quadratically: Newton is
                # at roundoff (complex64 otherwise wanders 8 -> 29 iterations on the noise)
                reason = "roundoff"
            if reason is not None:
                ok = reason in ("converged", "roundoff")
                res = monitor.residuals
                return SolveResult(Fx if ok else x, ok, len(res) - 1, tuple(res), reason, self.name)
            rel = monitor.residuals[-1]
            rhs = Fx - x
            d = (
                self._dense_step(problem, x, rhs, core)
                if dense
                else self._gmres_step(problem, x, rhs, core, rel)
            )
            x, Fx, descent = self._line_search(problem, x, d, float(batch_norm(rhs, rhs.ndim)))
            if not descent:
                # Newton's direction does not decrease ||F(x) - x|| at all: x is outside
                # its basin (Toda, paper W0, sydirk7 at h = 0.8: the sub-step of 1.05 from
                # the cold guess). One frozen-B step (a contraction where the plain map is
                # not) moves x on; Newton resumes from there.
                x = problem.frozen_map(x)
                Fx = problem.map(x)

    def _line_search(
        self, problem: ImplicitProblem, x: Array, d: Array, merit: float
    ) -> tuple[Array, Array, bool]:
        """Backtracking on ``||F(x) - x||``: the full step if it decreases the residual
        (always, near the solution: quadratic convergence is kept), else halve it up to
        ``max_halvings`` times. Returns the new iterate, its map value and whether the
        residual decreased."""
        lam = 1.0
        for _ in range(self.max_halvings):
            xn = x + lam * d
            Fn = problem.map(xn)
            with np.errstate(invalid="ignore", over="ignore"):
                trial = float(batch_norm(Fn - xn, Fn.ndim))
            if trial <= (1.0 - 1e-4 * lam) * merit:
                return xn, Fn, True
            lam *= 0.5
        return xn, Fn, False

    @staticmethod
    def _dense_step(problem: ImplicitProblem, x: Array, rhs: Array, core: int) -> Array:
        """Assemble ``I - F'(x)`` column by column (all batch members at once) and solve."""
        r = _to_real(rhs, core)
        batch, m = r.shape
        J = np.empty((batch, m, m))
        e = np.zeros((batch, m))
        for k in range(m):
            e[:, k] = 1.0
            J[:, :, k] = -_to_real(problem.map_derivative(x, _from_real(e, x, core)), core)
            e[:, k] = 0.0
        J[:, np.arange(m), np.arange(m)] += 1.0
        d = np.linalg.solve(J, r[..., None])[..., 0]
        return _from_real(d, x, core)

    @staticmethod
    def _gmres_step(problem: ImplicitProblem, x: Array, rhs: Array, core: int, rel: float) -> Array:
        """Matrix-free GMRES on ``(I - F'(x)) d = rhs`` for the whole batch at once."""
        import scipy.sparse.linalg as spla  # 0.1 s to import: on first use

        r = _to_real(rhs, core)
        shape = r.shape

        def apply(v: np.ndarray) -> np.ndarray:
            dv = _from_real(v.reshape(shape), x, core)
            return v - _to_real(problem.map_derivative(x, dv), core).ravel()

        op = spla.LinearOperator((r.size, r.size), matvec=apply, dtype=float)
        tol = max(min(0.1, rel), 1e-15)
        d, _info = spla.gmres(op, r.ravel(), rtol=tol, atol=0.0, restart=50, maxiter=20)
        return _from_real(d.reshape(shape), x, core)


@attrs.frozen
class Auto:
    """Fixed-point iteration first; if it stalls or diverges, Newton from the same guess.

    The :class:`SolveResult` names the solver that finished the step, and ``iterations``
    counts the updates of both.
    """

    first: Solver = attrs.field(factory=FixedPoint, validator=arguments.solver)
    fallback: Solver = attrs.field(factory=Newton, validator=arguments.solver)

    name = "auto"

    def solve(self, problem: ImplicitProblem) -> SolveResult:
        """Solve with ``first``; on failure, solve again with ``fallback``."""
        res = self.first.solve(problem)
        if res.converged:
            return res
        res2 = self.fallback.solve(problem)
        return attrs.evolve(
            res2,
            iterations=res.iterations + res2.iterations,
            residuals=res.residuals + res2.residuals,
        )


__all__ = ["Auto", "Newton"]
