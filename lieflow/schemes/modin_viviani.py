"""The classic Modin–Viviani ISOSyRK form with ``3s + s^2`` unknowns (SPEC §4.4, corrected)."""

from __future__ import annotations

from collections.abc import Callable

import attrs
import numpy as np

from ..algebras import Array
from ..backends import device_of, identity, namespace
from .base import (
    StageEquations,
    TableauProblem,
    TableauScheme,
    contract,
    solve_right,
)
from .block import _block_coefficient_matrix


class ModinVivianiProblem(TableauProblem):
    r"""Unknowns ``X_i, Y_i, K_ij`` (stacked as ``(..., 2s + s^2, n, n)``) with

    .. math::
        X_i &= -h\,(W_0 + \textstyle\sum_j a_{ij} X_j)\, B(\tilde W_i) \\
        Y_i &= h\, B(\tilde W_i)\,(W_0 + \textstyle\sum_j a_{ij} Y_j) \\
        K_{ij} &= h\, B(\tilde W_j) \textstyle\sum_l (a_{il} X_l + a_{jl} K_{il}) \\
        \tilde W_i &= W_0 + \textstyle\sum_j a_{ij} (X_j + Y_j + K_{ij})

    and :math:`W_1 = W_0 + h\sum_i b_i [B(\tilde W_i), \tilde W_i]` (SPEC §4.4: the seed
    paper's K equation has index errors). ``s^2 + 2s`` products per iteration.
    """

    core_ndim = 3

    def _prepare(self) -> None:
        W0, s, warm = self.W0, self.s, self.warm
        shape = (*W0.shape[:-2], 2 * s + s * s, *W0.shape[-2:])
        if self._host:
            self.x0 = (
                np.array(warm, dtype=W0.dtype) if warm is not None else np.zeros(shape, W0.dtype)
            )
        else:  # another array library (lieflow.backends)
            xp = namespace(W0)
            zeros = xp.zeros(shape, dtype=W0.dtype, device=device_of(W0))
            self.x0 = zeros if warm is None else xp.asarray(warm, dtype=W0.dtype, copy=True)

    def _split(self, x: Array) -> tuple[Array, Array, Array]:
        s = self.s
        K = namespace(x).reshape(x[..., 2 * s :, :, :], (*x.shape[:-3], s, s, *x.shape[-2:]))
        return x[..., :s, :, :], x[..., s : 2 * s, :, :], K

    def _join(self, X: Array, Y: Array, K: Array) -> Array:
        xp = namespace(K)
        K = xp.reshape(K, (*K.shape[:-4], self.s * self.s, *K.shape[-2:]))
        if self._host:
            return np.concatenate([X, Y, K], axis=-3)
        return xp.concat([X, Y, K], axis=-3)

    def stages(self, x: Array) -> Array:
        """``W~_i``, shape ``(..., s, n, n)``."""
        X, Y, K = self._split(x)
        return self._stages(X, Y, K, self.W0)

    def _mix(self, X: Array) -> Array:
        """``sum_j a_ij X_j`` over the stage axis ``-3``."""
        if self._host:
            return np.einsum("ij,...jab->...iab", self.A, X)
        return contract(self.A, X, -3)

    def _mix_rows(self, K: Array) -> Array:
        """``sum_l a_jl K_il``: ``(..., s, s, n, n)`` -> the same shape."""
        if self._host:
            return np.einsum("jl,...ilab->...ijab", self.A, K)
        return contract(self.A, K, -3)

    def _stages(self, X: Array, Y: Array, K: Array, W0: Array | None) -> Array:
        XY = self._mix(X + Y)
        if self._host:
            AK = np.einsum("ij,...ijab->...iab", self.A, K)
        else:  # sum_j a_ij K_ij for each i
            rows = []
            for i, row in enumerate(self.A.tolist()):
                terms = [a * K[..., i, j, :, :] for j, a in enumerate(row)]
                rows.append(sum(terms[1:], terms[0]))
            AK = namespace(K).stack(rows, axis=-3)
        return XY + AK if W0 is None else W0[..., None, :, :] + XY + AK

    def _rhs(
        self,
        X: Array,
        Y: Array,
        K: Array,
        B: Array,
        dB: Array | None = None,
        dX: Array | None = None,
        dY: Array | None = None,
        dK: Array | None = None,
    ) -> Array:
        """The map, or (with the d-arguments) its derivative, which is linear in them."""
        h = self.h
        W0 = self.W0[..., None, :, :]
        Bj = B[..., None, :, :, :]
        if dB is None:
            AX = self._mix(X)
            AY = self._mix(Y)
            Z = AX[..., :, None, :, :] + self._mix_rows(K)
            return self._join(-h * ((W0 + AX) @ B), h * (B @ (W0 + AY)), h * (Bj @ Z))
        assert dX is not None and dY is not None and dK is not None
        dBj = dB[..., None, :, :, :]
        AX, dAX = self._mix(X), self._mix(dX)
        AY, dAY = self._mix(Y), self._mix(dY)
        Z = AX[..., :, None, :, :] + self._mix_rows(K)
        dZ = dAX[..., :, None, :, :] + self._mix_rows(dK)
        return self._join(
            -h * (dAX @ B + (W0 + AX) @ dB),
            h * (dB @ (W0 + AY) + B @ dAY),
            h * (dBj @ Z + Bj @ dZ),
        )

    def map(self, x: Array) -> Array:
        X, Y, K = self._split(x)
        return self._rhs(X, Y, K, self.B(self._stages(X, Y, K, self.W0)))

    def map_derivative(self, x: Array, dx: Array) -> Array:
        X, Y, K = self._split(x)
        dX, dY, dK = self._split(dx)
        W = self._stages(X, Y, K, self.W0)
        B = self.B(W)
        dB = self.B_derivative(W, self._stages(dX, dY, dK, None))
        return self._rhs(X, Y, K, B, dB, dX, dY, dK)

    def frozen_map(self, x: Array) -> Array:
        r"""With ``B_i`` frozen the equations are linear, in block form
        ``X (I + h A^T B) = -h [W0 B_1 ... W0 B_s]``,
        ``(I - h B A) Y = h [B_1 W0; ...; B_s W0]`` and, for each ``i``,
        ``(I - h B A) [K_i1; ...; K_is] = h [B_1 Z_i; ...; B_s Z_i]``, ``Z_i = sum_l a_il X_l``.
        """
        W0, A, h, s = self.W0, self.A, self.h, self.s
        B = self.B(self.stages(x))
        n = B.shape[-1]
        xp = namespace(B)
        eye = identity(s * n, B)
        batch = W0.shape[:-2]
        # X: row block, X (I + h C) = R with blocks C_(j,i) = a_ij B_i
        C = _block_coefficient_matrix(A.T, B[..., None, :, :, :])
        R = -h * (W0[..., None, :, :] @ B)
        Rrow = xp.reshape(xp.moveaxis(R, -3, -2), (*batch, n, s * n))
        Xrow = solve_right(Rrow, eye + h * C)
        X = xp.moveaxis(xp.reshape(Xrow, (*batch, n, s, n)), -3, -2)
        # Y and all K_i: column blocks sharing the matrix I - h B A, blocks (i, j) = B_i a_ij
        D = _block_coefficient_matrix(A, B[..., :, None, :, :])
        Z = self._mix(X)  # Z_i
        rhs_Y = h * (B @ W0[..., None, :, :])  # (..., s, n, n)
        rhs_K = h * (B[..., None, :, :, :] @ Z[..., :, None, :, :])  # [i, j] = B_j Z_i
        # (..., 1+s, s, n, n)
        cols = xp.stack([rhs_Y, *(rhs_K[..., i, :, :, :] for i in range(s))], axis=-4)
        cols = xp.reshape(xp.moveaxis(cols, -4, -2), (*batch, s * n, (1 + s) * n))
        sol = xp.reshape(xp.linalg.solve(eye - h * D, cols), (*batch, s, n, 1 + s, n))
        sol = xp.moveaxis(sol, -2, -4)  # (..., 1+s, s, n, n)
        return self._join(X, sol[..., 0, :, :, :], sol[..., 1:, :, :, :])

    def offsets(self, x: Array) -> Array:
        """``x`` itself: the unknowns ``X, Y, K`` vanish at ``h = 0``."""
        return x


@attrs.frozen
class ModinViviani(TableauScheme):
    """The classic ``3s + s^2`` Modin–Viviani ISOSyRK form for any symplectic tableau.

    Kept as the reference formulation: the block algorithm must reproduce it to roundoff.
    ``tableau`` and ``update`` as for :class:`~lieflow.schemes.TableauScheme` (the
    conjugation form builds the lifted ``G_i`` from the stages' ``B``: the unknowns carry
    ``G_i^† W0``, not ``G_i``).
    """

    @property
    def name(self) -> str:
        return f"modin_viviani_{self.tableau.name}"

    @property
    def problem_class(self) -> Callable[..., StageEquations]:
        """:class:`ModinVivianiProblem`."""
        return ModinVivianiProblem
