"""The formulations of the compiled engine's loops (imported with
:mod:`lieflow.engines._compiled_loops`), each the numpy code path written out entry by entry:

* the maps whose fixed point a step solves: :func:`_midpoint_map` (a midpoint step, SPEC
  §4.1) and :func:`_reduced_map` (the reduced stage form, SPEC §4.5), each made for
  skew-Hermitian algebras or general ones (:func:`_midpoint_map_of`,
  :func:`_reduced_map_of`), and the commutator update :func:`_commutator_add`;
* the updates in conjugation form (SPEC §4.7): the Cayley update of a midpoint step
  (:func:`_cayley_into`) and the lifted update of the reduced form (:func:`_lifted_into`),
  both by :func:`_conjugate_into_of` and Newton–Schulz (:func:`_orthonormalize`), with
  Gauss–Jordan solves in loops (:func:`_gauss_jordan`).

The steps that solve them and the entry points are :mod:`lieflow.engines._compiled_loops`'s.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..schemes import conjugation
from ._compiled_maps import _apply_B
from ._compiled_rules import _schulz_step, _skew_to_roundoff_rule
from ._numba_jit import (
    LOOP_PRODUCTS_MAX_N,
    _abs2,
    _helper,
    _inlined_by_llvm,
    _inner,
    _is_complex,
    _matmul,
    _matmul_hn,
    _matmul_nh,
    _renamed,
)

# ------------------------------------------------------------------ formulations


#: The name of each kind of algebra in the names of the functions made for one
#: (``skew``: skew-Hermitian, so(n), u(n), su(N); else general, gl(n), symmetric).
_ALGEBRAS = {False: "general", True: "skew"}


def _midpoint_map_of(skew: bool) -> Any:
    """:func:`_midpoint_map` for skew-Hermitian algebras (``skew``) or general ones: a
    constant of the compiled code, so that the branches of the other kind are neither typed
    nor compiled (numba prunes a branch on a closure constant; issue 37 item 11)."""

    def _midpoint_map(
        W0: Any, coef: Any, x: Any, Bm: Any, BM: Any, BMB: Any, MB: Any, B: Any, params: Any,
        gemm: Any,
    ) -> tuple[float, float]:  # fmt: skip
        """One update of the midpoint map (SPEC §4.1), in place:

        ``M <- W0 + q (B M - M B) + q^2 B M B``, ``B = B(M)``, ``coef = (q, q^2)``
        (:func:`~lieflow.schemes.sydirk.midpoint_coefficients`, ``q = h/2``);
        for skew algebras ``M B = (B M)^†`` (two products per update, SPEC §4.1), and for
        small real ``n`` only half of the skew ``B M B`` is formed. The new iterate overwrites ``x``
        entry by entry once the products are formed; ``Bm``, ... ``MB`` are scratch matrices,
        ``gemm`` the products above ``n = LOOP_PRODUCTS_MAX_N`` (:func:`gemm`; ``None``: plain
        loops, :func:`_matmul`). Returns the squared norms of the update and of the new
        iterate.
        """
        n = W0.shape[0]
        q, qq = coef[0], coef[1]
        _apply_B(B, params, x, Bm)
        _matmul(Bm, x, BM, gemm)
        step2 = 0.0
        size2 = 0.0
        if skew and n <= LOOP_PRODUCTS_MAX_N and not _is_complex(x):
            # B M B is skew for skew B, M: form its strict upper triangle only (its diagonal
            # is zero in exact arithmetic) and mirror it, half a product instead of one.
            for i in range(n):
                g = W0[i, i]
                step2 += _abs2(g - x[i, i])
                size2 += _abs2(g)
                x[i, i] = g
                for j in range(i + 1, n):
                    bmb = 0.0
                    for c in range(n):
                        bmb += BM[i, c] * Bm[c, j]
                    c1 = BM[i, j] - BM[j, i]
                    g = W0[i, j] + q * c1 + qq * bmb
                    gt = W0[j, i] - q * c1 - qq * bmb
                    step2 += _abs2(g - x[i, j]) + _abs2(gt - x[j, i])
                    size2 += _abs2(g) + _abs2(gt)
                    x[i, j] = g
                    x[j, i] = gt
        else:
            _matmul(BM, Bm, BMB, gemm)
            if not skew:
                _matmul(x, Bm, MB, gemm)
            for i in range(n):
                for j in range(n):
                    mb = np.conj(BM[j, i]) if skew else MB[i, j]
                    g = W0[i, j] + q * (BM[i, j] - mb) + qq * BMB[i, j]
                    step2 += _abs2(g - x[i, j])
                    size2 += _abs2(g)
                    x[i, j] = g
        return step2, size2

    name = f"_midpoint_map_{_ALGEBRAS[skew]}"
    return _inlined_by_llvm(_renamed(_midpoint_map, name))


_midpoint_map_general, _midpoint_map_skew = (_midpoint_map_of(skew) for skew in _ALGEBRAS)


@_inner
def _commutator_add(
    W: Any, hb: float, skew: bool, M: Any, B: Any, params: Any, Bm: Any, BM: Any, MB: Any,
    gemm: Any,
) -> None:  # fmt: skip
    """``W += hb [B(M), M]`` in place (one product for skew algebras: ``M B = (B M)^†``);
    ``Bm``, ``BM``, ``MB`` are scratch matrices."""
    n = W.shape[0]
    _apply_B(B, params, M, Bm)
    _matmul(Bm, M, BM, gemm)
    if skew:
        for i in range(n):
            for j in range(n):
                MB[i, j] = np.conj(BM[j, i])
    else:
        _matmul(M, Bm, MB, gemm)
    for i in range(n):
        for j in range(n):
            W[i, j] = W[i, j] + hb * (BM[i, j] - MB[i, j])


def _reduced_map_of(skew: bool) -> Any:
    """:func:`_reduced_map` for skew-Hermitian algebras or general ones (as
    :func:`_midpoint_map_of`)."""

    def _reduced_map(
        W0: Any, coef: Any, x: Any, Wst: Any, Bs: Any, GB: Any, PB: Any, B: Any, params: Any,
        gemm: Any,
    ) -> tuple[float, float]:  # fmt: skip
        """One update of the reduced stage form (SPEC §4.5), in place (``x[0] = G``,
        ``x[1] = P``, each ``(s, n, n)``):

        ``G_i <- I + sum_j (C_G)_ij G_j B_j^†``, ``P_i <- W0 + sum_j (C_P)_ij P_j B_j``,
        ``B_j = B(G_j^† P_j)``; ``coef = (C_G; C_P)`` stacked, ``(2s, s)``
        (:func:`~lieflow.schemes.block.reduced_coefficients`: ``C_P = -hA``, ``C_G = hA``,
        or ``-hA`` for skew algebras, where ``G_j B_j`` is formed for ``G_j B_j^† = -G_j B_j``).
        ``3 s`` products per update; ``Wst``, ... ``PB`` are scratch stacks ``(s, n, n)``
        (``GB[j]`` and ``Wst[j]`` also hold the conjugates that complex data need, before they
        are overwritten; ``Wst`` and ``Bs`` then the stage sums, each entry summed in the order
        ``j = 1..s``). Returns the squared norms of the update and of the new iterate.
        """
        s, n = coef.shape[1], W0.shape[0]
        nn = n * n
        for j in range(s):
            _matmul_hn(x[0, j], x[1, j], Wst[j], GB[j], gemm)
            _apply_B(B, params, Wst[j], Bs[j])
            if skew:  # G_j B_j, whose sign goes into the coefficients below (B^† = -B)
                _matmul(x[0, j], Bs[j], GB[j], gemm)
            else:
                _matmul_nh(x[0, j], Bs[j], GB[j], Wst[j], gemm)
            _matmul(x[1, j], Bs[j], PB[j], gemm)
        # the stage sums, into Wst and Bs (free by now), over the n² entries of each matrix as
        # one flat loop (vectorised whatever n)
        GBf, PBf = GB.reshape((s, nn)), PB.reshape((s, nn))
        accG, accP = Wst.reshape((s, nn)), Bs.reshape((s, nn))
        for i in range(s):
            for e in range(nn):
                accG[i, e] = 0.0
                accP[i, e] = 0.0
            for j in range(s):
                wG, wP = coef[i, j], coef[s + i, j]
                for e in range(nn):
                    accG[i, e] += wG * GBf[j, e]
                    accP[i, e] += wP * PBf[j, e]
        step2 = 0.0
        size2 = 0.0
        for i in range(s):
            for a in range(n):
                for c in range(n):
                    gG = Wst[i, a, c] + (1.0 if a == c else 0.0)
                    gP = Bs[i, a, c] + W0[a, c]
                    step2 += _abs2(gG - x[0, i, a, c]) + _abs2(gP - x[1, i, a, c])
                    size2 += _abs2(gG) + _abs2(gP)
                    x[0, i, a, c] = gG
                    x[1, i, a, c] = gP
        return step2, size2

    name = f"_reduced_map_{_ALGEBRAS[skew]}"
    return _inlined_by_llvm(_renamed(_reduced_map, name))


_reduced_map_general, _reduced_map_skew = (_reduced_map_of(skew) for skew in _ALGEBRAS)


# ------------------------------------------------------------------ conjugation updates
# The compiled forms of :mod:`lieflow.schemes.conjugation` (SPEC §4.7), in the entry points
# of that update (:func:`entry`'s ``conjugation``): the same formulas, with Gauss–Jordan
# elimination in loops for the solves (compiled code here cannot allocate, so LAPACK's
# solve is not available).

_EPS64 = float(np.finfo(np.float64).eps)


@_helper
def _gauss_jordan(L: Any, R: Any) -> None:
    """``R <- L^{-1} R`` in place (``L``, ``n×n``, is destroyed): elimination with partial
    pivoting, then back substitution."""
    n, m = L.shape[0], R.shape[1]
    for k in range(n):
        p = k
        best = _abs2(L[k, k])
        for i in range(k + 1, n):
            v = _abs2(L[i, k])
            if v > best:
                best = v
                p = i
        if p != k:
            for j in range(k, n):
                t = L[k, j]
                L[k, j] = L[p, j]
                L[p, j] = t
            for j in range(m):
                t = R[k, j]
                R[k, j] = R[p, j]
                R[p, j] = t
        inv = 1.0 / L[k, k]
        for i in range(k + 1, n):
            f = L[i, k] * inv
            for j in range(k + 1, n):
                L[i, j] -= f * L[k, j]
            for j in range(m):
                R[i, j] -= f * R[k, j]
    for k in range(n - 1, -1, -1):
        inv = 1.0 / L[k, k]
        for j in range(m):
            acc = R[k, j]
            for c in range(k + 1, n):
                acc -= L[k, c] * R[c, j]
            R[k, j] = acc * inv


@_helper
def _skew_to_roundoff(B: Any) -> bool:
    """Whether ``B`` is skew-Hermitian to roundoff
    (:func:`~lieflow.schemes.conjugation.skew_to_roundoff` of its norms)."""
    n = B.shape[0]
    defect = 0.0
    size = 0.0
    for i in range(n):
        for j in range(n):
            defect += _abs2(B[i, j] + np.conj(B[j, i]))
            size += _abs2(B[i, j])
    return _skew_to_roundoff_rule(math.sqrt(defect), math.sqrt(size), _EPS64)


@_helper
def _orthonormalize(K: Any, E: Any, KE: Any, tmp: Any, gemm: Any) -> bool:
    """Newton–Schulz on ``U = I + K`` in its increment, in place:
    ``E = K + K^† + K^† K``, ``K <- K - (E + K E)/2``
    (:func:`~lieflow.schemes.conjugation.orthonormalize`, its decisions by
    :func:`~lieflow.schemes.conjugation.newton_schulz_step`); false if ``U`` is too far
    from unitary (``||E|| >= 1`` at the start)."""
    n = K.shape[0]
    last = math.inf
    for _ in range(conjugation.NEWTON_SCHULZ_STEPS):
        _matmul_hn(K, K, E, tmp, gemm)
        err2 = 0.0
        for i in range(n):
            for j in range(n):
                e = E[i, j] + K[i, j] + np.conj(K[j, i])
                E[i, j] = e
                err2 += _abs2(e)
        err = math.sqrt(err2)
        decision = _schulz_step(err, last, n, _EPS64)
        if decision == conjugation.SCHULZ_DONE:
            return True
        if decision == conjugation.SCHULZ_REFUSED:
            return False
        last = err
        _matmul(K, E, KE, gemm)
        for i in range(n):
            for j in range(n):
                K[i, j] -= 0.5 * (E[i, j] + KE[i, j])
        if decision == conjugation.SCHULZ_LAST:
            return True
    return True


def _conjugate_into_of(skew: bool) -> Any:
    """:func:`_conjugate_into` for skew-Hermitian algebras, where ``U`` is always made
    unitary (``unitary`` is not read: the Gauss–Jordan solve of the general case is not
    compiled), or general ones (as :func:`_midpoint_map_of`)."""

    def _conjugate_into(
        W: Any, K: Any, unitary: bool, s1: Any, s2: Any, s3: Any, gemm: Any
    ) -> bool:
        """``W <- U W U^{-1}``, ``U = I + K``, in place, as ``W`` plus an increment
        (:func:`~lieflow.schemes.conjugation.conjugate`): with ``unitary``, ``K`` made unitary
        and ``W += K W + W K^† + K W K^†`` (its skew-Hermitian part with ``skew``), else
        ``W += (K W - W K) U^{-1}`` by a solve with ``U^T``. ``s1``, ``s2``, ``s3``: scratch;
        false if ``U`` is too far from unitary."""
        n = W.shape[0]
        if skew or unitary:
            if not _orthonormalize(K, s1, s2, s3, gemm):
                return False
            _matmul(K, W, s1, gemm)
            if skew:
                _matmul_nh(s1, K, s2, s3, gemm)
                for i in range(n):
                    for j in range(i, n):
                        dij = s1[i, j] - np.conj(s1[j, i]) + s2[i, j]
                        dji = s1[j, i] - np.conj(s1[i, j]) + s2[j, i]
                        d = 0.5 * (dij - np.conj(dji))
                        W[i, j] = W[i, j] + d
                        if j != i:
                            W[j, i] = W[j, i] - np.conj(d)
            else:
                _matmul_nh(W, K, s3, s2, gemm)  # W K^† (real data: s2 is not touched)
                for i in range(n):
                    for j in range(n):
                        s3[i, j] += s1[i, j]
                _matmul_nh(s1, K, s2, s1, gemm)  # K W K^† (real data: s1 is not touched)
                for i in range(n):
                    for j in range(n):
                        W[i, j] = W[i, j] + (s3[i, j] + s2[i, j])
        else:
            _matmul(K, W, s1, gemm)
            _matmul(W, K, s2, gemm)
            for i in range(n):
                for j in range(n):
                    s3[i, j] = s1[j, i] - s2[j, i]  # D^T
                    s2[i, j] = K[j, i] + (1.0 if i == j else 0.0)  # U^T
            _gauss_jordan(s2, s3)  # (D U^{-1})^T = U^{-T} D^T
            for i in range(n):
                for j in range(n):
                    W[i, j] = W[i, j] + s3[j, i]
        return True

    return _helper(_renamed(_conjugate_into, f"_conjugate_into_{_ALGEBRAS[skew]}"))


_conjugate_into_general, _conjugate_into_skew = (_conjugate_into_of(skew) for skew in _ALGEBRAS)


@_inner
def _cayley_into(
    W: Any, a: float, skew: bool, M: Any, B: Any, params: Any, Bm: Any, L: Any, C: Any,
    s3: Any, gemm: Any,
) -> bool:  # fmt: skip
    """The midpoint update in Cayley form in place: ``W <- C W C^{-1}``,
    ``C = (I - aB)^{-1}(I + aB) = I + K``, ``K = 2a (I - aB)^{-1} B``, ``B = B(M)``
    (:func:`~lieflow.schemes.conjugation.cayley_update`); ``Bm``, ``L``, ``C``, ``s3``
    scratch (``M`` is read only)."""
    n = W.shape[0]
    _apply_B(B, params, M, Bm)
    unitary = skew or _skew_to_roundoff(Bm)  # (skew: a constant, see _sydirk_step_of)
    for i in range(n):
        for j in range(n):
            L[i, j] = (1.0 if i == j else 0.0) - a * Bm[i, j]
            C[i, j] = (2 * a) * Bm[i, j]
    _gauss_jordan(L, C)
    if skew:
        return _conjugate_into_skew(W, C, unitary, L, Bm, s3, gemm)
    return _conjugate_into_general(W, C, unitary, L, Bm, s3, gemm)


@_inner
def _lifted_into(
    W: Any, hb: Any, skew: bool, x: Any, B: Any, params: Any, Wi: Any, Bi: Any, P: Any,
    U: Any, gemm: Any,
) -> bool:  # fmt: skip
    """The Gauss update in conjugation form in place: ``W <- U W U^{-1}``, ``U = I + K``,
    ``K = sum_i hb_i B_i G_i^†`` (held in ``U``), ``B_i = B(G_i^† P_i)``, ``x = (G, P)``
    (:func:`~lieflow.schemes.conjugation.lifted_update`); ``Wi``, ``Bi``, ``P``, ``U``
    scratch."""
    n = W.shape[0]
    for a in range(n):
        for c in range(n):
            U[a, c] = 0.0
    unitary = True
    for i in range(hb.shape[0]):
        _matmul_hn(x[0, i], x[1, i], Wi, P, gemm)
        _apply_B(B, params, Wi, Bi)
        if not skew:  # (a constant, see _reduced_step_of)
            unitary = unitary and _skew_to_roundoff(Bi)
        _matmul_nh(Bi, x[0, i], P, Wi, gemm)
        for a in range(n):
            for c in range(n):
                U[a, c] += hb[i] * P[a, c]
    if skew:
        return _conjugate_into_skew(W, U, unitary, Wi, Bi, P, gemm)
    return _conjugate_into_general(W, U, unitary, Wi, Bi, P, gemm)
