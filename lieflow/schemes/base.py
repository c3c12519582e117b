"""The :class:`Scheme` interface and helpers shared by the built-in schemes."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

import attrs
import numpy as np

from ..algebras import Array, minus_dagger, skew_combination, transpose
from ..backends import is_numpy, namespace
from ..errors import ConvergenceError
from ..solvers.base import ImplicitProblem, Solver, SolveResult, einsum
from ..steps import StepStats
from ..systems.base import IsospectralSystem
from ..tableaus import ButcherTableau, gauss, one_of
from ..underflow import flush_tiny
from . import conjugation

P = TypeVar("P", bound=ImplicitProblem)

#: Up to this size ``n`` the maps of a single ``n×n`` problem form their products with
#: ``ndarray.dot`` into fresh arrays (per-call overhead outweighs arithmetic: the same
#: BLAS product as ``@`` on 2-D arrays, the same bits, a third of the time on 3×3); larger
#: ones write products into scratch (:func:`scratch`), as stacks do.
FRESH_PRODUCTS_MAX_N = 64


@attrs.frozen
class StepResult:
    """One step ``W0 -> W1`` of a scheme.

    Attributes
    ----------
    W : ndarray
        The new state ``W1``.
    warm : ndarray
        The solved unknowns as offsets from their ``h = 0`` values; passed back as ``warm``
        to the next step, it is that step's initial guess (a warm start, SPEC §5).
    stats : StepStats
        What the step cost: solver updates (summed over the sub-steps of a composition),
        the solver that finished it (the last sub-step's) and its last relative update.
    """

    W: Array = attrs.field(repr=False)
    warm: Array = attrs.field(repr=False)
    stats: StepStats


class Scheme(ABC):
    """An ISOSyRK scheme: one step ``W0 -> W1`` for any system, step size and solver.

    A scheme states its implicit equation as an :class:`~lieflow.solvers.ImplicitProblem`
    and lets the solver find it; it never raises for an unconverged solve silently: a failed
    solve raises :class:`~lieflow.errors.ConvergenceError`.
    """

    tableau: ButcherTableau

    @property
    def name(self) -> str:
        """The scheme's name (the tableau's by default)."""
        return self.tableau.name

    @property
    def order(self) -> int:
        """Classical order of accuracy."""
        return self.tableau.order

    @property
    def keeps_skew(self) -> bool:
        """Whether a step of a real skew algebra (so(n)) maps an exactly skew-symmetric
        ``W0`` (``W0^T = -W0`` bit for bit, a +0 diagonal: what so(n)'s projection returns)
        to an exactly skew ``W1`` in floating point, not only to roundoff (then a state
        already on so(n) need not be projected again:
        :meth:`SchemeFlow.step_from_phase_space
        <lieflow.flows.SchemeFlow.step_from_phase_space>`). ``False`` by default."""
        return False

    def compiled_form(self) -> tuple[str, Array, Array] | None:
        """How the compiled engine (:mod:`lieflow.engines.compiled`) can run this scheme, or
        ``None``
        (the default: numpy only).

        ``("sydirk", A, b)``: a composition of midpoint steps of sizes ``b_i h`` (SPEC §4.2);
        ``("reduced", A, b)``: the reduced stage form of the symplectic tableau ``(A, b)``
        (SPEC §4.5). A scheme returning one promises that its :meth:`step` is that method.
        """
        return None

    @abstractmethod
    def step(
        self,
        W0: Array,
        h: float,
        system: IsospectralSystem,
        solver: Solver,
        warm: Array | None = None,
    ) -> StepResult:
        """Advance ``W0`` by one step of size ``h`` of ``system``, solving with ``solver``
        from the initial guess ``warm`` (``None``: cold; :attr:`StepResult.warm` of the
        previous step: a warm start). ``W0`` may be a stack ``(..., n, n)``.

        The arguments come in the order of :meth:`Flow.step <lieflow.flows.Flow.step>`
        (``W, t, h, state``): the state, the step size (a scheme is autonomous: no ``t``),
        what the step runs on, and the carried state last."""


def solve(
    solver: Solver, build: Callable[[Array | None], P], warm: Array | None
) -> tuple[P, SolveResult]:
    """Solve the problem ``build(warm)``; if a warm-started solve fails, retry once from the
    cold guess ``build(None)`` (a previous step's solution is a poor guess when ``h`` is
    large). Iterations of both attempts are counted. Raises :class:`ConvergenceError` if
    the solve does not converge."""
    problem = build(warm)
    return retry(solver, build, warm, problem, solver.solve(problem))


def retries_cold(converged: bool, warm: bool) -> bool:
    """Whether a step's solve is tried again from the cold guess (SPEC §5): it failed, and
    it started from a warm guess (a previous step's solution is a poor guess when ``h`` is
    large). The iterations of both attempts count; a cold solve that fails fails the step.

    One source for both engines: :func:`retry` calls it, and the compiled loops
    (:mod:`lieflow.engines._compiled_loops`) compile it for a solver that is a fixed-point
    iteration alone
    (:class:`~lieflow.solvers.Auto` hands a failed solve to its next solver first, so its
    compiled solve hands the step to the numpy path instead); hence scalars only."""
    return warm and not converged


def retry(
    solver: Solver,
    build: Callable[[Array | None], P],
    warm: Array | None,
    problem: P,
    res: SolveResult,
) -> tuple[P, SolveResult]:
    """:func:`solve` after its first attempt: ``res`` of ``problem = build(warm)``. A scheme
    that builds and solves its problem itself (no ``build`` closure per stage and step)
    hands the result here when it did not converge."""
    if retries_cold(res.converged, warm is not None):
        problem, first = build(None), res
        res = solver.solve(problem)
        res = attrs.evolve(
            res,
            iterations=first.iterations + res.iterations,
            residuals=first.residuals + res.residuals,
        )
    if not res.converged:
        raise ConvergenceError(
            res.reason, solver=res.solver, iterations=res.iterations, residuals=res.residuals
        )
    return problem, res


class StageProblem:
    """What every stage problem holds — the system and ``W0`` — and the one place where
    stage values meet the system.

    Every evaluation of ``B`` by a scheme goes through :meth:`B` (and its linearization
    through :meth:`B_derivative`), and every step ends with :meth:`commutator_update`:
    stage values are first mapped by the system's linear
    :meth:`~lieflow.IsospectralSystem.project_stage` onto the span of its phase space (a
    no-op at the fixed point, so the scheme is unchanged; away from it, ``B`` is never
    evaluated off the phase space's span — e.g. on a non-symmetric matrix for the Toda
    lattice, whose ``B`` is a gradient only on symmetric ones).

    It is also where the system's underflow guard (:attr:`tau`, :mod:`lieflow.underflow`)
    meets the products: :meth:`B` guards the stage values and ``B``, the commutator update
    its operands, and the maps of the schemes guard their own operands through
    :meth:`guard`. Off (``tau = 0``, the default) nothing is called: the same bits as
    without it.
    """

    def __init__(self, system: IsospectralSystem, W0: Array) -> None:
        self.system = system
        self.W0 = W0
        #: the relative threshold of the underflow guard (0: off): the system's
        self.tau = float(system.underflow_guard)
        algebra = system.algebra
        self.skew = algebra.skew
        # how the maps compute, decided once per problem rather than per call: on NumPy
        # arrays (else another library, lieflow.backends), and on one small matrix (no
        # batch axes, at most FRESH_PRODUCTS_MAX_N square: products by ndarray.dot, no
        # scratch)
        self._host = host = type(W0) is np.ndarray or is_numpy(W0)
        self._small = host and W0.ndim == 2 and W0.shape[-1] <= FRESH_PRODUCTS_MAX_N
        # the system's maps, looked up once per problem rather than per iteration (the
        # default stage projection is the algebra's: called directly, one frame less)
        self._B = system.B
        default = type(system).project_stage is IsospectralSystem.project_stage
        self._project_stage = algebra.project if default else system.project_stage
        self._stage_B = system.stage_B

    def guard(self, X: Array, in_place: bool = False) -> Array:
        """``X`` through the underflow guard (:func:`lieflow.underflow.flush_tiny` with
        :attr:`tau`): entries below ``tau`` times their matrix's largest set to zero, before
        ``X`` enters a product. ``in_place``: ``X`` is a NumPy array the map owns (scratch)
        and may be overwritten. ``X`` itself when the guard is off."""
        return flush_tiny(X, self.tau, in_place) if self.tau else X

    def B(self, stages: Array) -> Array:
        """``B(P(W_i))`` for stage values ``W_i`` (any leading axes): the system's
        :meth:`~lieflow.IsospectralSystem.stage_B` (with the underflow guard on: of the
        guarded stage values, guarded)."""
        if self.tau:
            return self.guard(self._stage_B(self.guard(stages)))
        return self._stage_B(stages)

    def B_derivative(self, stages: Array, dstages: Array) -> Array:
        """The derivative of :meth:`B` at ``stages`` in the direction ``dstages``
        (``P`` is linear: ``DB(P W)[P dW]``)."""
        P = self._project_stage
        return self.system.B_derivative(P(stages), P(dstages))

    def commutator_update(self, stages: Array, hb: Array | float) -> Array:
        """``W1 = W0 + sum_i (h b_i) [B(W_i), W_i]`` with ``W_i = P(stages[..., i, :, :])``.

        One batched call of ``B``; for skew algebras ``W_i B_i = (B_i W_i)^†`` saves a
        product. The weights are cast to ``W0``'s real precision (single stays single).
        ``stages`` of ``W0``'s shape is one stage and ``hb`` its weight (a float): the
        midpoint rule's ``W0 + h [B(M), M]``, without a stage axis (the same values: a sum
        of one term ``h C`` is ``h C``).
        """
        # Few temporaries (a streamed run of a large system keeps ~20 states at most):
        # each is dropped as soon as it is used; W0 + (...) is evaluated as (...) += W0,
        # the same bits.
        W0 = self.W0
        one = stages.ndim == W0.ndim
        W = self._project_stage(stages)
        B = self._B(W)
        if self.tau:  # the underflow guard (lieflow.underflow) on the product's operands
            W, B = self.guard(W), self.guard(B)
        if self.skew:
            C = B.dot(W) if one and self._small else B @ W
            del W, B
            if one:  # W0 + h (C - C^†) in one pass (the same roundings as below)
                return skew_combination(C, real_scalar(float(hb), W0), W0)
            C = minus_dagger(C)
        else:
            C = B @ W - W @ B
            del W, B
        if one:
            # Exactly skew (Scheme.keeps_skew): for real W0 with W0^T = -W0 bit for bit
            # and a +0 diagonal, W1 = W0 + h (C - C^T) is exactly skew too, for any C and
            # h. Entry (i, j) of D = C - C^T is fl(c_ij - c_ji), entry (j, i) is
            # fl(c_ji - c_ij), its negative (round-to-nearest is symmetric:
            # fl(-x) = -fl(x)); the diagonal is c_ii - c_ii = +0. So entry (j, i) of
            # fl(h D) is -fl(h d_ij), and of W1 fl(-w_ij - fl(h d_ij)) = -fl(w_ij +
            # fl(h d_ij)); the diagonal is +0 + (+-0) = +0. The projection (W1 - W1^T)/2
            # returns W1 bit for bit: (w_ij + w_ij) * 0.5 is exact below 2^1023 (beyond,
            # it overflows to inf). Not so for the weighted sum of several stages below.
            C *= real_scalar(float(hb), W0)
            C += W0
            return C
        if not self._host:  # another array library: the weighted sum stage by stage
            terms = [float(w) * C[..., i, :, :] for i, w in enumerate(np.asarray(hb).tolist())]
            del C
            return sum(terms[1:], terms[0]) + W0
        weights = np.asarray(hb, dtype=W0.real.dtype)
        out = einsum("i,...iab->...ab", weights, C)
        del C
        out += W0
        return out


class TableauProblem(StageProblem, ABC):
    """What the stage equations of every tableau-based scheme hold: the system, ``W0``,
    ``h``, the coefficients ``A``, ``b`` and the warm start ``warm``.

    The coefficients are kept in ``W0``'s real precision and ``h`` as a Python float, so a
    single-precision state stays single (NumPy promotes ``complex64`` times a ``float64``
    array to ``complex128``).
    """

    def __init__(
        self,
        system: IsospectralSystem,
        W0: Array,
        h: float,
        tableau: ButcherTableau,
        warm: Array | None = None,
    ) -> None:
        super().__init__(system, W0)
        self.h = float(h)
        #: The previous step's :meth:`offsets` (a warm start), or ``None`` (cold).
        self.warm = warm
        # read-only here: no copy where the tableau's precision is W0's already; host
        # float64 for arrays of another library (placed on its device where a map needs it)
        real = W0.real.dtype if is_numpy(W0) else np.float64
        self.A = tableau.A.astype(real, copy=False)
        self.b = tableau.b.astype(real, copy=False)
        #: The number of stages.
        self.s = tableau.stages
        self._prepare()

    @abstractmethod
    def _prepare(self) -> None:
        """What the formulation derives once per step from the values above (its ``h = 0``
        guess, its coefficients); the end of :meth:`__init__`."""

    @abstractmethod
    def stages(self, x: Array) -> Array:
        """The stage values ``W_i`` of the unknown ``x``, shape ``(..., s, n, n)``."""

    def update(self, x: Array) -> Array:
        """``W1 = W0 + h sum_i b_i [B(W_i), W_i]`` with ``W_i`` the :meth:`stages` of ``x``:
        isospectral at the fixed point."""
        return self.commutator_update(self.stages(x), self.h * self.b)

    def conjugation_update(self, x: Array) -> Array:
        """``W1 = g1^† W0 g1^{-†}`` with the lifted ``G_i`` of the stages' ``B``
        (:func:`~lieflow.schemes.conjugation.frozen_stage_conjugator`): isospectral for any
        ``x`` (:func:`~lieflow.schemes.conjugation.lifted_update`)."""
        B = self.B(self.stages(x))
        Gdag = conjugation.frozen_stage_conjugator(B, self.A, self.h)
        return conjugation.lifted_update(self.W0, Gdag, B, self.h * self.b, self.skew)


def symplectic(tableau: ButcherTableau) -> ButcherTableau:
    """attrs converter: the tableau itself, after checking it is symplectic."""
    return tableau.require_symplectic()


class StageEquations(ImplicitProblem, Protocol):
    """What :class:`TableauScheme` asks of its stage equations: an implicit problem, and
    how its solution ``x`` gives ``W1`` and the next step's warm start."""

    def update(self, x: Array) -> Array:
        """``W1`` by the commutator update (:meth:`TableauProblem.update`)."""
        ...

    def conjugation_update(self, x: Array) -> Array:
        """``W1`` by a conjugation of ``W0`` (:meth:`TableauProblem.conjugation_update`)."""
        ...

    def offsets(self, x: Array) -> Array:
        """``x`` minus its value at ``h = 0``: what the next step's warm start adds to its
        own ``h = 0`` guess."""
        ...


def _gauss2() -> ButcherTableau:
    return gauss(2)


@attrs.frozen
class TableauScheme(Scheme):
    """A scheme whose step is one implicit solve for the stages of a symplectic tableau,
    then an update: :class:`~lieflow.schemes.BlockGauss` and
    :class:`~lieflow.schemes.ModinViviani`, which differ only in how they state the stage
    equations (:attr:`problem_class`).

    Parameters
    ----------
    tableau : ButcherTableau
        Any symplectic tableau (checked); Gauss–Legendre with 2 stages by default.
    update : {"commutator", "conjugation"}
        ``"commutator"`` (default): ``W1 = W0 + h sum_i b_i [B_i, W_i]``, isospectral at
        the fixed point; ``"conjugation"``: ``W1`` a conjugation of ``W0`` by the lifted
        ``g1`` made unitary, isospectral for any iterate (SPEC §4.7,
        :mod:`lieflow.schemes.conjugation`).
    """

    tableau: ButcherTableau = attrs.field(factory=_gauss2, converter=symplectic)
    update: str = attrs.field(
        default="commutator", validator=one_of(*conjugation.UPDATES), kw_only=True
    )

    @property
    @abstractmethod
    def problem_class(self) -> Callable[..., StageEquations]:
        """The stage equations, built as ``problem_class(system, W0, h, tableau, warm)``."""

    def step(
        self,
        W0: Array,
        h: float,
        system: IsospectralSystem,
        solver: Solver,
        warm: Array | None = None,
    ) -> StepResult:
        cls = self.problem_class
        problem, res = solve(solver, lambda guess: cls(system, W0, h, self.tableau, guess), warm)
        update = problem.update if self.update == "commutator" else problem.conjugation_update
        return StepResult(
            update(res.x),
            problem.offsets(res.x),
            StepStats(res.iterations, res.solver, res.residuals[-1]),
        )


def solve_right(rhs: Array, mat: Array) -> Array:
    """``rhs mat^{-1}`` (batched), as a solve with the transposed matrix; arrays of any
    library (``linalg.solve`` of the array's namespace)."""
    if is_numpy(mat):
        return np.swapaxes(
            np.linalg.solve(np.swapaxes(mat, -1, -2), np.swapaxes(rhs, -1, -2)), -1, -2
        )
    return transpose(namespace(mat).linalg.solve(transpose(mat), transpose(rhs)))


def contract(coef: np.ndarray, X: Array, axis: int) -> Array:
    """``Y[..., i, ...] = sum_k coef[i, k] X[..., k, ...]`` along the (negative) ``axis`` of
    ``X``: a host matrix of a tableau's coefficients applied to a stack of stage matrices
    (``numpy.einsum("ik,...k...->...i...")``), in ``X``'s library, as sums of Python-float
    multiples (the coefficients are constants of the tableau: they never become arrays of
    ``X``'s library, and a single-precision ``X`` stays single)."""
    xp = namespace(X)
    tail = (slice(None),) * (-axis - 1)
    indices: list[Any] = [(Ellipsis, k, *tail) for k in range(coef.shape[1])]
    parts = [X[index] for index in indices]
    rows = []
    for row in coef.tolist():
        terms = [c * part for c, part in zip(row, parts, strict=True)]
        rows.append(sum(terms[1:], terms[0]))
    return xp.stack(rows, axis=axis)


def scratch(held: Array | None, count: int, shape: tuple[int, ...], dtype: Any) -> Array:
    """``count`` scratch arrays of ``shape`` and ``dtype``, as one ``(count, *shape)`` array:
    ``held`` if it is that, else a new one. A stage problem keeps its scratch for its step,
    so that its iterations write their products into the same memory (at large ``n`` fresh
    temporaries cost page faults and cache misses comparable to the products); scratch never
    leaves the problem, whose maps return new arrays."""
    if held is None or held.shape != (count, *shape) or held.dtype != dtype:
        held = np.empty((count, *shape), dtype=dtype)
    return held


def real_scalar(value: float, like: Array) -> Any:
    """``value`` as a 0-d array of ``like``'s real precision, for in-place products with
    arrays like ``like``: the result NumPy gives for the Python float (which it rounds to
    that precision), in about half the time for small arrays. The float itself for
    non-floating ``like``."""
    if type(like) is np.ndarray and like.dtype.char == "d":  # float64 first (3 a step)
        return np.array(value)
    if not is_numpy(like):
        return value
    dtype = like.dtype
    if dtype.kind == "c":
        dtype = like.real.dtype
    elif dtype.kind != "f":
        return value
    return np.array(value, dtype=dtype)
