"""Newton's method on ``R(x) = x - F(x)`` and the fixed-point-then-Newton fallback."""

from __future__ import annotations

import math
from typing import Any

import attrs
import numpy as np

from ..algebras import Array
from ..backends import device_norms, device_of, identity, is_numpy, namespace
from ..errors import InputError
from . import arguments
from .base import ImplicitProblem, Solver, SolveResult, batch_norm
from .fixed_point import _EPS, FixedPoint, IterationMonitor, StoppingRule
from .krylov import WhileLoop, gmres, host_while_loop

#: GMRES's restart length and its most restart cycles in a Newton step.
GMRES_RESTART = 50
GMRES_CYCLES = 20


def real_size(x: Array, core_ndim: int) -> int:
    """How many real unknowns one problem of ``x`` has (complex entries count twice)."""
    size = math.prod(x.shape[x.ndim - core_ndim :])
    if is_numpy(x):
        return 2 * size if np.iscomplexobj(x) else size
    return 2 * size if namespace(x).isdtype(x.dtype, "complex floating") else size


def to_real(x: Array, core_ndim: int) -> Array:
    """``(batch..., core...)`` -> ``(batch_size, m)`` real; complex as [Re, Im] (arrays of
    any library)."""
    if is_numpy(x):
        core_size = math.prod(x.shape[x.ndim - core_ndim :])
        flat = x.reshape(-1, core_size)
        return np.concatenate([flat.real, flat.imag], axis=1) if np.iscomplexobj(x) else flat
    xp = namespace(x)
    core_size = math.prod(x.shape[x.ndim - core_ndim :])
    flat = xp.reshape(x, (-1, core_size))
    if not xp.isdtype(x.dtype, "complex floating"):
        return flat
    return xp.reshape(xp.stack([xp.real(flat), xp.imag(flat)], axis=1), (-1, 2 * core_size))


def from_real(v: Array, shape: tuple[int, ...], dtype: Any) -> Array:
    """Inverse of :func:`to_real`: rows ``v`` of real unknowns as an array of ``shape`` and
    the (real or complex) ``dtype`` of the unknowns."""
    if is_numpy(v):
        if np.dtype(dtype).kind == "c":
            half = v.shape[1] // 2
            v = v[:, :half] + 1j * v[:, half:]
        return v.reshape(shape).astype(dtype, copy=False)
    xp = namespace(v)
    if xp.isdtype(dtype, "complex floating"):
        half = v.shape[1] // 2
        v = xp.astype(v[:, :half], dtype) + xp.astype(v[:, half:], dtype) * 1j
    return xp.reshape(v, shape)


def dense_direction(problem: ImplicitProblem, x: Array, rhs: Array) -> Array:
    """Newton's direction ``d`` with ``(I - F'(x)) d = rhs``, the matrix assembled densely:
    its ``m`` columns (``m`` real unknowns per problem, a static count) by one call of
    ``problem.map_derivative`` on ``m`` unit directions stacked on a new leading axis (``x``
    broadcast along it), then one batched ``linalg.solve``. Arrays of any library; no value
    is read on the host (traceable)."""
    core = problem.core_ndim
    xp = namespace(x)
    r = to_real(rhs, core)
    batch, m = r.shape
    eye = identity(m, r)
    units = xp.reshape(xp.broadcast_to(eye[:, None, :], (m, batch, m)), (m * batch, m))
    stacked = (m, *x.shape)
    dx = from_real(units, stacked, x.dtype)
    columns = to_real(problem.map_derivative(xp.broadcast_to(x, stacked), dx), core)
    J = eye - xp.moveaxis(xp.reshape(columns, (m, batch, m)), 0, -1)  # [b, i, k]
    d = xp.linalg.solve(J, r[..., None])[..., 0]
    return from_real(d, x.shape, x.dtype)


def gmres_direction(
    problem: ImplicitProblem,
    x: Array,
    rhs: Array,
    *,
    forcing: Any,
    restart: int = GMRES_RESTART,
    cycles: int = GMRES_CYCLES,
    while_loop: WhileLoop = host_while_loop,
) -> Array:
    """Newton's direction ``d`` with ``(I - F'(x)) d = rhs`` by matrix-free GMRES
    (:func:`~lieflow.solvers.krylov.gmres`, relative tolerance ``forcing``) on the whole
    batch as one real system. Traceable with ``while_loop=jax.lax.while_loop``."""
    core = problem.core_ndim
    xp = namespace(x)
    r = to_real(rhs, core)
    shape = r.shape

    def apply(v: Array) -> Array:
        dv = from_real(xp.reshape(v, shape), x.shape, x.dtype)
        return v - xp.reshape(to_real(problem.map_derivative(x, dv), core), (-1,))

    d = gmres(
        apply, xp.reshape(r, (-1,)), rtol=forcing, restart=restart, cycles=cycles,
        while_loop=while_loop,
    )  # fmt: skip
    return from_real(xp.reshape(d, shape), x.shape, x.dtype)


def line_search(
    problem: ImplicitProblem,
    x: Array,
    d: Array,
    merit: Any,
    *,
    trials: int,
    while_loop: WhileLoop = host_while_loop,
) -> tuple[Array, Array, Any]:
    """Backtracking on ``||F(x) - x||`` (the whole batch's norm): the step ``x + λ d`` for
    ``λ = 1, 1/2, ...`` (at most ``trials`` of them) until the residual falls below
    ``(1 - 1e-4 λ) merit`` (Armijo's condition, ``merit = ||F(x) - x||``). Returns the last
    trial, its map value and whether it was accepted (a 0-d boolean array). Arrays of any
    library; traceable with ``while_loop=jax.lax.while_loop``."""
    xp = namespace(x)
    real = xp.finfo(x.dtype).dtype  # λ in x's real precision: a float32 x stays float32
    one = np.ones((), dtype=real) if is_numpy(x) else xp.ones((), dtype=real, device=device_of(x))

    def searching(state: tuple[Any, ...]) -> Any:
        k, _lam, _xn, _Fn, accepted = state
        return (k < trials) & ~accepted

    def trial(state: tuple[Any, ...]) -> tuple[Any, ...]:
        k, lam, _xn, _Fn, _accepted = state
        xn = x + lam * d
        Fn = problem.map(xn)
        with np.errstate(invalid="ignore", over="ignore"):  # NumPy's warnings only
            accepted = total_norm(Fn - xn) <= (1.0 - 1e-4 * lam) * merit
        return k + 1, xp.where(accepted, lam, 0.5 * lam), xn, Fn, accepted

    _k, _lam, xn, Fn, accepted = while_loop(searching, trial, (0, one, x, x, one < 0))
    return xn, Fn, accepted


def total_norm(x: Array) -> Any:
    """Frobenius norm of the whole array: a NumPy scalar (the plain sum of squares of
    :func:`~lieflow.solvers.base.batch_norm`) or a 0-d array of ``x``'s library."""
    if is_numpy(x):
        return batch_norm(x, x.ndim)
    return device_norms(x, x.ndim)


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
        return StoppingRule.of(self, 1e6, project=False)

    def __attrs_post_init__(self) -> None:
        if self.linear not in ("auto", "dense", "gmres"):
            raise InputError(f"linear must be 'auto', 'dense' or 'gmres', got {self.linear!r}")

    def solve(self, problem: ImplicitProblem) -> SolveResult:
        """Newton iteration from ``problem.x0``: the loop on the host, each iteration's
        linear algebra (:func:`dense_direction` or :func:`gmres_direction`, then
        :func:`line_search`) in the unknowns' own library."""
        core = problem.core_ndim
        x = problem.x0
        monitor = IterationMonitor(self.rule, core, x)
        m_real = real_size(x, core)
        dense = self.linear == "dense" or (self.linear == "auto" and m_real <= self.dense_max)
        Fx = problem.map(x)
        floor = monitor.rule.roundoff_floor  # scaled to the iterate's precision
        trials = max(self.max_halvings, 1)
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
            rhs = Fx - x
            if dense:
                d = dense_direction(problem, x, rhs)
            else:  # forcing term min(0.1, ||R||): quadratic convergence is kept
                forcing = max(min(0.1, monitor.residuals[-1]), 1e-15)
                d = gmres_direction(problem, x, rhs, forcing=forcing)
            x, Fx, descent = line_search(problem, x, d, total_norm(rhs), trials=trials)
            if not bool(descent):
                # Newton's direction does not decrease ||F(x) - x|| at all: x is outside
                # its basin (Toda, paper W0, sydirk7 at h = 0.8: the sub-step of 1.05 from
                # the cold guess). One frozen-B step (a contraction where the plain map is
                # not) moves x on; Newton resumes from there.
                x = problem.frozen_map(x)
                Fx = problem.map(x)


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
