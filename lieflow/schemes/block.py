"""The block algorithm for any symplectic tableau (SPEC §4.3) and its reduced stage form
(SPEC §4.5): two evaluations of the same fixed point, behind one scheme, :class:`BlockGauss`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import attrs
import numpy as np

from ..algebras import Array, dagger
from ..backends import copy, device_of, from_host, identity, is_numpy, namespace
from ..tableaus import one_of
from . import conjugation
from .base import (
    StageEquations,
    TableauProblem,
    TableauScheme,
    contract,
    scratch,
    solve_right,
)


def blocks_to_dense(X: Array) -> Array:
    """``(..., s, s, n, n)`` blocks ``X_kl`` -> the dense ``(..., sn, sn)`` matrix (arrays
    of any library)."""
    *batch, s, _, n, _ = X.shape
    xp = namespace(X)
    return xp.reshape(xp.moveaxis(X, -3, -2), (*batch, s * n, s * n))


def dense_to_blocks(X: Array, s: int) -> Array:
    """Inverse of :func:`blocks_to_dense`."""
    *batch, sn, _ = X.shape
    n = sn // s
    xp = namespace(X)
    return xp.moveaxis(xp.reshape(X, (*batch, s, n, s, n)), -3, -2)


def _block_coefficient_matrix(coef: np.ndarray, mats: Array) -> Array:
    """Dense ``(..., sn, sn)`` matrix with blocks ``coef[k, l] * mats[..., k or l]``.

    ``mats`` has shape ``(..., s, s, n, n)`` or one that broadcasts to it (a block row or
    column); ``coef`` is a host matrix (placed on ``mats``' device, in its dtype, for
    arrays of another library).
    """
    if not is_numpy(mats):
        coef = from_host(coef, mats, mats.dtype)
    return blocks_to_dense(coef[:, :, None, None] * mats)


def reduced_coefficients(h: float, A: np.ndarray, skew: bool) -> tuple[np.ndarray, np.ndarray]:
    r"""The coefficients ``(C_G, C_P)`` of the reduced stage form's stage sums (SPEC §4.5),
    ``G_i = I + sum_j (C_G)_ij G_j B̃_j`` and ``P_i = W_0 + sum_j (C_P)_ij P_j B_j``:
    ``C_P = -hA``, and ``C_G = hA`` with ``B̃_j = B_j^†``, or on a skew-Hermitian algebra
    (``B^† = -B``) ``C_G = -hA`` with ``B̃_j = B_j``, so that no negated copy of a stack is
    made. One derivation for both engines: :class:`ReducedProblem` and the compiled
    engine's plan (:mod:`lieflow.engines.compiled`), which hands them to its loops."""
    hA = h * A
    return (-hA if skew else hA), -hA


class BlockProblem(TableauProblem):
    r"""The block algorithm's implicit equation (SPEC §4.3), evaluated block-wise.

    Unknown ``M`` with ``n×n`` blocks ``M_kl``, shape ``(..., s, s, n, n)``;
    ``B_k = B(M_kk)``. Fixed-point map

    .. math:: M \leftarrow \mathbf W_0 + hA\mathbf B M - hM\mathbf B A^T
              + h^2 A\mathbf B M \mathbf B A^T,

    the rearrangement of :math:`\mathbf W_0 = (I - hA\mathbf B) M (I + h\mathbf B A^T)`
    (SPEC §4.3 prints the last sign as minus; expanding the product, and §4.1 for ``s = 1``,
    give plus, and only plus reproduces the Modin–Viviani form),

    with :math:`(A\mathbf BM)_{ij} = \sum_k a_{ik}B_kM_{kj}`,
    :math:`(M\mathbf BA^T)_{ij} = \sum_l a_{jl}M_{il}B_l` and
    :math:`(A\mathbf BM\mathbf BA^T)_{ij} = \sum_{kl}a_{ik}a_{jl}B_kM_{kl}B_l`:
    ``3 s^2`` products of ``n×n`` matrices per iteration, no dense ``sn×sn`` matrix.
    """

    core_ndim = 4

    def _prepare(self) -> None:
        W0, s = self.W0, self.s
        self.diag = np.arange(s)
        self.trivial = namespace(W0).broadcast_to(
            W0[..., None, None, :, :], (*W0.shape[:-2], s, s, *W0.shape[-2:])
        )

    @property
    def x0(self) -> Array:
        """``M`` at ``h = 0`` (every block ``W0``) plus ``warm``, a new array on each
        access."""
        return self.trivial + self.warm if self.warm is not None else copy(self.trivial)

    def stages(self, M: Array) -> Array:
        """The stage values ``M_kk``, shape ``(..., s, n, n)``."""
        if self._host:
            return M[..., self.diag, self.diag, :, :]
        # another array library: no indexing by integer arrays assumed
        return namespace(M).stack([M[..., k, k, :, :] for k in range(self.s)], axis=-3)

    def _combine(self, BM: Array, MB: Array, BMB: Array) -> Array:
        A, h = self.A, self.h
        if self._host:
            ABM = np.einsum("ik,...kjab->...ijab", A, BM)
            MBAt = np.einsum("jl,...ilab->...ijab", A, MB)
            ABMBAt = np.einsum("ik,jl,...klab->...ijab", A, A, BMB)
        else:  # another array library: the same sums, by contract
            ABM = contract(A, BM, -4)
            MBAt = contract(A, MB, -3)
            ABMBAt = contract(A, contract(A, BMB, -3), -4)
        return h * (ABM - MBAt) + (h * h) * ABMBAt

    def map(self, M: Array) -> Array:
        B = self.B(self.stages(M))
        Bk = B[..., :, None, :, :]  # B_k acting on block row k
        Bl = B[..., None, :, :, :]  # B_l acting on block column l
        BM = Bk @ M
        return self.W0[..., None, None, :, :] + self._combine(BM, M @ Bl, BM @ Bl)

    def map_derivative(self, M: Array, dM: Array) -> Array:
        D = self.stages(M)
        B = self.B(D)
        dB = self.B_derivative(D, self.stages(dM))
        Bk, Bl = B[..., :, None, :, :], B[..., None, :, :, :]
        dBk, dBl = dB[..., :, None, :, :], dB[..., None, :, :, :]
        BM = Bk @ M
        dBM = dBk @ M + Bk @ dM
        return self._combine(dBM, dM @ Bl + M @ dBl, dBM @ Bl + BM @ dBl)

    def frozen_map(self, M: Array) -> Array:
        B = self.B(self.stages(M))
        s = self.s
        eye = identity(s * B.shape[-1], B)
        AB = _block_coefficient_matrix(self.A, B[..., None, :, :, :])  # blocks a_ik B_k
        BAt = _block_coefficient_matrix(self.A.T, B[..., :, None, :, :])  # blocks B_k a_lk
        left = namespace(B).linalg.solve(eye - self.h * AB, blocks_to_dense(self.trivial))
        return dense_to_blocks(solve_right(left, eye + self.h * BAt), s)

    def offsets(self, M: Array) -> Array:
        """``M`` minus its ``h = 0`` value, for warm starts."""
        return M - self.W0[..., None, None, :, :]


class ReducedProblem(TableauProblem):
    r"""The reduced stage form (SPEC §4.5): the lifted RK stages with ``g0 = I``, ``p0 = W0``.

    .. math::
        G_i = I + h\sum_j a_{ij} G_j B_j^\dagger,\quad
        P_i = W_0 - h\sum_j a_{ij} P_j B_j,\quad B_j = B(G_j^\dagger P_j),

    unknown ``x = (G, P)`` of shape ``(..., 2, s, n, n)``; ``3 s`` products per iteration.
    The stage values ``G_i^† P_i`` equal the block algorithm's ``M_ii`` (same fixed point).
    """

    core_ndim = 4

    def _prepare(self) -> None:
        W0, s, n = self.W0, self.s, self.W0.shape[-1]
        shape = (*W0.shape[:-2], s, n, n)
        if is_numpy(W0):
            trivial = np.empty((*W0.shape[:-2], 2, s, n, n), dtype=W0.dtype)
            trivial[..., 0, :, :, :] = np.eye(n)
            trivial[..., 1, :, :, :] = W0[..., None, :, :]
        else:  # another array library (lieflow.backends): no slice assignment assumed
            xp = namespace(W0)
            eye = xp.eye(n, dtype=W0.dtype, device=device_of(W0))
            parts = [xp.broadcast_to(eye, shape), xp.broadcast_to(W0[..., None, :, :], shape)]
            trivial = xp.stack(parts, axis=-4)
        self.trivial = trivial
        self._coefficients = reduced_coefficients(self.h, self.A, self.skew)
        self._stages: Array | None = None
        self._products: Array | None = None

    @property
    def x0(self) -> Array:
        """``(I, W0)`` plus ``warm``, a new array on each access: the solver reads it once,
        and no copy outlives the first update."""
        return self.trivial + self.warm if self.warm is not None else copy(self.trivial)

    def stages(self, x: Array) -> Array:
        """Stage values ``G_i^† P_i``, shape ``(..., s, n, n)``."""
        return dagger(x[..., 0, :, :, :]) @ x[..., 1, :, :, :]

    def _Bdag(self, B: Array) -> Array:
        return -B if self.skew else dagger(B)

    def _assemble(self, GB: Array, PB: Array, constant: Array | None) -> Array:
        """``(h sum_j a_ij G_j B_j^†, -h sum_j a_ij P_j B_j) + constant`` from ``GB_j = G_j B_j``
        (skew algebras: ``B^† = -B``, so the sign goes into the coefficients,
        :func:`reduced_coefficients`) or ``G_j B_j^†`` (others): one ``(s×s)@(s×n²)``
        product per half, written into the result."""
        *batch, s, n, _ = GB.shape
        halves = tuple(zip(self._coefficients, (GB, PB), strict=True))
        if not is_numpy(GB):  # another array library: the same products, fresh arrays
            xp = namespace(GB)
            parts = [  # coefficients in GB's dtype: some libraries (torch) do not mix
                from_host(coef, GB, GB.dtype) @ xp.reshape(Y, (*batch, s, n * n))
                for coef, Y in halves
            ]
            joined = xp.reshape(xp.stack(parts, axis=-3), (*batch, 2, s, n, n))
            return joined if constant is None else joined + constant
        out = np.empty((*batch, 2, s, n * n), dtype=np.result_type(GB, PB, self.A))
        for half, (coef, Y) in enumerate(halves):
            np.matmul(coef, Y.reshape(*batch, s, n * n), out=out[..., half, :, :])
        out = out.reshape(*batch, 2, s, n, n)
        if constant is not None:
            out += constant
        return out

    def _times_B(self, G: Array, B: Array) -> Array:
        """``G B`` on skew algebras, ``G B^†`` otherwise (what :meth:`_assemble` takes)."""
        return G @ (B if self.skew else dagger(B))

    def map(self, x: Array) -> Array:
        # the products go into scratch kept for the step (:func:`scratch`): an iteration
        # allocates only B and its result
        G, P = x[..., 0, :, :, :], x[..., 1, :, :, :]
        if not is_numpy(x):  # another array library: the same products, fresh arrays
            B = self.B(dagger(G) @ P)
            GB, PB = G @ (B if self.skew else dagger(B)), P @ B
            del B
            return self._assemble(GB, PB, self.trivial)
        (W,) = self._stages = scratch(self._stages, 1, G.shape, x.dtype)
        B = self.B(np.matmul(dagger(G), P, out=W))
        dtype = np.result_type(x, B)
        GB, PB = self._products = scratch(self._products, 2, G.shape, dtype)
        np.matmul(G, B if self.skew else dagger(B), out=GB)
        np.matmul(P, B, out=PB)
        del B
        return self._assemble(GB, PB, self.trivial)

    def map_derivative(self, x: Array, dx: Array) -> Array:
        G, P = x[..., 0, :, :, :], x[..., 1, :, :, :]
        dG, dP = dx[..., 0, :, :, :], dx[..., 1, :, :, :]
        W = dagger(G) @ P
        B = self.B(W)
        dB = self.B_derivative(W, dagger(dG) @ P + dagger(G) @ dP)
        dGB = self._times_B(dG, B) + self._times_B(G, dB)
        dPB = dP @ B + P @ dB
        return self._assemble(dGB, dPB, None)

    def frozen_map(self, x: Array) -> Array:
        r"""With ``B`` frozen both stage equations are linear (row-block form):
        ``G (I - h B^†A^T) = [I ... I]`` and ``P (I + h B A^T) = [W0 ... W0]``."""
        B = self.B(self.stages(x))
        s, n = self.A.shape[0], B.shape[-1]
        xp = namespace(B)
        eye = identity(s * n, B)
        # blocks (j, i) = a_ij B_j: the matrix B A^T acting on a block row from the right
        At = self.A.T
        Bdag = self._Bdag(B)
        CG = _block_coefficient_matrix(At, Bdag[..., :, None, :, :])
        CP = _block_coefficient_matrix(At, B[..., :, None, :, :])
        trivial = self.trivial
        rows = xp.reshape(xp.moveaxis(trivial, -3, -2), (*trivial.shape[:-3], n, s * n))
        G = solve_right(rows[..., 0, :, :], eye - self.h * CG)
        P = solve_right(rows[..., 1, :, :], eye + self.h * CP)
        out = xp.reshape(xp.stack([G, P], axis=-3), (*G.shape[:-2], 2, n, s, n))
        return xp.moveaxis(out, -3, -2)

    def conjugation_update(self, x: Array) -> Array:
        """``W1 = Q^† W0 Q``, ``Q`` the lifted ``g1 = I + h sum_j b_j G_j B_j^†`` made
        unitary (a similarity by ``g1^†`` for non-skew ``B``): isospectral for any ``x``
        (:func:`~lieflow.schemes.conjugation.lifted_update`)."""
        B = self.B(self.stages(x))
        Gdag = dagger(x[..., 0, :, :, :])
        return conjugation.lifted_update(self.W0, Gdag, B, self.h * self.b, self.skew)

    def offsets(self, x: Array) -> Array:
        """``x`` minus its ``h = 0`` value ``(I, W0)``, for warm starts."""
        return x - self.trivial


@attrs.frozen
class BlockGauss(TableauScheme):
    """ISOSyRK for any symplectic tableau via the block algorithm (SPEC §4.3).

    Parameters
    ----------
    tableau : ButcherTableau
        As for :class:`~lieflow.schemes.TableauScheme`: any symplectic tableau,
        Gauss–Legendre with 2 stages by default.
    form : {"reduced", "block"}
        ``"reduced"`` (default) iterates the ``2s`` stage matrices of the lifted system
        (SPEC §4.5, ``3s`` products per iteration); ``"block"`` iterates the paper's ``s×s``
        block matrix ``M`` block-wise (``3s^2`` products). Both have the same fixed point
        and give the same ``W1`` to roundoff.
    update : {"commutator", "conjugation"}
        As for :class:`~lieflow.schemes.TableauScheme` (the conjugation form:
        ``W1 = Q^† W0 Q`` with the lifted ``g1`` made unitary).
    """

    form: Literal["reduced", "block"] = attrs.field(
        default="reduced", validator=one_of("reduced", "block")
    )

    @property
    def name(self) -> str:
        return self.tableau.name if self.form == "reduced" else f"block_{self.tableau.name}"

    def compiled_form(self) -> tuple[str, Array, Array] | None:
        """``("reduced", A, b)`` for the reduced form (compiled, with the scheme's
        ``update``); ``None`` for the block form."""
        return ("reduced", self.tableau.A, self.tableau.b) if self.form == "reduced" else None

    @property
    def problem_class(self) -> Callable[..., StageEquations]:
        """:class:`ReducedProblem` or :class:`BlockProblem`, by :attr:`form`."""
        return ReducedProblem if self.form == "reduced" else BlockProblem
