"""The implicit midpoint rule in minimal-variable form and its compositions (ISOSyDIRK)."""

from __future__ import annotations

from typing import Any

import attrs
import numpy as np

from ..algebras import Array, skew_combination, skew_combination_norms, skew_matmul
from ..backends import copy, identity, is_numpy, namespace
from ..errors import TableauError
from ..solvers.base import Solver
from ..steps import StepStats
from ..systems.base import IsospectralSystem
from ..tableaus import ButcherTableau, midpoint, one_of
from . import conjugation
from .base import (
    Scheme,
    StageProblem,
    StepResult,
    real_scalar,
    retry,
    scratch,
    solve_right,
)


def midpoint_coefficients(h: float) -> tuple[float, float]:
    """The coefficients ``q = h/2`` and ``q^2`` of the midpoint map (SPEC §4.1), and ``q``
    the Cayley update's ``a`` (SPEC §4.7), for a (sub-)step of size ``h``. One derivation
    for both engines: :class:`MidpointProblem` and the compiled engine's plan
    (:mod:`lieflow.engines.compiled`), which hands them to its loops."""
    q = 0.5 * h
    return q, q * q


class MidpointProblem(StageProblem):
    r"""The midpoint equation in minimal-variable form (SPEC §4.1).

    Solve :math:`W_0 = (I - \tfrac h2 B(M))\, M\, (I + \tfrac h2 B(M))` for ``M`` by

    .. math:: M \leftarrow W_0 + \tfrac h2 (BM - MB) + \tfrac{h^2}{4} BMB,\qquad B = B(M),

    two matrix products per iteration for skew algebras (``MB = (BM)^†``; the second,
    ``BMB``, skew-Hermitian, from its upper block triangle for large NumPy matrices:
    :func:`~lieflow.algebras.skew_matmul`), three otherwise.
    The step is :math:`W_1 = W_0 + h[B(M), M]`.
    """

    core_ndim = 2

    def __init__(
        self, system: IsospectralSystem, W0: Array, h: float, warm: Array | None = None
    ) -> None:
        super().__init__(system, W0)
        q, qq = midpoint_coefficients(float(h))
        self.half = q
        self.warm = warm
        # q and q^2 as 0-d arrays of W0's real precision: the values a Python float gives
        # (NumPy rounds it to that precision too) at half the cost of a multiplication
        # (float64 NumPy, once per step: real_scalar's own first case, inline)
        if self._host and W0.dtype.char == "d":
            self._q, self._qq = np.array(q), np.array(qq)
        else:
            self._q, self._qq = real_scalar(q, W0), real_scalar(qq, W0)
        self._scratch: Array | None = None

    @property
    def skew_unknowns(self) -> bool:
        """Whether the unknown ``M`` is skew-Hermitian (skew-symmetric if real) up to
        roundoff: for skew algebras, whose ``W0`` and ``BM - (BM)^†`` are, and ``BMB``
        is up to the rounding of its products. What lets Anderson acceleration read the
        upper triangles alone (:func:`lieflow.solvers.anderson.update`)."""
        return self.skew

    @property
    def x0(self) -> Array:
        """``W0 + warm`` (cold: ``W0``), a new array on each access: the solver reads it
        once, and no copy outlives the first update."""
        return self.W0 + self.warm if self.warm is not None else copy(self.W0)

    def map(self, M: Array) -> Array:
        return self._map(M, False)[0]

    def map_with_norms(self, M: Array) -> tuple[Array, tuple[float, float] | None]:
        """``(F(M), norms)``: :meth:`map` (the same bits) and, where the map's last pass
        computes them (:func:`~lieflow.algebras.skew_combination_norms`), the squared
        norms ``(||F(M)||², ||F(M) - M||²)`` that a fixed-point update's stopping test
        reads (:func:`lieflow.solvers.fixed_point.lean_check`); else ``None``."""
        return self._map(M, True)

    def _map(self, M: Array, norms: bool) -> tuple[Array, tuple[float, float] | None]:
        # W0 + q (BM - MB) + q^2 BMB with the same roundings (``x += y`` is ``y + x``).
        # One small NumPy matrix: ``ndarray.dot`` (the BLAS product ``@`` calls, without the
        # ufunc machinery: 3×3 0.9 -> 0.34 µs); larger ones and stacks write the products
        # into two scratch matrices kept for the step (:func:`scratch`), so an iteration
        # allocates only B and its result; for skew algebras BMB is skew-Hermitian and
        # formed from its upper triangle (skew_matmul: 0.7x a product from n = 192 on, its
        # mirrored entries the exact -conj of the computed ones, which differ from the
        # product's own roundings at roundoff). Arrays of another library
        # (lieflow.backends): the same operations on fresh arrays. B is :meth:`B`, the
        # system's stage_B called directly (one Python frame less per update).
        guard = self.tau  # the underflow guard (lieflow.underflow): M, B and BM before products
        iterate = M
        if guard:
            M = self.guard(M)
            B = self.guard(self._stage_B(M))
        else:
            B = self._stage_B(M)
        if self._small:
            BM = B.dot(M)
            if guard:
                BM = self.guard(BM, in_place=True)
            BMB = BM.dot(B)
        elif self._host:
            BM, BMB = self._scratch = scratch(self._scratch, 2, M.shape, np.result_type(B, M))
            np.matmul(B, M, out=BM)
            if guard:
                self.guard(BM, in_place=True)
            if self.skew:  # BMB is skew-Hermitian: its upper triangle (skew_matmul)
                skew_matmul(BM, B, BMB)
            else:
                np.matmul(BM, B, out=BMB)
        else:
            BM = B @ M
            if guard:
                BM = self.guard(BM)
            BMB = BM @ B
        if self.skew:  # MB = (BM)^†: the whole sum in one pass, the same roundings
            del B
            if norms:
                return skew_combination_norms(BM, self._q, self.W0, BMB, self._qq, iterate)
            return skew_combination(BM, self._q, self.W0, BMB, self._qq), None
        MB = M @ B
        del B
        out = BM - MB
        del MB
        out *= self._q
        out += self.W0
        BMB *= self._qq
        out += BMB
        return out, None

    def map_derivative(self, M: Array, dM: Array) -> Array:
        B = self.B(M)
        dB = self.B_derivative(M, dM)
        q = self.half
        first = dB @ M + B @ dM - dM @ B - M @ dB
        second = dB @ M @ B + B @ dM @ B + B @ M @ dB
        return q * first + (q * q) * second

    def frozen_map(self, M: Array) -> Array:
        B = self.B(M)
        eye = identity(B.shape[-1], B)
        left = namespace(B).linalg.solve(eye - self.half * B, self.W0)
        return solve_right(left, eye + self.half * B)

    def update(self, M: Array) -> Array:
        """``W1 = W0 + h [B(M), M]``."""
        return self.commutator_update(M, 2 * self.half)

    def conjugation_update(self, M: Array) -> Array:
        """``W1 = C W0 C^{-1}``, ``C`` the Cayley transform of ``(h/2) B(M)``: isospectral
        for any ``M`` (:func:`~lieflow.schemes.conjugation.cayley_update`)."""
        return conjugation.cayley_update(self.W0, self.B(M), self.half, self.skew)


def _composition_tableau(tableau: ButcherTableau) -> ButcherTableau:
    b = tableau.b
    expected = np.tril(np.broadcast_to(b, (b.size, b.size)), -1) + np.diag(b / 2)
    if not np.abs(tableau.A - expected).max() <= 1e-15:
        raise TableauError(
            f"tableau {tableau.name!r} is not a composition of midpoint steps "
            "(a_ij = b_j for j < i, a_ii = b_i / 2); use BlockGauss for a general "
            "symplectic tableau"
        )
    return tableau.require_symplectic()


@attrs.frozen
class SyDIRK(Scheme):
    """A symplectic DIRK: a composition of midpoint steps of sizes ``b_1 h, ..., b_s h``
    (SPEC §4.2). ``SyDIRK()`` is the implicit midpoint rule (1s-SyDIRK).

    Each sub-step solves its own :class:`MidpointProblem`; ``warm`` stacks the sub-steps'
    unknowns (offsets ``M_i - W^{(i-1)}``), shape ``(..., s, n, n)``.

    ``update``: ``"commutator"`` (default, ``W1 = W0 + h b_i [B(M), M]`` per sub-step,
    isospectral at the fixed point) or ``"conjugation"`` (the Cayley form
    ``W1 = C W0 C^{-1}``, isospectral for any iterate: SPEC §4.7,
    :mod:`lieflow.schemes.conjugation`).
    """

    tableau: ButcherTableau = attrs.field(factory=midpoint, converter=_composition_tableau)
    update: str = attrs.field(
        default="commutator", validator=one_of(*conjugation.UPDATES), kw_only=True
    )
    #: The sub-steps' weights ``b_i`` as Python floats (read once, not on every step).
    _weights: tuple[float, ...] = attrs.field(init=False, eq=False, repr=False)

    @_weights.default
    def _tableau_weights(self) -> tuple[float, ...]:
        return tuple(self.tableau.b.tolist())

    @property
    def keeps_skew(self) -> bool:
        """``True`` for the commutator update: each sub-step's ``W + h_i (C - C^T)`` is
        exactly skew for an exactly skew ``W`` (the proof is in
        :meth:`~lieflow.schemes.base.StageProblem.commutator_update`); the Cayley form is
        skew only to roundoff."""
        return self.update == "commutator"

    def compiled_form(self) -> tuple[str, Array, Array] | None:
        """``("sydirk", A, b)``: the compiled engine runs this composition (with the
        scheme's ``update``)."""
        return "sydirk", self.tableau.A, self.tableau.b

    def step(
        self,
        W0: Array,
        h: float,
        system: IsospectralSystem,
        solver: Solver,
        warm: Array | None = None,
    ) -> StepResult:
        W = W0
        weights = self._weights
        host = type(W0) is np.ndarray or is_numpy(W0)
        shape = W0.shape
        one = host and W0.ndim == 2  # one NumPy matrix: sub-step i of the offsets is [i]
        alone = one and len(weights) == 1  # the midpoint rule on one matrix
        offsets: Any = (
            np.empty((*shape[:-2], len(weights), *shape[-2:]), dtype=W0.dtype)
            if host and not alone
            else None
        )
        parts: list[Any] = []  # the offsets of another array library, stacked at the end
        iterations = 0
        commutator = self.update == "commutator"
        for i, bi in enumerate(weights):
            hi = bi * h
            at: Any = i if one else (..., i, slice(None), slice(None))
            guess = None if warm is None else warm[at]
            problem = MidpointProblem(system, W, hi, guess)
            res = solver.solve(problem)
            if not res.converged:  # retried cold (or raised): the one rule of schemes.solve

                def build(guess: Array | None, W: Array = W, hi: float = hi) -> MidpointProblem:
                    return MidpointProblem(system, W, hi, guess)

                problem, res = retry(solver, build, guess, problem, res)
            iterations += res.iterations
            x = res.x
            if alone:  # its offset itself, with the stage axis (a view)
                offsets = (x - W)[None]
            elif host:
                np.subtract(x, W, out=offsets[at])
            else:
                parts.append(x - W)
            W = problem.update(x) if commutator else problem.conjugation_update(x)
        if not host:
            offsets = namespace(W0).stack(parts, axis=-3)
        return StepResult(W, offsets, StepStats(iterations, res.solver, res.residuals[-1]))
